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

The kernels' threads are OpenMP's. A compiler without it (Apple's clang has no ``-fopenmp``), or
``INDOORGS_CPU_OPENMP=0``, gets the same kernels built for one thread (``indoorgs_cpu_serial``,
``csrc/omp_compat.h``; a warning says so) instead of the torch backend, 6-10x slower than it on
2 cores (docs/rasterizer.md).
"""

from __future__ import annotations

import functools
import logging
import os
import platform
from pathlib import Path
from types import ModuleType

import torch

from splat.ext_build import build_or_load, cache_dir, compiler_error

log = logging.getLogger(__name__)

EXT_NAME = "indoorgs_cpu"
AVX2_EXT_NAME = "indoorgs_cpu_avx2"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "composite_cpu.cpp", CSRC / "project_cpu.cpp", CSRC / "losses_cpu.cpp", CSRC / "maps_cpu.cpp",
           CSRC / "bindings.cpp")
HEADERS = (CSRC / "composite_cpu.h", CSRC / "kernels.h", CSRC / "omp_compat.h")
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


def openmp_wanted() -> bool:
    """False when ``INDOORGS_CPU_OPENMP=0`` asks for the one-thread build."""
    return os.environ.get("INDOORGS_CPU_OPENMP", "1") != "0"


def ext_name(simd: str | None = None, openmp: bool = True) -> str:
    """The extension's name for a build ("avx2" or "baseline"; default: the one this machine uses),
    with OpenMP threads or (``openmp=False``) for one thread."""
    name = AVX2_EXT_NAME if (simd or selected_simd()) == "avx2" else EXT_NAME
    return name if openmp else f"{name}_serial"


def build_flags(simd: str | None = None, openmp: bool = True) -> list[str]:
    """Compiler flags of a build: without OpenMP, no -fopenmp and its pragmas ignored quietly."""
    flags = AVX2_CFLAGS if ext_name(simd) == AVX2_EXT_NAME else CFLAGS
    return flags if openmp else [f for f in flags if f != "-fopenmp"] + ["-Wno-unknown-pragmas"]


def build_dir(simd: str | None = None, openmp: bool = True) -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags>."""
    return cache_dir(ext_name(simd, openmp), (*SOURCES, *HEADERS), build_flags(simd, openmp) + [torch.__version__])


def _build(simd: str | None = None, openmp: bool = True) -> ModuleType:
    """Load the cached build or compile the extension; ImportError with the compiler output on failure."""
    avx2 = ext_name(simd) == AVX2_EXT_NAME
    return build_or_load(ext_name(simd, openmp), SOURCES, build_dir(simd, openmp),
                         "C++ rasterizer kernels" + (" for AVX2" if avx2 else "") + ("" if openmp else " for one thread"),
                         cflags=build_flags(simd, openmp), ldflags=["-fopenmp"] if openmp else [])


def _build_selected() -> tuple[ModuleType, str, bool]:
    """The first build that compiles: this CPU's SIMD with OpenMP, the baseline with OpenMP, then the
    baseline for one thread; (module, simd, openmp). The last failure's ImportError if none does."""
    simd = selected_simd()
    threaded = ([(simd, True)] if simd == "avx2" else []) + [("baseline", True)]
    tries = (threaded if openmp_wanted() else []) + [("baseline", False)]
    errors = []
    for build_simd, openmp in tries:
        try:
            module = _build(build_simd, openmp)
            break
        except ImportError as exc:
            if (build_simd, openmp) == tries[-1]:
                raise
            errors.append(f"{ext_name(build_simd, openmp)} did not build ({compiler_error(exc)})")
    if errors:
        log.warning("using the %s build of the C++ kernels: %s", ext_name(build_simd, openmp), "; ".join(errors))
    if not openmp:
        log.warning("the C++ kernels run on one thread (built without OpenMP%s): training is about as many "
                    "times slower as there are cores; a compiler with OpenMP (gcc, or clang with libomp) "
                    "gives the threaded build", "" if openmp_wanted() else ": INDOORGS_CPU_OPENMP=0")
    return module, build_simd, openmp


@functools.cache
def baseline_ext() -> ModuleType:
    """The baseline (SSE4.2, 4 float lanes) build: :data:`ext` itself, or built on first call."""
    return ext if SIMD == "baseline" else _build("baseline")  # an AVX2 build is an OpenMP one


ext, SIMD, OPENMP = _build_selected()
#: lanes of the float compositing loops in the build in use
COMPOSITE_LANES = 8 if SIMD == "avx2" else 4
