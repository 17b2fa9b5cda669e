"""Hard cases: every output and every gradient stays finite, for every available backend.

Each test renders float32 Gaussians with one troublesome property and backpropagates a loss on
rgb + depth + median depth + normal + alpha. The "cpu" backend is tested when splat.composite_cpu
builds here (skipped otherwise), so the C++ backend meets the same cases; "cuda" is the torch backend
on a CUDA device (skipped where there is none).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splat.camera import Camera
from splat.composite import cpu_backend_available
from splat.rasterize import render

WIDTH, HEIGHT = 32, 24


@pytest.fixture(params=["torch", "cpu", "cuda"])
def backend(request) -> str:
    if request.param == "cpu" and not cpu_backend_available():
        pytest.skip("C++ compositing backend (splat.composite_cpu) not available")
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    return request.param


def make_camera(center=(0.0, 0.0, 0.0), yaw=0.0) -> Camera:
    R = np.array([[math.cos(yaw), 0, -math.sin(yaw)], [0, 1, 0], [math.sin(yaw), 0, math.cos(yaw)]])
    K = np.array([[30.0, 0, WIDTH / 2], [0, 30.0, HEIGHT / 2], [0, 0, 1]])
    return Camera.from_Rt(K, R, -R @ np.asarray(center, dtype=np.float64), WIDTH, HEIGHT)


def make_params(n: int, seed: int = 0, spread: float = 0.5, depth: float = 2.0, log_scale: float = -2.5):
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g) * spread + torch.tensor([0.0, 0.0, depth]),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.full((n, 3), log_scale) + 0.3 * torch.randn(n, 3, generator=g),
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.rand(n, 1, 3, generator=g),
        "shN": 0.1 * torch.randn(n, 3, 3, generator=g),
    }


def render_and_check(params: dict, camera: Camera, backend: str) -> dict:
    """Render, check finite outputs and alpha in [0, 1], backprop, check finite gradients.

    ``backend="cuda"`` renders with the torch backend on the GPU; the outputs come back on the CPU.
    """
    device = "cuda" if backend == "cuda" else "cpu"
    leaves = {k: v.detach().to(device).clone().requires_grad_() for k, v in params.items()}
    out = render(leaves, camera.to(device), backend="torch" if backend == "cuda" else backend,
                 background=torch.tensor([0.2, 0.3, 0.4], device=device))
    for key in ("rgb", "depth", "median_depth", "normal", "alpha", "means2d"):
        assert torch.isfinite(out[key]).all(), f"non-finite {key}"
    alpha = out["alpha"].detach()
    assert float(alpha.min()) >= 0.0 and float(alpha.max()) <= 1.0
    loss = (out["rgb"].sum() + out["depth"].sum() + out["median_depth"].sum() + out["normal"].sum()
            + out["alpha"].sum())
    if loss.requires_grad:
        loss.backward()
        for key, leaf in leaves.items():
            assert leaf.grad is None or torch.isfinite(leaf.grad).all(), f"non-finite grad of {key}"
    return {k: v.detach().cpu() if isinstance(v, torch.Tensor) else v for k, v in out.items()}


def test_behind_camera_and_straddling_near_plane(backend):
    params = make_params(40, seed=1)
    z = torch.linspace(-2.0, 0.3, 40)
    params["means"][:, 2] = z  # behind, at, and just past the near plane (0.01 m)
    params["means"][:, :2] *= 0.2
    params["scales"][:20] = math.log(0.5)  # big ones straddle the near plane
    out = render_and_check(params, make_camera(), backend)
    assert not bool(out["visible"][z <= 0.01].any())
    assert bool(out["visible"][z > 0.05].any())


@pytest.mark.parametrize("log_scale", [math.log(1e-7), math.log(1e3)])
def test_extreme_scales(backend, log_scale):
    params = make_params(30, seed=2)
    params["scales"][:] = log_scale
    params["scales"][::3, 0] = math.log(0.05)  # mixed with ordinary axes
    out = render_and_check(params, make_camera(), backend)
    if log_scale > 0:
        assert float(out["alpha"].min()) > 0.5  # kilometre Gaussians cover the whole image


def test_zero_norm_quaternions(backend):
    params = make_params(20, seed=3)
    params["quats"][:10] = 0.0
    out = render_and_check(params, make_camera(), backend)
    assert bool(out["visible"][:10].any())


def test_opacity_logits_plus_minus_40(backend):
    params = make_params(30, seed=4)
    params["opacities"][:15] = 40.0
    params["opacities"][15:] = -40.0
    out = render_and_check(params, make_camera(), backend)
    assert float(out["alpha"].max()) > 0.98


def test_needles_and_discs(backend):
    params = make_params(60, seed=5)
    params["scales"][:30] = torch.log(torch.tensor([0.5, 1e-4, 1e-4]))  # needles
    params["scales"][30:] = torch.log(torch.tensor([0.4, 0.4, 1e-6]))  # discs
    # some seen exactly edge-on: identity rotation, disc normal (z) orthogonal to x-offset rays
    params["quats"][30:40] = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    params["means"][30:40, 1] = 0.0
    render_and_check(params, make_camera(), backend)


def test_far_outside_the_image(backend):
    params = make_params(20, seed=6)
    params["means"][:5, 0] = 1e4  # far to the side
    params["means"][5:10, 1] = -1e5
    params["means"][10:15, 2] = 1e7  # very far away
    params["means"][15:, 0] = 0.5 * params["means"][15:, 2]  # just outside the frustum
    out = render_and_check(params, make_camera(), backend)
    assert not bool(out["visible"][:10].any())


def test_thousands_on_one_pixel(backend):
    n = 3000
    params = make_params(n, seed=7, spread=1e-4, log_scale=math.log(0.01))
    params["opacities"][:] = -1.0
    out = render_and_check(params, make_camera(), backend)
    centre = out["alpha"][HEIGHT // 2, WIDTH // 2]
    assert float(centre) > 0.99
    assert int(out["n_contrib"].max()) >= 20


def test_empty_scene(backend):
    params = make_params(0)
    out = render_and_check(params, make_camera(), backend)
    assert float(out["alpha"].abs().max()) == 0.0
    torch.testing.assert_close(out["rgb"], torch.tensor([0.2, 0.3, 0.4]).expand(HEIGHT, WIDTH, 3))
    culled = make_params(5)
    culled["means"][:, 2] = -1.0  # all behind the camera
    render_and_check(culled, make_camera(), backend)


def test_world_offset_1e4(backend):
    """Offsetting the scene and the camera by 1e4 m changes nothing: positions on a 2^-10 m grid are
    exact in float32 at 1e4, and the camera centre is subtracted before rotating."""
    params = make_params(50, seed=8)
    params["means"] = torch.round(params["means"] * 1024) / 1024
    offset = torch.tensor([1e4, -1e4, 1e4])
    base = render_and_check(params, make_camera(yaw=0.3), backend)
    moved = dict(params, means=params["means"] + offset)
    far = render_and_check(moved, make_camera(center=offset.double().numpy(), yaw=0.3), backend)
    for key in ("rgb", "depth", "median_depth", "normal", "alpha"):
        torch.testing.assert_close(far[key], base[key], rtol=1e-5, atol=1e-5, msg=key)


@pytest.mark.parametrize("index", [0, 3])
def test_a_nan_colour_stays_in_its_gaussian_s_footprint(backend, index):
    """A non-finite colour of one Gaussian reaches only the pixels it blends into. The torch backend
    gathered the -1 pads of its per-pixel selection as Gaussian 0 and multiplied them by alpha 0:
    Gaussian 0's NaN reached 27 pixels outside its 43-pixel footprint (0 * NaN = NaN)."""
    params = make_params(8, seed=3)
    params["means"][index] = torch.tensor([-0.5, -0.3, 2.0])
    device = "cuda" if backend == "cuda" else "cpu"
    name = "torch" if backend == "cuda" else backend

    def rgb(p):
        with torch.no_grad():
            return render({k: v.to(device) for k, v in p.items()}, make_camera().to(device), backend=name)["rgb"].cpu()

    brighter = {k: v.clone() for k, v in params.items()}
    brighter["sh0"][index] += 1.0
    footprint = (rgb(brighter) - rgb(params)).abs().amax(-1) > 0
    poisoned = {k: v.clone() for k, v in params.items()}
    poisoned["sh0"][index, 0, 0] = float("nan")
    nan_px = ~torch.isfinite(rgb(poisoned)).all(-1)
    assert footprint.sum() > 10 and bool(nan_px[footprint].all())
    assert not bool(nan_px[~footprint].any()), int(nan_px[~footprint].sum())


