"""Atomic writes: build a file or a folder under a temporary sibling name, then rename it into place.

An interrupted stage leaves either the old result or none, never a half-written one.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync(path: Path, folder: bool = False) -> None:
    """fsync a file (opened for writing: Windows refuses fsync on a read-only one) or, on POSIX, a folder
    (some FUSE and SMB mounts refuse that: the rename is then as durable as the mount makes it)."""
    if folder and os.name != "posix":
        return
    fd = os.open(path, os.O_RDONLY if folder else os.O_RDWR)
    try:
        os.fsync(fd)
    except OSError:
        if not folder:
            raise
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path, durable: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling of ``path``; on success rename it onto ``path`` (atomic on POSIX),
    on error remove it. The temp name keeps the suffix so writers that append one (np.savez) agree.
    ``durable``: the file's data reach the disk before the rename, and the rename after it (fsync of
    the file and its folder), so a power cut leaves the old file or the new one, not an empty one (a
    training checkpoint: hours of work; the many cache files are not worth the wait)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if tmp.exists():  # mkstemp makes 0600: give the result the user's umask, as open() would
            os.chmod(tmp, 0o666 & ~_umask())
            if durable:
                _fsync(tmp)
        os.replace(tmp, path)
        if durable:
            _fsync(path.parent, folder=True)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def output_lock(out_dir: str | Path, command: str) -> Iterator[None]:
    """Within the block this process alone writes ``out_dir``: an exclusive flock on a hidden sibling
    ``.OUT.lock`` (removed after; the kernel releases it however the process ends). Another process
    holding it: ValueError naming ``command`` (two runs into one OUT removed or published each other's
    work). Where the platform or file system has no flock nothing is locked."""
    out_dir = Path(out_dir)
    try:
        import fcntl
    except ImportError:  # Windows
        yield
        return
    lock = out_dir.absolute().with_name(f".{out_dir.name}.lock")
    made = [p for p in (lock.parent, *lock.parent.parents) if not p.exists()]  # deepest first
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666 & ~_umask())
    except OSError:  # no folder to lock in (a file on the path, read-only): the command's own checks say so
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"another {command} is writing {out_dir} now (it holds {lock}); wait for it to "
                             "end, or write elsewhere") from None
        except OSError:  # a file system without locks: as before
            yield
            return
        try:
            yield
        finally:
            lock.unlink(missing_ok=True)
    finally:
        os.close(fd)
        for folder in made:  # the folders made for the lock, left empty by a command that failed
            try:
                folder.rmdir()
            except OSError:
                break


def locks_output(command: str, arg: str = "out_dir") -> Callable:
    """Decorator: the function runs holding :func:`output_lock` on its argument ``arg`` (the command's
    OUT)."""
    def wrap(fn: Callable) -> Callable:
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def locked(*args, **kwargs):
            with output_lock(signature.bind(*args, **kwargs).arguments[arg], command):
                return fn(*args, **kwargs)
        return locked
    return wrap


@contextlib.contextmanager
def atomic_dir(final: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling folder of ``final``; on success it replaces ``final`` (an existing
    one is moved aside first and removed after), on error it is removed."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    replace_dir(tmp, final)


def replace_dir(src: str | Path, final: str | Path) -> Path:
    """Rename the finished folder ``src`` onto ``final``; an existing ``final`` is moved aside
    first and removed after, so ``final`` holds one complete result at every moment but the two
    renames."""
    src, final = Path(src), Path(final)
    if final.exists():
        backup = final.with_name(f".{final.name}.old")
        shutil.rmtree(backup, ignore_errors=True)
        os.replace(final, backup)
        os.replace(src, final)
        shutil.rmtree(backup, ignore_errors=True)
    else:
        os.replace(src, final)
    return final


def check_output_dir(path: str | Path) -> Path:
    """Fail early, before any work, when the output folder ``path`` cannot be written: it is a file,
    or the folder (or, where it does not exist yet, its nearest existing parent, where the staging
    sibling is made) refuses a new file (permissions, a read-only file system). The check writes and
    removes a probe file, so it holds for root without CAP_DAC_OVERRIDE and for ACLs as well."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"the output path {path} is a file, not a folder")
    probes = [path] if path.is_dir() else []
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"cannot make the output folder {path}: {parent} is a file, not a folder")
    probes.append(parent)
    for folder in probes:
        try:
            fd, probe = tempfile.mkstemp(prefix=".write-probe.", dir=folder)
        except OSError as exc:
            why = exc.strerror.lower() if exc.strerror else type(exc).__name__
            raise PermissionError(f"cannot write the output folder {path}: {folder} is not writable "
                                  f"({why})") from exc
        os.close(fd)
        os.unlink(probe)
    return path


