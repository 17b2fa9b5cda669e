"""The torch backend on a CUDA device: same maps and gradients as on the CPU (skipped without a GPU).

CI has no GPU, so these tests are skipped there; they run wherever ``torch.cuda.is_available()``.
The hard cases of tests/test_render_hard_cases.py run on CUDA too (their "cuda" parameter).
"""

from __future__ import annotations

import pytest
import torch

from splat.bench import bench_camera, surface_gaussians
from splat.rasterize import render

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

KEYS = ("rgb", "depth", "median_depth", "normal", "alpha")


def render_with_grads(params: dict, camera, device: str, dtype=torch.float32):
    leaves = {k: v.to(device=device, dtype=dtype).clone().requires_grad_() for k, v in params.items()}
    out = render(leaves, camera.to(device), backend="torch", max_per_pixel=256)
    loss = sum((out[k] * (i + 1)).sum() for i, k in enumerate(KEYS))
    grads = torch.autograd.grad(loss, list(leaves.values()))
    return ({k: out[k].detach().cpu() for k in (*KEYS, "n_contrib")},
            {k: g.cpu() for k, g in zip(params, grads)})


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_cuda_matches_cpu_on_room_surfaces(sh_degree):
    """float32 on both devices: maps within 1e-4, gradients within 1e-3 of each parameter's scale."""
    params = surface_gaussians(5000, sh_degree=sh_degree, seed=4)
    camera = bench_camera(96, 72)
    out_cpu, g_cpu = render_with_grads(params, camera, "cpu")
    out_gpu, g_gpu = render_with_grads(params, camera, "cuda")
    assert 3 < int(out_cpu["n_contrib"].max()) < 256 and float(out_cpu["alpha"].mean()) > 0.5
    torch.testing.assert_close(out_gpu["n_contrib"], out_cpu["n_contrib"], rtol=0, atol=1)
    for k in KEYS:
        torch.testing.assert_close(out_gpu[k], out_cpu[k], rtol=1e-4, atol=1e-4, msg=lambda m: f"{k}: {m}")
    for name in params:
        if g_cpu[name].numel() == 0:  # shN at SH degree 0
            continue
        scale = float(g_cpu[name].abs().max())
        assert scale > 0, name
        torch.testing.assert_close(g_gpu[name], g_cpu[name], rtol=1e-3, atol=1e-3 * scale,
                                   msg=lambda m: f"{name}: {m}")


def test_cuda_float64_equals_cpu():
    """In float64 the two devices agree to rounding (same arithmetic, different reduction order)."""
    params = surface_gaussians(800, sh_degree=1, seed=5)
    camera = bench_camera(48, 36)
    out_cpu, g_cpu = render_with_grads(params, camera, "cpu", torch.float64)
    out_gpu, g_gpu = render_with_grads(params, camera, "cuda", torch.float64)
    for k in KEYS:
        torch.testing.assert_close(out_gpu[k], out_cpu[k], rtol=1e-9, atol=1e-9, msg=lambda m: f"{k}: {m}")
    for name in params:
        scale = float(g_cpu[name].abs().max())
        torch.testing.assert_close(g_gpu[name], g_cpu[name], rtol=1e-7, atol=1e-8 * scale,
                                   msg=lambda m: f"{name}: {m}")


def test_auto_backend_on_cuda_stays_on_the_gpu():
    """backend="auto" with CUDA tensors must not pick the C++ CPU kernels (it picks the CUDA
    kernels when they build, else the torch backend)."""
    params = {k: v.cuda() for k, v in surface_gaussians(500, sh_degree=0, seed=6).items()}
    out = render(params, bench_camera(32, 24).to("cuda"), backend="auto")
    assert out["rgb"].is_cuda and torch.isfinite(out["rgb"]).all()
