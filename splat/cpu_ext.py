"""The C++ CPU rasterizer extension: built on first import into the project's cache.

One extension (``indoorgs_cpu``) holds the compositing kernel (``csrc/composite_cpu.cpp``, used by
:mod:`splat.composite_cpu`), the fused projection (``csrc/project_cpu.cpp``, used by
:mod:`splat.project_cpu`), render's per-pixel maps (``csrc/maps_cpu.cpp``, :mod:`splat.maps_cpu`) and
the loss's fused SSIM, L_n and L_nc (``csrc/losses_cpu.cpp``, used by :mod:`splat.losses_cpu`). Importing this module compiles it with ``torch.utils.cpp_extension.load``
into ``<repo>/.cache/torch_extensions/<name>/<hash>`` (or ``$INDOORGS_CACHE/torch_extensions/...``),
where the hash covers the sources and headers, the compiler flags, the torch version and the Python
ABI; later imports load that build directly (splat/ext_build.py). If the build fails, the import
raises ImportError carrying the compiler's message, and :mod:`splat.composite` falls back to torch
with a warning.

On x86-64 CPUs with AVX2 the extension is built with ``-mavx2`` (``indoorgs_cpu_avx2``: the
compositing loops take 8 float lanes instead of 4, the compiler's vector loops of the SSIM twice the
width); elsewhere, with ``INDOORGS_CPU_SIMD=baseline``, or when that build fails (with a warning),
the baseline build (``indoorgs_cpu``, SSE4.2) is used. Each build has its own cache folder, so a
cache moved to an older x86-64 machine stays valid. :func:`baseline_ext` gives the baseline build
in any case (tests compare the two).
"""

from __future__ import annotations

import functools
import logging
import os
import platform
from pathlib import Path
from types import ModuleType

import torch

from splat.ext_build import build_or_load, cache_dir

log = logging.getLogger(__name__)

EXT_NAME = "indoorgs_cpu"
AVX2_EXT_NAME = "indoorgs_cpu_avx2"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "composite_cpu.cpp", CSRC / "project_cpu.cpp", CSRC / "losses_cpu.cpp", CSRC / "maps_cpu.cpp",
           CSRC / "bindings.cpp")
HEADERS = (CSRC / "composite_cpu.h", CSRC / "kernels.h")
# -ffp-contract=off: forward and backward must evaluate alpha bit-identically (same skip decisions).
# SSE4.2 (every x86-64 CPU since ~2009) gives inline floor/ceil; not -march=native, so that a cached
# build stays valid when the repository moves to another x86-64 machine.
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off"]
X86 = platform.machine().lower() in ("x86_64", "amd64")
if X86:
    CFLAGS.append("-msse4.2")
# no -mfma: with -ffp-contract=off every lane's arithmetic stays that of the baseline build
AVX2_CFLAGS = [*CFLAGS, "-mavx2"]


def cpu_has_avx2() -> bool:
    """Whether this CPU runs AVX2 code (torch's dispatch capability: honours ``ATEN_CPU_CAPABILITY``)."""
    return X86 and torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")


def selected_simd() -> str:
    """"avx2" where the CPU has it and ``INDOORGS_CPU_SIMD`` is not "baseline", else "baseline"."""
    choice = os.environ.get("INDOORGS_CPU_SIMD", "auto")
    if choice not in ("auto", "baseline"):
        log.warning("INDOORGS_CPU_SIMD=%r is not 'auto' or 'baseline'; using 'auto'", choice)
    return "avx2" if choice != "baseline" and cpu_has_avx2() else "baseline"


def ext_name(simd: str | None = None) -> str:
    """The extension's name for a build ("avx2" or "baseline"; default: the one this machine uses)."""
    return AVX2_EXT_NAME if (simd or selected_simd()) == "avx2" else EXT_NAME


def build_dir(simd: str | None = None) -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags>."""
    flags = AVX2_CFLAGS if ext_name(simd) == AVX2_EXT_NAME else CFLAGS
    return cache_dir(ext_name(simd), (*SOURCES, *HEADERS), flags + [torch.__version__])


def _build(simd: str | None = None) -> ModuleType:
    """Load the cached build or compile the extension; ImportError with the compiler output on failure."""
    avx2 = ext_name(simd) == AVX2_EXT_NAME
    return build_or_load(ext_name(simd), SOURCES, build_dir(simd),
                         "C++ rasterizer kernels" + (" for AVX2" if avx2 else ""),
                         cflags=AVX2_CFLAGS if avx2 else CFLAGS, ldflags=["-fopenmp"])


def _build_selected() -> tuple[ModuleType, str]:
    simd = selected_simd()
    if simd == "avx2":
        try:
            return _build("avx2"), "avx2"
        except ImportError as exc:
            log.warning("the AVX2 build of the C++ kernels failed (%s); using the baseline build",
                        str(exc).splitlines()[0])
    return _build("baseline"), "baseline"


@functools.cache
def baseline_ext() -> ModuleType:
    """The baseline (SSE4.2, 4 float lanes) build: :data:`ext` itself, or built on first call."""
    return ext if SIMD == "baseline" else _build("baseline")


ext, SIMD = _build_selected()
#: lanes of the float compositing loops in the build in use
COMPOSITE_LANES = 8 if SIMD == "avx2" else 4
