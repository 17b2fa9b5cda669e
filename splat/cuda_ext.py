"""The CUDA rasterizer extension: built on first import into the project's cache (CUDA machines only).

One extension (``indoorgs_cuda``) holds the tile-based compositing kernels
(``csrc/composite_cuda.cu``, used by :mod:`splat.composite_cuda`) and the fused projection
(``csrc/project_cuda.cu``, used by :mod:`splat.project_cuda`). Importing this module compiles it
with ``torch.utils.cpp_extension.load`` (nvcc and ninja needed) into
``<repo>/.cache/torch_extensions/indoorgs_cuda/<hash>`` (or ``$INDOORGS_CACHE/torch_extensions/...``),
where the hash covers the sources and headers, the compiler flags, the torch and CUDA versions and
the GPU's compute capability (torch builds for the GPU it sees); later imports reuse that build.
Without a CUDA device, or if the build fails, the import raises ImportError (with the compiler's
message) and :mod:`splat.composite` falls back to torch with a warning. :mod:`splat.composite` only
imports this module when ``torch.cuda.is_available()``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from pathlib import Path

import torch

log = logging.getLogger(__name__)

EXT_NAME = "indoorgs_cuda"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "composite_cuda.cu", CSRC / "project_cuda.cu", CSRC / "bindings_cuda.cpp")
HEADERS = (CSRC / "composite_cuda.h",)
# No --use_fast_math: its __expf and flushed denormals would move alphas near the 1/255 and 1e-4
# thresholds off the other backends' decisions; the kernel rounds the alpha arithmetic per
# operation itself (__fmul_rn), so the default FMA contraction elsewhere is harmless.
CUDA_FLAGS = ["-O3"]
CFLAGS = ["-O3"]


def build_dir() -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags+GPU>."""
    root = os.environ.get("INDOORGS_CACHE")
    base = Path(root) if root else Path(__file__).resolve().parents[1] / ".cache"
    arch = torch.cuda.get_device_capability() if torch.cuda.is_available() else (0, 0)
    tag = CUDA_FLAGS + CFLAGS + [torch.__version__, str(torch.version.cuda), f"sm_{arch[0]}{arch[1]}"]
    digest = hashlib.sha1(" ".join(tag).encode())
    for path in (*SOURCES, *HEADERS):  # torch's own check does not cover the headers
        digest.update(path.read_bytes() if path.is_file() else b"")
    return base / "torch_extensions" / EXT_NAME / digest.hexdigest()[:12]


def _build():
    """Compile (or load the cached build of) the extension; ImportError on failure or without CUDA."""
    if not torch.cuda.is_available():
        raise ImportError("no CUDA device: the CUDA rasterizer kernels are not built")
    missing = [str(p) for p in SOURCES if not p.is_file()]
    if missing:
        raise ImportError(f"CUDA sources not found: {missing}")
    from torch.utils.cpp_extension import load

    out_dir = build_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if not any(out_dir.glob(f"{EXT_NAME}*.so")):
        log.info("building the CUDA rasterizer kernels (first run only, about 1.5 min) in %s", out_dir)
    try:
        module = load(name=EXT_NAME, sources=[str(p) for p in SOURCES], extra_cflags=CFLAGS,
                      extra_cuda_cflags=CUDA_FLAGS, build_directory=str(out_dir), verbose=False)
    except Exception as exc:  # noqa: BLE001 - ninja/nvcc errors come as RuntimeError/OSError/...
        raise ImportError(f"building {EXT_NAME} in {out_dir} failed: {exc}") from exc
    log.debug("CUDA rasterizer extension ready in %.1f s (%s)", time.perf_counter() - t0, out_dir)
    return module


ext = _build()
