"""The C++ CPU rasterizer extension: built on first import into the project's cache.

One extension (``indoorgs_cpu``) holds the compositing kernel (``csrc/composite_cpu.cpp``, used by
:mod:`splat.composite_cpu`), the fused projection (``csrc/project_cpu.cpp``, used by
:mod:`splat.project_cpu`) and the loss's fused SSIM (``csrc/losses_cpu.cpp``, used by :mod:`splat.losses_cpu`). Importing this module compiles it with ``torch.utils.cpp_extension.load``
into ``<repo>/.cache/torch_extensions/<name>/<hash>`` (or ``$INDOORGS_CACHE/torch_extensions/...``),
where the hash covers the sources and headers, the compiler flags, the torch version and the Python
ABI; later imports load that build directly (splat/ext_build.py). If the build fails, the import
raises ImportError carrying the compiler's message, and :mod:`splat.composite` falls back to torch
with a warning.

On x86-64 CPUs with AVX2 the compositing kernels are built a second time with ``-mavx2``
(``indoorgs_cpu_avx2``: 8 float lanes instead of 4) and :data:`composite_ext` is that build; elsewhere,
when ``INDOORGS_CPU_SIMD=baseline`` is set, or when that build fails (with a warning), it is ``ext``.
The baseline build never holds AVX2 code, so a cache moved to an older x86-64 machine stays valid.
"""

from __future__ import annotations

import logging
import os
import platform
from pathlib import Path

import torch

from splat.ext_build import build_or_load, cache_dir

log = logging.getLogger(__name__)

EXT_NAME = "indoorgs_cpu"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "composite_cpu.cpp", CSRC / "project_cpu.cpp", CSRC / "losses_cpu.cpp", CSRC / "bindings.cpp")
HEADERS = (CSRC / "composite_cpu.h", CSRC / "kernels.h")
# -ffp-contract=off: forward and backward must evaluate alpha bit-identically (same skip decisions).
# SSE4.2 (every x86-64 CPU since ~2009) gives inline floor/ceil; not -march=native, so that a cached
# build stays valid when the repository moves to another x86-64 machine.
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off"]
X86 = platform.machine().lower() in ("x86_64", "amd64")
if X86:
    CFLAGS.append("-msse4.2")
AVX2_EXT_NAME = "indoorgs_cpu_avx2"
AVX2_SOURCES = (CSRC / "composite_cpu.cpp", CSRC / "bindings_composite.cpp")
AVX2_CFLAGS = [*CFLAGS, "-mavx2"]  # no -mfma: -ffp-contract=off keeps every lane's arithmetic as in the baseline


def build_dir() -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags>."""
    return cache_dir(EXT_NAME, (*SOURCES, *HEADERS), CFLAGS + [torch.__version__])


def avx2_build_dir() -> Path:
    """Cache folder of the AVX2 compositing build (as :func:`build_dir`)."""
    return cache_dir(AVX2_EXT_NAME, (*AVX2_SOURCES, *HEADERS), AVX2_CFLAGS + [torch.__version__])


def cpu_has_avx2() -> bool:
    """Whether this CPU runs AVX2 code (torch's dispatch capability: honours ``ATEN_CPU_CAPABILITY``)."""
    return X86 and torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")


def _build():
    """Load the cached build or compile the extension; ImportError with the compiler output on failure."""
    return build_or_load(EXT_NAME, SOURCES, build_dir(), "C++ rasterizer kernels", cflags=CFLAGS,
                         ldflags=["-fopenmp"])


def _build_composite():
    """The compositing kernels to use: the AVX2 build where the CPU has AVX2 (see the module doc)."""
    choice = os.environ.get("INDOORGS_CPU_SIMD", "auto")
    if choice not in ("auto", "baseline"):
        log.warning("INDOORGS_CPU_SIMD=%r is not 'auto' or 'baseline'; using 'auto'", choice)
    if choice == "baseline" or not cpu_has_avx2():
        return ext
    try:
        return build_or_load(AVX2_EXT_NAME, AVX2_SOURCES, avx2_build_dir(), "C++ compositing kernels for AVX2",
                             cflags=AVX2_CFLAGS, ldflags=["-fopenmp"])
    except ImportError as exc:
        log.warning("the AVX2 build of the compositing kernels failed (%s); using the 4-lane build", exc)
        return ext


ext = _build()
composite_ext = _build_composite()
#: lanes of the float compositing loops in the build in use
COMPOSITE_LANES = 8 if composite_ext is not ext else 4
