"""splat/ext_build.py: a finished build in the cache is imported as it is (no ninja, so a cache copied
to another checkout or machine is not rebuilt), and a build killed half-way leaves no lock that
makes the next run wait for ever."""

from __future__ import annotations

import logging
import os
import shutil
import time

import pytest

from splat import ext_build


def test_a_finished_build_is_imported_without_the_jit_loader(tmp_path, monkeypatch):
    pytest.importorskip("splat.cpu_ext", reason="the C++ CPU extension does not build here")
    from splat import cpu_ext

    src = cpu_ext.build_dir()
    monkeypatch.setenv("INDOORGS_CACHE", str(tmp_path / "cache"))
    dst = cpu_ext.build_dir()
    assert dst.parent == tmp_path / "cache" / "torch_extensions" / cpu_ext.EXT_NAME and dst.name == src.name
    shutil.copytree(src, dst)
    # a copied cache: every file newer than its log says, as on another machine (ninja would rebuild)
    future = time.time() + 3600
    for p in dst.iterdir():
        os.utime(p, (future, future))

    def no_jit(*args, **kw):
        raise AssertionError("torch.utils.cpp_extension.load called for a finished build")

    imported = []
    real_import = ext_build._import_so
    monkeypatch.setattr("torch.utils.cpp_extension.load", no_jit)
    monkeypatch.setattr(ext_build, "_import_so", lambda name, so: imported.append(so) or real_import(name, so))
    module = cpu_ext._build()
    assert imported == [dst / f"{cpu_ext.EXT_NAME}.so"]
    assert hasattr(module, "forward") and hasattr(module, "project_forward")

    (dst / ext_build.MARKER).unlink()  # not marked finished: the JIT loader is asked
    with pytest.raises(ImportError, match="finished build"):
        cpu_ext._build()


def test_a_stale_lock_is_removed_and_a_fresh_one_is_waited_on(tmp_path, caplog):
    lock = tmp_path / "lock"
    lock.write_text("")
    with caplog.at_level(logging.INFO, logger="splat.ext_build"):
        ext_build.clear_stale_lock(tmp_path)
    assert lock.exists() and "waiting" in caplog.text  # a build may be running: say so, keep it
    old = time.time() - ext_build.STALE_LOCK_S - 60
    os.utime(lock, (old, old))
    with caplog.at_level(logging.WARNING, logger="splat.ext_build"):
        ext_build.clear_stale_lock(tmp_path)
    assert not lock.exists() and "did not finish" in caplog.text
    ext_build.clear_stale_lock(tmp_path)  # no lock: nothing to do


def test_missing_sources_are_an_import_error(tmp_path):
    with pytest.raises(ImportError, match="sources not found"):
        ext_build.build_or_load("nothing", (tmp_path / "absent.cpp",), tmp_path / "b", "test kernels", cflags=[])
