"""splat/ext_build.py: a finished build in the cache is imported as it is (no ninja, so a cache copied
to another checkout or machine is not rebuilt), and a build killed half-way leaves no lock that
makes the next run wait for ever."""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
import types

import pytest

from splat import ext_build


def test_a_finished_build_is_imported_without_the_jit_loader(tmp_path, monkeypatch):
    pytest.importorskip("splat.cpu_ext", reason="the C++ CPU extension does not build here")
    from splat import cpu_ext

    src = cpu_ext.build_dir()
    monkeypatch.setenv("INDOORGS_CACHE", str(tmp_path / "cache"))
    dst = cpu_ext.build_dir()
    assert dst.parent == tmp_path / "cache" / "torch_extensions" / cpu_ext.ext_name() and dst.name == src.name
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
    assert imported == [dst / f"{cpu_ext.ext_name()}.so"]
    assert hasattr(module, "forward") and hasattr(module, "project_forward")

    (dst / ext_build.MARKER).unlink()  # not marked finished: the JIT loader is asked
    with pytest.raises(ImportError, match="finished build"):
        cpu_ext._build()


def _fake_build(tmp_path, monkeypatch, load):
    monkeypatch.setattr("torch.utils.cpp_extension.load", load)
    src = tmp_path / "k.cpp"
    src.write_text("// kernel\n")
    return lambda: ext_build.build_or_load("fake_ext", (src,), tmp_path / "b", "test kernels", cflags=[])


def test_a_killed_builds_lock_file_does_not_block_and_the_marker_follows_success(tmp_path, monkeypatch):
    """torch's lock file left by a killed build (any age) is removed under the build lock; the marker
    is written only after the build imported; a failed build leaves none."""
    out = tmp_path / "b"
    out.mkdir()
    (out / "lock").write_text("")  # what torch's FileBaton would wait on for ever
    seen = []

    def load(**kw):
        seen.append((out / "lock").exists())
        return types.ModuleType(kw["name"])

    build = _fake_build(tmp_path, monkeypatch, load)
    assert build().__name__ == "fake_ext" and seen == [False]
    assert (out / ext_build.MARKER).is_file()

    (out / ext_build.MARKER).unlink()

    def failing(**kw):
        raise RuntimeError("deliberate_compiler_error")

    build = _fake_build(tmp_path, monkeypatch, failing)
    with pytest.raises(ImportError, match="deliberate_compiler_error"):
        build()
    assert not (out / ext_build.MARKER).exists()


def test_a_second_process_waits_for_the_build_lock(tmp_path, monkeypatch, caplog):
    """While another holder has the build lock, the build waits (with a message) and starts after."""
    fcntl = pytest.importorskip("fcntl")
    out = tmp_path / "b"
    out.mkdir()
    order = []

    def load(**kw):
        order.append("build")
        return types.ModuleType(kw["name"])

    build = _fake_build(tmp_path, monkeypatch, load)
    holder = open(out / "build.flock", "a")  # another open file description: conflicts like a process
    fcntl.flock(holder, fcntl.LOCK_EX)
    worker = threading.Thread(target=build)
    with caplog.at_level(logging.INFO, logger="splat.ext_build"):
        worker.start()
        time.sleep(0.5)
        order.append("released")
        fcntl.flock(holder, fcntl.LOCK_UN)
        holder.close()
        worker.join(10)
    assert order == ["released", "build"] and "waiting" in caplog.text


def test_a_cached_build_that_does_not_import_is_built_again(tmp_path, monkeypatch):
    out = tmp_path / "b"
    out.mkdir()
    for f in ("fake_ext.so", ext_build.MARKER, ".ninja_log"):
        (out / f).write_text("not a shared object")
    built = []

    def load(**kw):
        built.append(sorted(p.name for p in out.iterdir() if p.name in ("fake_ext.so", ".ninja_log")))
        return types.ModuleType(kw["name"])

    _fake_build(tmp_path, monkeypatch, load)()
    assert built == [[]]  # the broken outputs were removed, so ninja compiles again


def test_missing_sources_are_an_import_error(tmp_path):
    with pytest.raises(ImportError, match="sources not found"):
        ext_build.build_or_load("nothing", (tmp_path / "absent.cpp",), tmp_path / "b", "test kernels", cflags=[])


def test_the_torch_library_path_is_quoted_for_the_link_line_while_building(monkeypatch):
    """torch writes -L{TORCH_LIB_PATH} into ninja's link line unquoted: a checkout under a folder with a
    space (the venv inside it) failed to link ('ld: cannot find dir/main/.venv/...'), found by CI run
    from '/tmp/ci dir'. The CI of that path builds the real extensions; this checks the quoting."""
    import shlex

    import torch.utils.cpp_extension as cpp

    from splat.ext_build import _quoted_torch_lib_path

    monkeypatch.setattr(cpp, "TORCH_LIB_PATH", "/home/me/My Projects/indoorgs/.venv/torch/lib")
    with _quoted_torch_lib_path():
        assert cpp.TORCH_LIB_PATH == "'/home/me/My Projects/indoorgs/.venv/torch/lib'"
        assert shlex.split(f"-L{cpp.TORCH_LIB_PATH}") == ["-L/home/me/My Projects/indoorgs/.venv/torch/lib"]
    assert cpp.TORCH_LIB_PATH == "/home/me/My Projects/indoorgs/.venv/torch/lib"
    monkeypatch.setattr(cpp, "TORCH_LIB_PATH", "/usr/lib/torch/lib")
    with _quoted_torch_lib_path():
        assert cpp.TORCH_LIB_PATH == "/usr/lib/torch/lib"  # nothing to quote: unchanged
