"""The fused C++ projection (splat.project_cpu) against the torch projection, its oracle: values and
gradients of every output on ordinary and hard Gaussians, float64 gradcheck, dispatch rules."""

from __future__ import annotations

import importlib
import math
import shutil

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from splat.camera import Camera
from splat.projection import ProjectionConfig, project_gaussians

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the cpu backend cannot be built here")

KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")
OUTPUTS = ("means2d", "conics", "depths", "opacities", "colors", "depth_slopes", "normals")


@pytest.fixture(scope="session")
def cpu():
    return importlib.import_module("splat.project_cpu")


def camera(width=48, height=36, center=(0.0, 0.0, 0.0), yaw=0.2, dtype=torch.float64) -> Camera:
    R = np.array([[math.cos(yaw), 0, -math.sin(yaw)], [0, 1, 0], [math.sin(yaw), 0, math.cos(yaw)]])
    K = np.array([[40.0, 0, width / 2 + 1.5], [0, 42.0, height / 2 - 2.0], [0, 0, 1]])
    cam = Camera.from_Rt(K, R, -R @ np.asarray(center, dtype=np.float64), width, height)
    c64 = torch.as_tensor(np.asarray(center, dtype=np.float64))
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3], vm[:3, 3] = torch.as_tensor(R), -torch.as_tensor(R) @ c64
    return Camera(K=cam.K.to(dtype), viewmat=vm.to(dtype), width=width, height=height, center=c64.to(dtype))


