"""render(): analytic depth/normal of a tilted flat Gaussian, gradcheck, outputs and conventions."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from splat.camera import Camera
from splat.rasterize import pixel_centres, render

DT = torch.float64


def camera64(width, height, f, R=None, t=None) -> Camera:
    viewmat = torch.eye(4, dtype=DT)
    if R is not None:
        viewmat[:3, :3] = torch.as_tensor(R, dtype=DT)
    if t is not None:
        viewmat[:3, 3] = torch.as_tensor(t, dtype=DT)
    K = torch.tensor([[f, 0, width / 2 - 0.7], [0, f, height / 2 + 0.4], [0, 0, 1]], dtype=DT)
    return Camera(K=K, viewmat=viewmat, width=width, height=height)


def rot_to_quat(R: torch.Tensor) -> torch.Tensor:
    """wxyz quaternion of a rotation matrix (trace > 0 branch is enough for these tests)."""
    w = 0.5 * torch.sqrt(1 + R[0, 0] + R[1, 1] + R[2, 2])
    return torch.stack([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])


def axis_angle(axis, angle) -> torch.Tensor:
    a = torch.tensor(axis, dtype=DT) / np.linalg.norm(axis)
    skew = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=DT)
    return torch.linalg.matrix_exp(skew * angle)


def single_flat_gaussian(center, frame, scales, opacity_logit=3.0):
    """One Gaussian whose local axes are the columns of ``frame`` (world), log-scales of ``scales``."""
    return {
        "means": torch.tensor([center], dtype=DT),
        "quats": rot_to_quat(frame)[None],
        "scales": torch.log(torch.tensor([scales], dtype=DT)),
        "opacities": torch.tensor([opacity_logit], dtype=DT),
        "sh0": torch.full((1, 1, 3), 0.3, dtype=DT),
        "shN": torch.zeros(1, 0, 3, dtype=DT),
    }


@pytest.mark.parametrize("tilt_axis,tilt,cam_yaw", [([0, 1, 0], 0.7, 0.0), ([1, 1, 0], -0.9, 0.2)])
def test_tilted_flat_gaussian_renders_its_plane(tilt_axis, tilt, cam_yaw):
    width, height, f = 64, 48, 400.0
    cam_R = axis_angle([0, 1, 0], cam_yaw)
    cam_C = torch.tensor([0.3, -0.2, -1.0], dtype=DT)
    cam = camera64(width, height, f, R=cam_R, t=-cam_R @ cam_C)
    frame = axis_angle(tilt_axis, tilt)  # Gaussian frame; its third axis is the plane normal
    # place the Gaussian on the optical axis, 2.5 m in front of the camera
    center = cam_C + cam_R.T @ torch.tensor([0.01, -0.02, 2.5], dtype=DT)
    params = single_flat_gaussian(center.tolist(), frame, [0.03, 0.02, 1e-7])
    out = render(params, cam, backend="torch")
    alpha = out["alpha"]
    assert float(alpha.min()) >= 0.0 and float(alpha.max()) <= 1.0
    covered = alpha > 0.05
    assert int(covered.sum()) > 100  # a real footprint, not a couple of pixels
    # analytic: intersect each pixel's ray with the plane (camera frame)
    n_cam = cam_R @ frame[:, 2]
    p0_cam = cam_R @ (center - cam_C)
    q = pixel_centres(width, height, torch.device("cpu"), DT)
    rays = torch.stack([(q[..., 0] - cam.K[0, 2]) / f, (q[..., 1] - cam.K[1, 2]) / f,
                        torch.ones_like(q[..., 0])], -1)  # z = 1 rays
    z_plane = (p0_cam @ n_cam) / (rays @ n_cam)  # [H, W]
    # the paper's depth is the plane's first-order expansion around the mean's ray (d = z' + p.dx);
    # its error against the exact intersection is z' x^2 / (1 + x), x = n.(r - r0) / (n.r0)
    r0 = p0_cam / p0_cam[2]
    x = ((rays - r0) @ n_cam) / (r0 @ n_cam)
    second_order = p0_cam[2] * x * x / (1 + x)
    err = (out["depth"] - z_plane).abs()
    assert torch.all(err[covered] <= second_order[covered] + 1e-9), float((err - second_order)[covered].max())
    assert float(err[covered].max()) < 2e-3 * float(p0_cam[2])
    linear = p0_cam[2] - p0_cam[2] * x  # the first-order plane itself, exactly
    torch.testing.assert_close(out["depth"][covered], linear[covered], rtol=1e-9, atol=1e-9)
    # median depth = the same plane where T crosses 0.5 (alpha >= 0.5), 0 elsewhere
    half = alpha >= 0.5 + 1e-9
    assert int(half.sum()) > 20
    torch.testing.assert_close(out["median_depth"][half], linear[half], rtol=1e-9, atol=1e-9)
    assert float(out["median_depth"][alpha < 0.5 - 1e-9].abs().max()) == 0.0
    # the normal: the plane's normal in the camera frame, facing the camera
    n_face = -n_cam if float(n_cam @ p0_cam) > 0 else n_cam
    normals = out["normal"][covered]
    torch.testing.assert_close(normals, n_face.expand_as(normals), rtol=0, atol=1e-9)
    assert torch.all((normals * rays[covered]).sum(-1) < 0)


def test_gradcheck_render_tiny_scene():
    width, height = 8, 6
    cam = camera64(width, height, 9.0)
    g = torch.Generator().manual_seed(3)
    n = 4
    params = {
        "means": torch.tensor([[0.0, 0.0, 2.0], [0.3, 0.1, 2.3], [-0.3, -0.2, 1.8], [0.1, -0.3, 2.6]], dtype=DT),
        "quats": torch.randn(n, 4, generator=g, dtype=DT),
        "scales": torch.log(0.15 + 0.2 * torch.rand(n, 3, generator=g, dtype=DT)),
        "opacities": torch.tensor([0.5, -0.2, 1.0, 0.3], dtype=DT),
        "sh0": torch.rand(n, 1, 3, generator=g, dtype=DT),
        "shN": 0.1 * torch.randn(n, 3, 3, generator=g, dtype=DT),
    }
    keys = list(params)
    leaves = [params[k].clone().requires_grad_() for k in keys]
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=DT)

    def fn(*tensors):
        out = render(dict(zip(keys, tensors)), cam, backend="torch", background=bg)
        return out["rgb"], out["depth"], out["normal"], out["alpha"], out["median_depth"]

    out = fn(*leaves)
    assert int(render(params, cam, backend="torch")["n_contrib"].max()) >= 3  # overlapping
    assert all(torch.isfinite(o).all() for o in out)
    # every parameter at once along random directions (fast mode), then means and opacities fully
    assert torch.autograd.gradcheck(fn, leaves, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    idx = [keys.index("means"), keys.index("opacities")]

    def fn_subset(means, opacities):
        args = list(leaves)
        args[idx[0]], args[idx[1]] = means, opacities
        return fn(*args)

    assert torch.autograd.gradcheck(fn_subset, [leaves[i] for i in idx], eps=1e-6, atol=1e-5, rtol=1e-4)


def test_outputs_shapes_background_and_means2d_grad():
    width, height = 20, 14
    cam = Camera.from_Rt(np.array([[25.0, 0, 10], [0, 25, 7], [0, 0, 1]]), np.eye(3), np.zeros(3), width, height)
    g = torch.Generator().manual_seed(0)
    n = 30
    params = {
        "means": torch.randn(n, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0]),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.full((n, 3), -2.5),
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.rand(n, 1, 3, generator=g),
        "shN": torch.zeros(n, 8, 3),
    }
    for v in params.values():
        v.requires_grad_()
    bg = torch.tensor([1.0, 0.0, 0.5])
    out = render(params, cam, backend="torch", background=bg, sh_degree=1)
    assert out["rgb"].shape == (height, width, 3) and out["depth"].shape == (height, width)
    assert out["normal"].shape == (height, width, 3) and out["median_depth"].shape == (height, width)
    assert out["radii"].dtype == torch.int32 and out["visible"].dtype == torch.bool
    alpha = out["alpha"].detach()
    assert float(alpha.min()) >= 0 and float(alpha.max()) <= 1
    empty = alpha == 0
    assert int(empty.sum()) > 0
    torch.testing.assert_close(out["rgb"][empty], bg.expand(int(empty.sum()), 3))
    assert float(out["depth"][empty].abs().max()) == 0.0  # 0 = invalid
    norms = out["normal"].norm(dim=-1)
    torch.testing.assert_close(norms[alpha > 0.01], torch.ones_like(norms[alpha > 0.01]))
    loss = out["rgb"].sum() + out["depth"].sum() + out["normal"].sum()
    loss.backward()
    assert out["means2d"].grad is not None and out["means2d"].grad.shape == (n, 2)
    assert float(out["means2d"].grad[out["visible"]].abs().sum()) > 0
    assert float(out["means2d"].grad[~out["visible"]].abs().sum()) == 0
    with pytest.raises(ValueError, match=r"background must have shape \(3,\)"):
        render(params, cam, background=torch.zeros(4))
