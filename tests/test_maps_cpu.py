"""splat/maps_cpu.py: render()'s fused per-pixel maps (depth, median depth, normal) against the torch
code, splat.rasterize.pixel_maps, its oracle — values and gradients in float64 and float32, the hard
pixels (alpha at and below ALPHA_EPS, vanishing and tiny blended normals, huge values), gradcheck."""

from __future__ import annotations

import shutil

import pytest
import torch
from torch.autograd import gradcheck

from splat.rasterize import ALPHA_EPS, pixel_maps

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the cpu backend cannot be built here")


@pytest.fixture(scope="module")
def fused():
    from splat.maps_cpu import pixel_maps_cpu

    return lambda f, m, a: pixel_maps_cpu(f, m, a, ALPHA_EPS)


def maps_inputs(h=13, w=17, c=9, dtype=torch.float64, seed=0, hard=True):
    g = torch.Generator().manual_seed(seed)
    f = torch.randn(h, w, c, generator=g, dtype=torch.float64)
    m = torch.randn(h, w, 3, generator=g, dtype=torch.float64)
    a = torch.rand(h, w, generator=g, dtype=torch.float64) * 0.98 + 0.01
    if hard:
        a[0, :4] = torch.tensor([0.0, ALPHA_EPS, ALPHA_EPS * 0.5, ALPHA_EPS * 2])  # at / below / above eps
        f[1, :3, 6:9] = 0.0  # no blended normal
        f[1, 3, 6:9] = 1e-7  # |n|^2 = 3e-14 < 1e-12: reported 0
        f[1, 4, 6:9] = torch.tensor([1e-6, 0.0, 0.0]) * 1.5  # |n|^2 = 2.25e-12 > 1e-12: normalised
        f[2, 0, 3:6] = torch.tensor([1e8, -1e6, 1e6])  # huge plane
        a[2, 1] = 1.0
    return [t.to(dtype).requires_grad_() for t in (f, m, a)]


def _values_and_grads(fn, leaves, seed=1):
    outs = fn(*leaves)
    g = torch.Generator().manual_seed(seed)
    loss = sum((o * torch.randn(o.shape, generator=g, dtype=torch.float64).to(o.dtype)).sum() for o in outs)
    return outs, torch.autograd.grad(loss, leaves)


@pytest.mark.parametrize("c", [9, 12])
def test_float64_equals_torch(fused, c):
    leaves = maps_inputs(c=c)
    (o_a, g_a), (o_b, g_b) = _values_and_grads(fused, leaves), _values_and_grads(pixel_maps, leaves)
    for a, b in zip((*o_a, *g_a), (*o_b, *g_b)):  # atol: rounding of 1/|n| ~ 7e5 at the tiny normal
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12 * max(1.0, float(b.abs().max())))
    depth, _, normal = o_a
    assert float(depth[0, 0]) == float(depth[0, 1]) == float(depth[0, 2]) == 0.0 and float(depth[0, 3]) != 0.0
    assert float(normal[1, :4].abs().max()) == 0.0 and torch.allclose(normal[1, 4], torch.tensor([1.0, 0, 0], dtype=normal.dtype))
    assert float(g_a[0][..., :3].abs().max()) == 0.0 and float(g_a[0][..., 9:].abs().sum()) == 0.0


def test_float32_matches_torch(fused):
    leaves = maps_inputs(h=48, w=64, dtype=torch.float32, seed=3, hard=False)
    (o_a, g_a), (o_b, g_b) = _values_and_grads(fused, leaves), _values_and_grads(pixel_maps, leaves)
    for a, b in zip((*o_a, *g_a), (*o_b, *g_b)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_gradcheck_float64(fused):
    leaves = maps_inputs(h=5, w=6, seed=4, hard=False)
    assert gradcheck(fused, leaves, eps=1e-6, atol=1e-7)


def test_render_uses_it_and_agrees_with_the_torch_maps(monkeypatch):
    """render(backend="cpu") takes the fused maps; the same render through the torch maps agrees."""
    from splat import maps_cpu, rasterize
    from splat.bench import bench_camera, surface_gaussians

    params = {k: v.requires_grad_() for k, v in surface_gaussians(3000, 1, 0).items()}
    cam = bench_camera(64, 48)
    calls = []
    real = maps_cpu.pixel_maps_cpu
    monkeypatch.setattr(maps_cpu, "pixel_maps_cpu", lambda *a: calls.append(1) or real(*a))
    fast = rasterize.render(params, cam, backend="cpu")
    assert calls
    monkeypatch.setattr(maps_cpu, "pixel_maps_cpu", lambda f, m, a, eps: pixel_maps(f, m, a))
    ref = rasterize.render(params, cam, backend="cpu")
    for key in ("depth", "median_depth", "normal"):
        torch.testing.assert_close(fast[key], ref[key], rtol=1e-5, atol=1e-5)
    g_fast = torch.autograd.grad(fast["depth"].sum() + fast["normal"].sum(), params["means"])[0]
    g_ref = torch.autograd.grad(ref["depth"].sum() + ref["normal"].sum(), params["means"])[0]
    torch.testing.assert_close(g_fast, g_ref, rtol=1e-4, atol=1e-5 * float(g_ref.abs().max()))
