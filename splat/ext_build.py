"""Build or load one of the project's compiled extensions (C++ CPU, CUDA) from its cache folder.

The folder is ``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash>, the hash
covering the sources, headers, flags, the torch version, the Python extension ABI and whatever ``tag``
adds (CUDA version, GPU architecture). So a folder holding a finished build (its ``<name>.so`` and the
``built.ok`` marker written after the build loaded) is valid by construction and is imported
directly, without ``torch.utils.cpp_extension.load``: ninja would otherwise rebuild a cache copied to
another machine or checkout (its log records the outputs' old times, older than the copied sources).

Builds are serialised by an advisory ``flock`` on ``<folder>/build.flock``, which the kernel releases
when its holder dies: a process that finds another one building says so and waits, then imports the
finished build; a build killed half-way leaves no lock that blocks the next run (torch's own ``lock``
file, which it would wait on for ever, is removed by whoever holds the flock: no other build can be
running then).
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import sysconfig
import time
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import torch

log = logging.getLogger(__name__)

MARKER = "built.ok"


def cache_dir(name: str, sources: tuple[Path, ...], tag: list[str]) -> Path:
    """The build folder of extension ``name``: a hash of ``tag`` (flags, versions), the Python
    extension suffix (interpreter ABI) and every file."""
    root = os.environ.get("INDOORGS_CACHE")
    base = Path(root) if root else Path(__file__).resolve().parents[1] / ".cache"
    digest = hashlib.sha1(" ".join([*tag, str(sysconfig.get_config_var("EXT_SUFFIX"))]).encode())
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


@contextmanager
def build_lock(out_dir: Path):
    """Hold the exclusive build lock of ``out_dir`` (waiting, with a message, while another process
    builds there); on systems without ``fcntl`` nothing is locked."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no serialisation beyond torch's own lock file
        yield
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / "build.flock", "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.warning("another process is building in %s; waiting for it", out_dir)
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _finished(name: str, out_dir: Path) -> ModuleType | None:
    """The finished build in ``out_dir`` imported, or None (none there, or it does not import: then its
    outputs are removed so that ninja builds them again)."""
    so = out_dir / f"{name}.so"
    if not ((out_dir / MARKER).is_file() and so.is_file()):
        return None
    try:
        return _import_so(name, so)
    except ImportError as exc:  # e.g. a cache copied from an incompatible machine
        log.warning("could not import the cached build %s (%s); building again", so, exc)
        for stale in (out_dir / MARKER, so, out_dir / ".ninja_log"):
            stale.unlink(missing_ok=True)
        return None


def compiler_error(exc: Exception, width: int = 200) -> str:
    """The compiler's first error line in a failed build's message (ninja's first line is the whole
    command), else the message's first line; at most ``width`` characters."""
    lines = str(exc).splitlines()
    found = [ln.strip() for ln in lines if "error:" in ln.lower() and "error building extension" not in ln.lower()]
    text = found[0] if found else (lines[0] if lines else type(exc).__name__)
    return text if len(text) <= width else text[:width - 3] + "..."


@contextmanager
def _quoted_torch_lib_path():
    """torch writes ``-L{TORCH_LIB_PATH}`` into ninja's link line unquoted (its compile flags it
    quotes): a checkout under a folder with a space (``~/My Projects``, the venv inside it) failed to
    link (``ld: cannot find dir/main/.venv/...``). Within the block the path is shell-quoted, as ninja
    runs the line through the shell; restored after."""
    import shlex

    import torch.utils.cpp_extension as cpp

    lib = cpp.TORCH_LIB_PATH
    if lib == shlex.quote(lib):
        yield
        return
    cpp.TORCH_LIB_PATH = shlex.quote(lib)
    try:
        yield
    finally:
        cpp.TORCH_LIB_PATH = lib


def build_or_load(name: str, sources: tuple[Path, ...], out_dir: Path, what: str, *, cflags: list[str],
                  cuda_cflags: list[str] | None = None, ldflags: list[str] | None = None) -> ModuleType:
    """Import the finished build in ``out_dir`` or compile ``sources`` there with torch's JIT loader.

    ``what`` names the kernels in the one message a first build logs. Raises ImportError (with the
    compiler's message) when the build fails; the marker is written only after the build imported.
    """
    missing = [str(p) for p in sources if not p.is_file()]
    if missing:
        raise ImportError(f"{what} sources not found: {missing}")
    module = _finished(name, out_dir)
    if module is not None:
        return module
    from torch.utils.cpp_extension import load

    with build_lock(out_dir):
        module = _finished(name, out_dir)  # built by the process this one waited for
        if module is not None:
            return module
        (out_dir / "lock").unlink(missing_ok=True)  # torch's baton: stale, no other build can hold it now
        t0 = time.perf_counter()
        log.info("building the %s (first run only, about 1-2 min) in %s", what, out_dir)
        try:
            with _quoted_torch_lib_path():
                module = load(name=name, sources=[str(p) for p in sources], extra_cflags=cflags,
                              extra_cuda_cflags=cuda_cflags, extra_ldflags=ldflags, build_directory=str(out_dir),
                              verbose=False)
        except Exception as exc:  # noqa: BLE001 - ninja/compiler errors come as RuntimeError/OSError/...
            raise ImportError(f"building {name} in {out_dir} failed: {exc}") from exc
        (out_dir / MARKER).write_text(f"{torch.__version__}\n")
    log.debug("%s ready in %.1f s (%s)", name, time.perf_counter() - t0, out_dir)
    return module