def check_not_input(path: str | Path, inputs: dict[str, str | Path | None]) -> None:
    """Refuse the output folder ``path`` when it is, or holds, one of the command's inputs
    (``inputs``: what it is called -> its path; None skipped): a command that replaces or fills its
    output folder would delete or mix into it (`splat train SCENE -o SCENE --overwrite` removed the
    scene). An output inside an input (``-o SCENE/cues``) is fine, but not inside its photos
    (``SCENE/images/...``). What an input folder links to (a
    derived scene's images/ and priors/ are links to its source's) counts as the input too."""
    out = Path(path).resolve()
    for name, given in inputs.items():
        if given is None:
            continue
        given = Path(given)
        linked = [c for c in given.iterdir() if c.is_symlink()] if given.is_dir() and not given.is_symlink() else []
        for src, what in [(given.resolve(), f"the {name} ({given})")] + [
                (c.resolve(), f"what the {name}'s {c.name} links to ({c.resolve()})") for c in linked]:
            if src == out or out in src.parents:
                raise ValueError(f"the output folder {path} {'is' if src == out else 'holds'} {what}: "
                                 f"writing there would replace it; choose another output folder")
        photos = (given / "images").resolve()
        if given.is_dir() and photos in out.parents:  # its files would be taken for photos or mixed with them
            raise ValueError(f"the output folder {path} is inside the {name}'s photos folder {given / 'images'}; "
                             "choose another output folder")


JUNK = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})  # what file browsers leave in any folder


def _json_has(path: Path, key: str) -> bool:
    """Whether the JSON file ``path`` holds the dotted ``key`` (``"priors.simulated"``)."""
    import json

    try:
        node = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def check_replaceable(path: str | Path, marker: str, what: str,
                      inputs: dict[str, str | Path | None] | None = None, key: str | None = None) -> None:
    """For a command that replaces its output folder whole: refuse, whatever ``--overwrite`` says, a
    folder that is or holds an input (:func:`check_not_input`) and a non-empty folder without
    ``marker``, the file every earlier output of the command holds and no other command writes (with
    ``key``: a JSON file holding that dotted key; ``what`` names such an output): it is someone
    else's folder, and replacing it would delete what it holds. Only file browsers' litter
    (:data:`JUNK`) does not count: a folder holding just ``.git`` is someone's too."""
    check_not_input(path, inputs or {})
    path = Path(path)
    ours = (path / marker).exists() and (key is None or _json_has(path / marker, key))
    if path.is_dir() and not ours:
        others = sorted(e.name for e in path.iterdir() if e.name not in JUNK)
        if others:
            shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
            raise ValueError(f"{path} is not {what} (no {marker}{f' with {key!r}' if key else ''}) but holds {len(others)} "
                             f"entr{'y' if len(others) == 1 else 'ies'} ({shown}); the output folder is "
                             f"replaced whole, so choose a new or empty folder")


def check_output_file(path: str | Path, overwrite: bool = False) -> Path:
    """Fail early, before any work, when the output file ``path`` cannot be written: it is a folder,
    it exists and ``overwrite`` is off (a finished output is replaced only when asked), or its folder
    refuses a new file (:func:`check_output_dir`). Write it with :func:`atomic_path`."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"the output path {path} is a folder, not a file")
    if path.exists() and not overwrite:
        raise ValueError(f"{path} exists; pass --overwrite to replace it")
    check_output_dir(path.parent)
    return path
