"""The fused CUDA projection (splat.project_cuda) against the torch projection, its oracle: values
and gradients of every output on the benchmark room and on the hard cases of tests/test_project_cpu.py,
render() with backend "cuda" against "torch" on the GPU, and the fallbacks to torch.

CI has no GPU: every test here is skipped without CUDA; they run on a GPU machine. The kernel is
float32 only, so the reference is the torch projection on the same GPU in float32, with the
tolerances of tests/test_project_cpu.py's float32 test; where float32 rounding decides (the hard
cases: scales of 1e3 m and 1e-7 m, means 1e4 m from the origin) the kernel's error against the
torch projection in float64 on the same (float32) inputs must be no larger than twice the torch
float32 projection's, as tests/test_composite_cuda.py does for render(). Gradients are compared
per Gaussian (each Gaussian's gradient depends on its own outputs only), on the Gaussians whose
radius (culling decision) the compared projections agree on: all but a handful.
"""

from __future__ import annotations

import importlib

import pytest
import torch

from splat.projection import ProjectionConfig, project_gaussians

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (CI has none)")

KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")
OUTPUTS = ("means2d", "conics", "depths", "opacities", "colors", "depth_slopes", "normals")


@pytest.fixture(scope="session")
def cuda():
    """splat.project_cuda (importing it builds the CUDA extension, about 1.5 min the first time)."""
    return importlib.import_module("splat.project_cuda")


def project_and_grads(fn, params, cam, dtype=torch.float32, device="cuda"):
    """Project with ``fn(leaves, cam)``, then the gradients of a fixed random weighting of every output."""
    leaves = {k: v.detach().to(device=device, dtype=dtype).clone().requires_grad_() for k, v in params.items()}
    proj = fn(leaves, cam)
    gen = torch.Generator().manual_seed(7)
    loss = sum((getattr(proj, name) * torch.randn(getattr(proj, name).shape, generator=gen,
                                                  dtype=torch.float64).to(device=device, dtype=dtype)).sum()
               for name in OUTPUTS)
    grads = torch.autograd.grad(loss, [leaves[k] for k in KEYS])
    return proj, [g.detach() for g in grads]


def kernel(cuda, sh_degree=None, **cfg):
    return lambda p, cam: cuda.project_gaussians_cuda(p, cam, sh_degree=sh_degree, config=ProjectionConfig(**cfg))


def torch_proj(sh_degree=None, **cfg):
    return lambda p, cam: project_gaussians(p, cam, sh_degree=sh_degree, config=ProjectionConfig(**cfg),
                                            backend="torch")


def agreeing_rows(*radii, max_mismatch: int) -> torch.Tensor:
    """Rows where every projection made the same culling decision; at most ``max_mismatch`` differ."""
    same = torch.ones_like(radii[0], dtype=torch.bool)
    for r in radii[1:]:
        same &= r == radii[0]
    assert int((~same).sum()) <= max_mismatch, f"{int((~same).sum())} radii differ"
    return same


