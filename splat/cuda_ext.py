"""The CUDA extension: built on first import into the project's cache (CUDA machines only).

One extension (``indoorgs_cuda``) holds the tile-based compositing kernels
(``csrc/composite_cuda.cu``, used by :mod:`splat.composite_cuda`), the fused projection
(``csrc/project_cuda.cu``, used by :mod:`splat.project_cuda`) and the fused loss terms
(``csrc/losses_cuda.cu``, used by :mod:`splat.losses_cuda`). Importing this module compiles it
with ``torch.utils.cpp_extension.load`` (nvcc and ninja needed) into
``<repo>/.cache/torch_extensions/indoorgs_cuda/<hash>`` (or ``$INDOORGS_CACHE/torch_extensions/...``),
where the hash covers the sources and headers, the compiler flags, the torch and CUDA versions and
the GPU's compute capability (torch builds for the GPU it sees) and the Python ABI; later imports
load that build directly (splat/ext_build.py).
Without a CUDA device, or if the build fails, the import raises ImportError (with the compiler's
message) and :mod:`splat.composite` falls back to torch with a warning. :mod:`splat.composite` only
imports this module when ``torch.cuda.is_available()``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from splat.ext_build import build_or_load, cache_dir

EXT_NAME = "indoorgs_cuda"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "composite_cuda.cu", CSRC / "project_cuda.cu", CSRC / "losses_cuda.cu",
           CSRC / "bindings_cuda.cpp")
HEADERS = (CSRC / "composite_cuda.h",)
# No --use_fast_math: its __expf and flushed denormals would move alphas near the 1/255 and 1e-4
# thresholds off the other backends' decisions; the kernel rounds the alpha arithmetic per
# operation itself (__fmul_rn), so the default FMA contraction elsewhere is harmless.
CUDA_FLAGS = ["-O3"]
CFLAGS = ["-O3"]


def build_dir() -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags+GPU>."""
    arch = torch.cuda.get_device_capability() if torch.cuda.is_available() else (0, 0)
    tag = CUDA_FLAGS + CFLAGS + [torch.__version__, str(torch.version.cuda), f"sm_{arch[0]}{arch[1]}"]
    return cache_dir(EXT_NAME, (*SOURCES, *HEADERS), tag)


def _build():
    """Load the cached build or compile the extension; ImportError on failure or without CUDA."""
    if not torch.cuda.is_available():
        raise ImportError("no CUDA device: the CUDA rasterizer kernels are not built")
    return build_or_load(EXT_NAME, SOURCES, build_dir(), "CUDA kernels", cflags=CFLAGS,
                         cuda_cflags=CUDA_FLAGS)


ext = _build()
