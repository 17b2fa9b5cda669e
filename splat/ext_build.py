"""Build or load one of the project's compiled extensions (C++ CPU, CUDA) from its cache folder.

The folder is ``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash>, the hash
covering the sources, headers, flags, the torch version and whatever ``tag`` adds (CUDA version, GPU
architecture). So a folder holding a finished build (its ``<name>.so`` and the ``built.ok`` marker
written after the build loaded) is valid by construction and is imported directly, without
``torch.utils.cpp_extension.load``: ninja would otherwise rebuild a cache copied to another machine or
checkout (its log records the outputs' old times, older than the copied sources), and wait forever on
the ``lock`` file of a build that was killed. Before building, a ``lock`` older than
``STALE_LOCK_S`` (no build takes that long) is removed with a warning; a younger one is waited on
with a message naming it.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import time
from pathlib import Path
from types import ModuleType

import torch

log = logging.getLogger(__name__)

STALE_LOCK_S = 20 * 60.0
MARKER = "built.ok"


def cache_dir(name: str, sources: tuple[Path, ...], tag: list[str]) -> Path:
    """The build folder of extension ``name``: a hash of ``tag`` (flags, versions) and every file."""
    root = os.environ.get("INDOORGS_CACHE")
    base = Path(root) if root else Path(__file__).resolve().parents[1] / ".cache"
    digest = hashlib.sha1(" ".join(tag).encode())
    for path in sources:  # torch's own check does not cover the headers
        digest.update(path.read_bytes() if path.is_file() else b"")
    return base / "torch_extensions" / name / digest.hexdigest()[:12]


def _import_so(name: str, so: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, so)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import {so}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def clear_stale_lock(out_dir: Path, stale_s: float = STALE_LOCK_S) -> None:
    """Remove ``out_dir/lock`` left by a killed build (older than ``stale_s``); say so if one is younger."""
    lock = out_dir / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return
    if age > stale_s:
        log.warning("removing the lock file %s left %.0f min ago by a build that did not finish", lock, age / 60)
        lock.unlink(missing_ok=True)
    else:
        log.info("another process is building in %s (its lock file is %.0f s old); waiting for it "
                 "(delete the file if no build is running)", out_dir, age)


def build_or_load(name: str, sources: tuple[Path, ...], out_dir: Path, what: str, *, cflags: list[str],
                  cuda_cflags: list[str] | None = None, ldflags: list[str] | None = None) -> ModuleType:
    """Import the finished build in ``out_dir`` or compile ``sources`` there with torch's JIT loader.

    ``what`` names the kernels in the one message a first build logs. Raises ImportError (with the
    compiler's message) when the build fails.
    """
    missing = [str(p) for p in sources if not p.is_file()]
    if missing:
        raise ImportError(f"{what} sources not found: {missing}")
    so = out_dir / f"{name}.so"
    if (out_dir / MARKER).is_file() and so.is_file():
        try:
            return _import_so(name, so)
        except ImportError as exc:  # e.g. a cache copied from an incompatible machine: build again
            log.warning("could not import the cached build %s (%s); building again", so, exc)
            (out_dir / MARKER).unlink(missing_ok=True)
    from torch.utils.cpp_extension import load

    out_dir.mkdir(parents=True, exist_ok=True)
    clear_stale_lock(out_dir)
    t0 = time.perf_counter()
    log.info("building the %s (first run only, about 1-2 min) in %s", what, out_dir)
    try:
        module = load(name=name, sources=[str(p) for p in sources], extra_cflags=cflags,
                      extra_cuda_cflags=cuda_cflags, extra_ldflags=ldflags, build_directory=str(out_dir),
                      verbose=False)
    except Exception as exc:  # noqa: BLE001 - ninja/compiler errors come as RuntimeError/OSError/...
        raise ImportError(f"building {name} in {out_dir} failed: {exc}") from exc
    (out_dir / MARKER).write_text(f"{torch.__version__}\n")
    log.debug("%s ready in %.1f s (%s)", name, time.perf_counter() - t0, out_dir)
    return module
