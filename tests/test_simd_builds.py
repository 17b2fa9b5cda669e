"""The AVX2 build of the C++ kernels (splat/cpu_ext.py: 8 float lanes in the compositing, the compiler's
wider vector loops elsewhere) against the baseline build (SSE4.2, 4 lanes), in one process. Every lane
evaluates the same operations in the same order without FMA contraction, so images, alpha, median,
counts, projections and losses are bitwise equal; float compositing gradients differ only by the order
of the per-Gaussian sums over a row's lanes. Skipped where the AVX2 build is not in use (no AVX2, or
INDOORGS_CPU_SIMD=baseline): there the baseline build is the one every other test checks. The first
run here builds the baseline extension too (about a minute)."""

from __future__ import annotations

import shutil

import pytest
import torch

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the cpu backend cannot be built here")


@pytest.fixture(scope="module")
def builds():
    from splat import cpu_ext

    if cpu_ext.SIMD != "avx2":
        pytest.skip("the AVX2 build is not in use here (no AVX2, or INDOORGS_CPU_SIMD=baseline)")
    return cpu_ext.baseline_ext(), cpu_ext.ext


@pytest.mark.parametrize("nch,dtype", [(9, torch.float32), (4, torch.float32), (9, torch.float64)])
def test_compositing_agrees(builds, monkeypatch, nch, dtype):
    from test_composite_cpu import random_scene, run

    from splat import composite_cpu

    width, height = 100, 70
    leaves, depths, radii = random_scene(3000, width, height, nch=nch, dtype=dtype, seed=8)
    results = []
    for build in builds:
        monkeypatch.setattr(composite_cpu, "_ext", build)
        out, grads = run(composite_cpu.composite, leaves, depths, radii, width, height)
        results.append(([out.features, out.alpha, out.median, out.n_contrib], grads))
    (outs_a, grads_a), (outs_b, grads_b) = results
    assert all(torch.equal(a, b) for a, b in zip(outs_a, outs_b))
    for a, b in zip(grads_a, grads_b):
        if dtype == torch.float64:  # 4 lanes in both builds: the same sums
            assert torch.equal(a, b)
        else:
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6 * float(a.abs().max()))


def projection_and_losses(builds, monkeypatch, dtype) -> list[list[torch.Tensor]]:
    """With each build: the projection's outputs and gradients, the fused SSIM and its gradient."""
    from test_project_cpu import OUTPUTS, camera, hard_params, project_and_grads

    from splat import losses_cpu, project_cpu

    params, cam = hard_params(n=800, seed=3, dtype=dtype), camera(dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(37, 53, 3, generator=gen, dtype=torch.float64).to(dtype)
    y = torch.rand(37, 53, 3, generator=gen, dtype=torch.float64).to(dtype)
    results = []
    for build in builds:
        monkeypatch.setattr(project_cpu, "_ext", build)
        monkeypatch.setattr(losses_cpu, "_EXT", [build])
        proj, grads = project_and_grads(params, cam, "cpu", sh_degree=3)
        xs = x.clone().requires_grad_()
        ssim = losses_cpu.ssim_mean(xs, y)
        ssim.backward()
        results.append([*(getattr(proj, k) for k in (*OUTPUTS, "radii")), *grads, ssim.detach(), xs.grad])
    return results


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_projection_and_losses_are_bitwise_equal(builds, monkeypatch, dtype):
    for a, b in zip(*projection_and_losses(builds, monkeypatch, dtype)):
        assert torch.equal(a, b)


def test_the_builds_train_to_the_same_metrics(builds, monkeypatch):
    """A fixed-seed short training with each build, under the tolerance the fused Adam and loss kernels
    are held to (tests/test_train_step.py): the gradients differ in the last bits, which Adam's
    near-sign steps and the refine steps amplify."""
    from test_train_step import _short_run

    from splat import composite_cpu, losses_cpu, project_cpu

    runs = []
    for build in builds:
        monkeypatch.setattr(composite_cpu, "_ext", build)
        monkeypatch.setattr(project_cpu, "_ext", build)
        monkeypatch.setattr(losses_cpu, "_EXT", [build])
        runs.append(_short_run("fused", 120))
    (pa, ca), (pb, cb) = runs
    assert abs(pa - pb) < 0.5, (pa, pb)
    assert all(abs(x - y) <= 0.03 * max(y, 10) for x, y in zip(ca, cb)), (ca, cb)