def test_a_vanishing_gaussian_without_low_pass_keeps_finite_gradients(backend):
    """eps2d = 0 (allowed) and a 1e-8 m Gaussian 2 m away: its 2D covariance determinant is ~1e-28 px^4,
    and autograd's -g c / det^2 of the torch projection underflowed det^2 in float32 (NaN gradients of
    means and scales, where the C++ backend computed -(g . conic) / det and gave 0)."""
    device = "cuda" if backend == "cuda" else "cpu"
    cam = Camera.from_Rt(np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), np.eye(3), np.zeros(3), 16, 12)
    p = {"means": torch.tensor([[0.0, 0.0, 2.0]]), "quats": torch.tensor([[1.0, 0, 0, 0]]),
         "scales": torch.full((1, 3), math.log(1e-8)), "opacities": torch.zeros(1),
         "sh0": torch.full((1, 1, 3), 0.5), "shN": torch.zeros(1, 0, 3)}
    p = {k: v.to(device).requires_grad_() for k, v in p.items()}
    out = render(p, cam.to(device), backend="torch" if backend == "cuda" else backend, eps2d=0.0)
    (out["rgb"].sum() + out["depth"].sum()).backward()
    for key in ("means", "scales", "quats"):
        assert torch.isfinite(p[key].grad).all(), key