def hard_params(n=400, seed=0, offset=(0.0, 0.0, 0.0), degree=3, dtype=torch.float64) -> dict:
    """Random Gaussians in front of the camera with every hard case of the rasterizer mixed in."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    means = torch.randn(n, 3, generator=g, dtype=f64) * torch.tensor([0.8, 0.6, 0.5], dtype=f64)
    means[:, 2] += 2.5
    scales = -2.5 + 0.5 * torch.randn(n, 3, generator=g, dtype=f64)
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    opac = torch.randn(n, generator=g, dtype=f64)
    k = n // 16
    means[0:k, 2] = torch.linspace(-1.0, 0.02, k, dtype=f64)  # behind / straddling the near plane
    scales[k:2 * k] = math.log(1e-7)  # tiny (flat guard: all axes below 1e-4 m)
    scales[2 * k:3 * k] = math.log(1e3)  # huge
    quats[3 * k:4 * k] = 0.0  # zero-norm quaternions
    opac[4 * k:5 * k] = 40.0
    opac[5 * k:6 * k] = -40.0
    scales[6 * k:7 * k] = torch.log(torch.tensor([0.5, 1e-4, 1e-4], dtype=f64))  # needles
    scales[7 * k:8 * k] = torch.log(torch.tensor([0.4, 0.4, 1e-6], dtype=f64))  # discs (flat)
    # every other disc seen exactly edge-on (normal along y, mean at y = 0: the min_cos clamp)
    quats[7 * k:8 * k:2] = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0], dtype=f64)
    means[7 * k:8 * k:2, 1] = 0.0
    means[8 * k:9 * k, 0] = 1e4  # far outside the image
    # outside the frustum but reaching into the image (the clamped Jacobian of the EWA projection)
    means[9 * k:10 * k, 0] = means[9 * k:10 * k, 2]
    scales[9 * k:10 * k] = math.log(0.6)
    scales[10 * k:11 * k] = scales[10 * k:11 * k, :1]  # isotropic: ties in the smallest scale
    means += torch.tensor(offset, dtype=f64)
    nb = (degree + 1) ** 2 - 1
    params = {"means": means, "quats": quats, "scales": scales, "opacities": opac,
              "sh0": torch.rand(n, 1, 3, generator=g, dtype=f64) - 0.5,
              "shN": 0.3 * torch.randn(n, nb, 3, generator=g, dtype=f64)}
    return {k: v.to(dtype) for k, v in params.items()}


def project_and_grads(params, cam, backend, sh_degree=None, **cfg):
    leaves = {k: v.detach().clone().requires_grad_() for k, v in params.items()}
    proj = project_gaussians(leaves, cam, sh_degree=sh_degree, config=ProjectionConfig(**cfg), backend=backend)
    gen = torch.Generator().manual_seed(7)
    loss = sum((getattr(proj, name) * torch.randn(getattr(proj, name).shape, generator=gen,
                                                  dtype=torch.float64).to(proj.means2d.dtype)).sum()
               for name in OUTPUTS)
    return proj, torch.autograd.grad(loss, [leaves[k] for k in KEYS])


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (1e4, -2e3, 5e3)])
def test_float64_equals_torch_on_hard_cases(cpu, antialiased, offset):
    params = hard_params(offset=offset)
    cam = camera(center=offset)
    ref, ref_grads = project_and_grads(params, cam, "torch", antialiased=antialiased)
    out, grads = project_and_grads(params, cam, "cpu", antialiased=antialiased)
    assert torch.equal(out.radii, ref.radii)
    assert 100 < int((ref.radii > 0).sum()) < len(ref.radii)  # a mix of visible and culled
    for name in OUTPUTS:
        a, b = getattr(out, name), getattr(ref, name)
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-12, msg=lambda m: f"{name}: {m}")
    for key, a, b in zip(KEYS, grads, ref_grads):
        assert torch.isfinite(a).all(), key
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()),
                                   msg=lambda m: f"d {key}: {m}")
        assert float(b.abs().max()) > 0, key


@pytest.mark.parametrize("degree,available", [(0, 3), (1, 3), (2, 2), (3, 3)])
def test_float32_matches_torch_on_room_surfaces(cpu, degree, available):
    from splat.bench import bench_camera, surface_gaussians

    params = surface_gaussians(4000, sh_degree=available, seed=3)
    cam = bench_camera(64, 48)
    ref, ref_grads = project_and_grads(params, cam, "torch", sh_degree=degree)
    out, grads = project_and_grads(params, cam, "cpu", sh_degree=degree)
    assert torch.equal(out.radii, ref.radii) and int((ref.radii > 0).sum()) > 500
    for name in OUTPUTS:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-5, atol=1e-5,
                                   msg=lambda m: f"{name}: {m}")
    for key, a, b in zip(KEYS, grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * max(float(b.abs().max()), 1e-30),
                                   msg=lambda m: f"d {key}: {m}")
    if degree < available:  # unused coefficients get exactly zero gradient
        assert float(grads[5][:, (degree + 1) ** 2 - 1:].abs().max()) == 0.0


def test_gradcheck_float64(cpu):
    """Finite differences of the C++ forward against its analytic backward (tiny scene in view)."""
    params = hard_params(n=6, seed=4, degree=2)
    params["means"][:, 2] = 2.0 + torch.rand(6, dtype=torch.float64)
    params["scales"][:] = -1.5 + 0.4 * torch.randn(6, 3, dtype=torch.float64)
    params["opacities"][:] = 0.3
    cam = camera()
    cfg = ProjectionConfig(antialiased=True)

    def fn(*tensors):
        proj = cpu.project_gaussians_cpu(dict(zip(KEYS, tensors)), cam, 2, cfg)
        assert bool((proj.radii > 0).all())
        return tuple(getattr(proj, name) for name in OUTPUTS)

    inputs = tuple(params[k].clone().requires_grad_() for k in KEYS)
    assert gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_dispatch(cpu):
    params = hard_params(n=50, seed=5, dtype=torch.float32)
    cam = camera(dtype=torch.float32)
    with pytest.raises(ValueError, match="projection backend"):
        project_gaussians(params, cam, backend="cuda")
    with pytest.raises(ValueError, match="SH degree 3"):
        project_gaussians({**params, "shN": params["shN"][:, :3]}, cam, sh_degree=3, backend="cpu")
    # a camera that requires grad takes the torch path, which gives the pose a gradient
    cam.viewmat.requires_grad_()
    proj = project_gaussians(params, cam, backend="cpu")
    (proj.means2d.sum() + proj.depths.sum()).backward()
    assert cam.viewmat.grad is not None and float(cam.viewmat.grad.abs().sum()) > 0


@pytest.mark.parametrize("degree", [0, 3])
def test_colours_only_backward_equals_the_full_one(cpu, degree):
    """With means, quats, scales and opacities detached (a frozen geometry) the C++ backward runs the
    colours' chain alone: sh0 and shN get the full backward's gradients bit for bit (and the torch
    reference's within float64 rounding); the geometry gets none."""
    params = hard_params(degree=3)
    cam = camera()
    grads = {}
    for name, backend, geometry in (("full", "cpu", True), ("colours", "cpu", False), ("torch", "torch", False)):
        leaves = {k: v.detach().clone().requires_grad_(geometry or k in ("sh0", "shN")) for k, v in params.items()}
        proj = project_gaussians(leaves, cam, sh_degree=degree, backend=backend)
        gen = torch.Generator().manual_seed(7)
        loss = (proj.colors * torch.randn(proj.colors.shape, generator=gen, dtype=proj.colors.dtype)).sum()
        grads[name] = torch.autograd.grad(loss, [leaves["sh0"], leaves["shN"]])
    assert float(grads["full"][0].abs().max()) > 0
    for a, b, c in zip(grads["colours"], grads["full"], grads["torch"]):
        assert torch.equal(a, b)
        torch.testing.assert_close(a, c, rtol=1e-9, atol=1e-12)