def rows(t: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return t.detach()[mask].double().cpu()


@pytest.mark.parametrize("degree,available", [(0, 3), (1, 3), (2, 2), (3, 3)])
@pytest.mark.parametrize("antialiased", [False, True])
def test_float32_matches_torch_on_room_surfaces(cuda, degree, available, antialiased):
    """The benchmark room (4000 flat Gaussians, 64x48): tests/test_project_cpu.py's float32 tolerances."""
    from splat.bench import bench_camera, surface_gaussians

    params = surface_gaussians(4000, sh_degree=available, seed=3)
    cam = bench_camera(64, 48).to("cuda")
    ref, ref_grads = project_and_grads(torch_proj(degree, antialiased=antialiased), params, cam)
    out, grads = project_and_grads(kernel(cuda, degree, antialiased=antialiased), params, cam)
    assert out.radii.dtype == torch.int32 and out.means2d.is_cuda
    same = agreeing_rows(out.radii, ref.radii, max_mismatch=2)
    assert int((ref.radii > 0).sum()) > 500
    for name in OUTPUTS:
        a, b = getattr(out, name), getattr(ref, name)
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(rows(a, same), rows(b, same), rtol=1e-5, atol=1e-5,
                                   msg=lambda m: f"{name}: {m}")
    for key, a, b in zip(KEYS, grads, ref_grads):
        assert torch.isfinite(a).all(), key
        if b.numel() == 0:
            continue
        scale = float(b.abs().max())
        torch.testing.assert_close(rows(a, same), rows(b, same), rtol=1e-4, atol=1e-5 * max(scale, 1e-30),
                                   msg=lambda m: f"d {key}: {m}")
    if degree < available:  # unused coefficients get exactly zero gradient
        assert float(grads[5][:, (degree + 1) ** 2 - 1:].abs().max()) == 0.0


def assert_no_worse(name, a, b, c, rtol, atol_rel):
    """a (kernel) within rtol / atol_rel of scale of b (torch float32), or no further from c (torch
    float64 on the same inputs) than twice b's distance from it, plus atol_rel of scale."""
    scale = max(float(c.abs().max()) if c.numel() else 0.0, 1e-30)
    if torch.allclose(a, b, rtol=rtol, atol=atol_rel * scale):
        return
    err_a, err_b = float((a - c).abs().max()), float((b - c).abs().max())
    assert err_a <= 2 * err_b + atol_rel * scale, (name, err_a, err_b, scale)


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (1e4, -2e3, 5e3)])
def test_float32_hard_cases(cuda, antialiased, offset):
    """tests/test_project_cpu.py's hard cases (near plane, tiny / huge scales, zero quaternions,
    logits +-40, needles, discs seen edge-on, far outside the image, clamped Jacobian, ties in the
    smallest scale) in float32, far from the origin too: finite, culling as torch, values and
    gradients as close to the float64 projection as the torch float32 projection's."""
    from test_project_cpu import camera, hard_params

    params = {k: v.to(torch.float32) for k, v in hard_params(offset=offset).items()}
    cam32 = camera(center=offset, dtype=torch.float32).to("cuda")
    cam64 = camera(center=offset, dtype=torch.float64).to("cuda")
    out, grads = project_and_grads(kernel(cuda, antialiased=antialiased), params, cam32)
    ref, ref_grads = project_and_grads(torch_proj(antialiased=antialiased), params, cam32)
    r64, g64 = project_and_grads(torch_proj(antialiased=antialiased), params, cam64, dtype=torch.float64)
    n = len(out.radii)
    assert 100 < int((out.radii > 0).sum()) < n  # a mix of visible and culled
    same = agreeing_rows(out.radii, ref.radii, r64.radii, max_mismatch=n // 100)
    culled = same & (out.radii == 0)
    for name in OUTPUTS:
        a = getattr(out, name)
        assert torch.isfinite(a).all(), name
        fill = 1.0 if name == "depths" else 0.0  # culled: zeros, depth 1
        assert bool((a[culled] == fill).all()), name
        assert_no_worse(name, rows(a, same), rows(getattr(ref, name), same), rows(getattr(r64, name), same),
                        rtol=1e-5, atol_rel=1e-5)
    for key, a, b, c in zip(KEYS, grads, ref_grads, g64):
        assert torch.isfinite(a).all(), key
        assert float(a[culled].abs().max()) == 0.0, key  # no gradient to culled Gaussians
        assert float(c.abs().max()) > 0, key
        assert_no_worse(f"d {key}", rows(a, same), rows(b, same), rows(c, same), rtol=1e-4, atol_rel=1e-5)


def test_fallbacks_to_torch(cuda):
    """float64 Gaussians, CPU tensors and a camera that requires grad take the torch projection."""
    from test_project_cpu import camera, hard_params

    params = hard_params(n=64, seed=5)
    cam = camera(dtype=torch.float64).to("cuda")
    p64 = {k: v.cuda() for k, v in params.items()}
    a = cuda.project_gaussians_cuda(p64, cam)
    b = project_gaussians(p64, cam, backend="torch")
    for name in (*OUTPUTS, "radii"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    p32 = {k: v.to("cuda", torch.float32) for k, v in params.items()}
    cam32 = camera(dtype=torch.float32).to("cuda")
    cam32.viewmat.requires_grad_()
    proj = cuda.project_gaussians_cuda(p32, cam32)
    (proj.means2d.sum() + proj.depths.sum()).backward()
    assert cam32.viewmat.grad is not None and float(cam32.viewmat.grad.abs().sum()) > 0
    with pytest.raises(ValueError, match="SH degree 3"):
        cuda.project_gaussians_cuda({**p32, "shN": p32["shN"][:, :3]}, camera(dtype=torch.float32).to("cuda"),
                                    sh_degree=3)
    empty = {k: v[:0] for k, v in p32.items()}
    e = cuda.project_gaussians_cuda(empty, camera(dtype=torch.float32).to("cuda"))
    assert e.means2d.shape == (0, 2) and e.radii.shape == (0,)


@pytest.mark.parametrize("antialiased", [False, True])
def test_render_cuda_matches_torch_backend(cuda, monkeypatch, antialiased):
    """render(backend="cuda") (CUDA projection + compositing) against render(backend="torch") on the
    GPU on the benchmark room at SH degree 3: tests/test_composite_cuda.py's render tolerances."""
    from splat.bench import bench_camera, surface_gaussians
    from test_composite_cuda import assert_render_close, render_both

    calls = []
    original = cuda._ProjectCUDA.apply
    monkeypatch.setattr(cuda._ProjectCUDA, "apply", lambda *a: (calls.append(1), original(*a))[1])
    params = {k: v.cuda() for k, v in surface_gaussians(20_000, sh_degree=3, seed=2).items()}
    camera = bench_camera(160, 120).to("cuda")
    assert_render_close(render_both(params, camera, antialiased=antialiased), list(params))
    assert len(calls) == 1  # the "cuda" render used the kernels (the two torch renders did not)
