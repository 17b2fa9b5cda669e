"""The C++ CPU rasterizer extension: built on first import into the project's cache.

One extension (``indoorgs_cpu``) holds the compositing kernel (``csrc/composite_cpu.cpp``, used by
:mod:`splat.composite_cpu`), the fused projection (``csrc/project_cpu.cpp``, used by
:mod:`splat.project_cpu`) and the loss's fused SSIM (``csrc/losses_cpu.cpp``, used by :mod:`splat.losses_cpu`). Importing this module compiles it with ``torch.utils.cpp_extension.load``
into ``<repo>/.cache/torch_extensions/<name>/<hash>`` (or ``$INDOORGS_CACHE/torch_extensions/...``),
where the hash covers the sources and headers, the compiler flags, the torch version and the Python
ABI; later imports load that build directly (splat/ext_build.py). If the build fails, the import
raises ImportError carrying the compiler's message, and :mod:`splat.composite` falls back to torch
with a warning.
"""

from __future__ import annotations

import platform
from pathlib import Path

import torch

from splat.ext_build import build_or_load, cache_dir

EXT_NAME = "indoorgs_cpu"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "composite_cpu.cpp", CSRC / "project_cpu.cpp", CSRC / "losses_cpu.cpp", CSRC / "bindings.cpp")
HEADERS = (CSRC / "composite_cpu.h", CSRC / "kernels.h")
# -ffp-contract=off: forward and backward must evaluate alpha bit-identically (same skip decisions).
# SSE4.2 (every x86-64 CPU since ~2009) gives inline floor/ceil; not -march=native, so that a cached
# build stays valid when the repository moves to another x86-64 machine.
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off"]
if platform.machine().lower() in ("x86_64", "amd64"):
    CFLAGS.append("-msse4.2")


def build_dir() -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags>."""
    return cache_dir(EXT_NAME, (*SOURCES, *HEADERS), CFLAGS + [torch.__version__])


def _build():
    """Load the cached build or compile the extension; ImportError with the compiler output on failure."""
    return build_or_load(EXT_NAME, SOURCES, build_dir(), "C++ rasterizer kernels", cflags=CFLAGS,
                         ldflags=["-fopenmp"])


ext = _build()
