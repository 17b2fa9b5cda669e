"""The one-thread build of the C++ kernels (splat/cpu_ext.py, csrc/omp_compat.h): what a compiler
without OpenMP gets (Apple's clang) instead of the torch backend. Built here without -fopenmp and held
bitwise to the OpenMP baseline build: the tiles' results are merged in tile order whatever thread
made them, so one thread computes the same sums. And the choice of build: OpenMP first, the one-thread
build when that fails or INDOORGS_CPU_OPENMP=0 asks, with a warning. The first run here builds the
one-thread extension (about a minute)."""

from __future__ import annotations

import logging
import shutil

import pytest
import torch

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the cpu backend cannot be built here")


@pytest.fixture(scope="module")
def builds():
    cpu_ext = pytest.importorskip("splat.cpu_ext", reason="the C++ CPU extension does not build here")
    if not cpu_ext.OPENMP:
        pytest.skip("the one-thread build is the one in use here: every other test checks it")
    return cpu_ext.baseline_ext(), cpu_ext._build("baseline", openmp=False)


@pytest.fixture
def two_threads():
    """The OpenMP build on two threads at least (the kernels take at::get_num_threads())."""
    threads = torch.get_num_threads()
    torch.set_num_threads(max(2, threads))
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("nch,dtype", [(9, torch.float32), (9, torch.float64)])
def test_compositing_is_bitwise_equal(builds, two_threads, monkeypatch, nch, dtype):
    from test_composite_cpu import random_scene, run

    from splat import composite_cpu

    leaves, depths, radii = random_scene(3000, 100, 70, nch=nch, dtype=dtype, seed=8)
    results = []
    for build in builds:
        monkeypatch.setattr(composite_cpu, "_ext", build)
        out, grads = run(composite_cpu.composite, leaves, depths, radii, 100, 70)
        results.append([out.features, out.alpha, out.median, out.n_contrib, *grads])
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_projection_and_losses_are_bitwise_equal(builds, two_threads, monkeypatch):
    from test_simd_builds import projection_and_losses

    for a, b in zip(*projection_and_losses(builds, monkeypatch, torch.float32)):
        assert torch.equal(a, b)


class TestChoice:
    """_build_selected with builds that fail on purpose (no compiler runs)."""

    @staticmethod
    def fake(monkeypatch, fails):
        from splat import cpu_ext

        tried = []

        def build(simd=None, openmp=True):
            tried.append(cpu_ext.ext_name(simd, openmp))
            if fails(simd, openmp):
                raise ImportError(f"building {cpu_ext.ext_name(simd, openmp)} failed: no -fopenmp here\nmore")
            return object()

        monkeypatch.setattr(cpu_ext, "_build", build)
        monkeypatch.setattr(cpu_ext, "selected_simd", lambda: "avx2")
        return cpu_ext, tried

    def test_no_openmp_gives_the_one_thread_build_with_a_warning(self, monkeypatch, caplog):
        cpu_ext, tried = self.fake(monkeypatch, lambda simd, openmp: openmp)
        with caplog.at_level(logging.WARNING, logger="splat.cpu_ext"):
            _, simd, openmp = cpu_ext._build_selected()
        assert (simd, openmp) == ("baseline", False)
        assert tried == ["indoorgs_cpu_avx2", "indoorgs_cpu", "indoorgs_cpu_serial"]
        text = caplog.text
        assert "indoorgs_cpu_avx2 did not build (building indoorgs_cpu_avx2 failed: no -fopenmp here)" in text
        assert "run on one thread (built without OpenMP)" in text

    def test_openmp_first_and_the_environment_switch(self, monkeypatch, caplog):
        cpu_ext, tried = self.fake(monkeypatch, lambda simd, openmp: False)
        with caplog.at_level(logging.WARNING, logger="splat.cpu_ext"):
            assert cpu_ext._build_selected()[1:] == ("avx2", True)
        assert tried == ["indoorgs_cpu_avx2"] and not caplog.text
        monkeypatch.setenv("INDOORGS_CPU_OPENMP", "0")
        tried.clear()
        assert cpu_ext._build_selected()[1:] == ("baseline", False) and tried == ["indoorgs_cpu_serial"]
        assert "INDOORGS_CPU_OPENMP=0" in caplog.text

    def test_nothing_builds_raises_the_last_failure(self, monkeypatch):
        cpu_ext, tried = self.fake(monkeypatch, lambda simd, openmp: True)
        with pytest.raises(ImportError, match="indoorgs_cpu_serial failed"):
            cpu_ext._build_selected()
        assert len(tried) == 3


def test_the_rasterizer_is_named_with_its_build(monkeypatch):
    """`splat train` logs and reports which kernels run: the slow paths must be visible."""
    cpu_ext = pytest.importorskip("splat.cpu_ext", reason="the C++ CPU extension does not build here")
    from splat.composite import describe_backend

    cpu = torch.device("cpu")
    assert describe_backend("torch", cpu) == "torch"
    monkeypatch.setattr(cpu_ext, "OPENMP", True)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    assert describe_backend("auto", cpu) == f"cpu (C++ {cpu_ext.SIMD} build, OpenMP, 3 threads)"
    monkeypatch.setattr(cpu_ext, "OPENMP", False)
    assert describe_backend("cpu", cpu) == f"cpu (C++ {cpu_ext.SIMD} build, one thread)"


def test_the_warning_quotes_the_compilers_error_not_ninjas_command_line():
    from splat.ext_build import compiler_error

    ninja = ("building indoorgs_cpu in /c failed: Error building extension 'indoorgs_cpu': [1/6] c++ -MMD "
             + "-isystem /x " * 50 + "-fopenmp -c k.cpp\nFAILED: k.o\nclang: error: unsupported option '-fopenmp'\n"
             "ninja: build stopped: subcommand failed.")
    assert compiler_error(ImportError(ninja)) == "clang: error: unsupported option '-fopenmp'"
    assert compiler_error(ImportError("cannot import x.so\ndetails")) == "cannot import x.so"
    assert len(compiler_error(ImportError("y" * 500))) == 200
