"""The C++ CPU rasterizer extension: built on first import into the project's cache.

One extension (``indoorgs_cpu``) holds the compositing kernel (``csrc/composite_cpu.cpp``, used by
:mod:`splat.composite_cpu`) and the fused projection (``csrc/project_cpu.cpp``, used by
:mod:`splat.project_cpu`). Importing this module compiles it with ``torch.utils.cpp_extension.load``
into ``<repo>/.cache/torch_extensions/<name>/<hash>`` (or ``$INDOORGS_CACHE/torch_extensions/...``),
where the hash covers the sources and headers, the compiler flags and the torch version; later
imports reuse that build (about 0.5 s). If the build fails, the import raises ImportError carrying
the compiler's message, and :mod:`splat.composite` falls back to torch with a warning.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import time
from pathlib import Path

import torch

log = logging.getLogger(__name__)

EXT_NAME = "indoorgs_cpu"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "composite_cpu.cpp", CSRC / "project_cpu.cpp", CSRC / "bindings.cpp")
HEADERS = (CSRC / "composite_cpu.h", CSRC / "kernels.h")
# -ffp-contract=off: forward and backward must evaluate alpha bit-identically (same skip decisions).
# SSE4.2 (every x86-64 CPU since ~2009) gives inline floor/ceil; not -march=native, so that a cached
# build stays valid when the repository moves to another x86-64 machine.
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off"]
if platform.machine().lower() in ("x86_64", "amd64"):
    CFLAGS.append("-msse4.2")


def build_dir() -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags>."""
    root = os.environ.get("INDOORGS_CACHE")
    base = Path(root) if root else Path(__file__).resolve().parents[1] / ".cache"
    digest = hashlib.sha1(" ".join(CFLAGS + [torch.__version__]).encode())
    for path in (*SOURCES, *HEADERS):  # torch's own check does not cover the headers
        digest.update(path.read_bytes() if path.is_file() else b"")
    return base / "torch_extensions" / EXT_NAME / digest.hexdigest()[:12]


def _build():
    """Compile (or load the cached build of) the extension; ImportError with the compiler output on failure."""
    missing = [str(p) for p in SOURCES if not p.is_file()]
    if missing:
        raise ImportError(f"C++ sources not found: {missing}")
    from torch.utils.cpp_extension import load

    out_dir = build_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if not any(out_dir.glob(f"{EXT_NAME}*.so")):
        log.info("building the C++ rasterizer kernels (first run only, about 1 min on 2 cores) in %s", out_dir)
    try:
        module = load(name=EXT_NAME, sources=[str(p) for p in SOURCES], extra_cflags=CFLAGS,
                      extra_ldflags=["-fopenmp"], build_directory=str(out_dir), verbose=False)
    except Exception as exc:  # noqa: BLE001 - ninja/compiler errors come as RuntimeError/OSError/...
        raise ImportError(f"building {EXT_NAME} in {out_dir} failed: {exc}") from exc
    log.debug("C++ rasterizer extension ready in %.1f s (%s)", time.perf_counter() - t0, out_dir)
    return module


ext = _build()
