"""Projection: camera, quaternions, EWA covariance, culling, SH colour, RaDe-GS planes, gradcheck."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from splat.camera import Camera
from splat.projection import (
    ProjectionConfig,
    check_params,
    depth_plane_and_normal,
    project_gaussians,
    quat_to_rotmat,
)
from splat.sh import SH_C0, SH_C1, sh_to_rgb

DT = torch.float64


def make_camera(width=16, height=12, f=20.0, dtype=DT, R=None, t=None) -> Camera:
    K = np.array([[f, 0, width / 2 + 0.3], [0, f * 1.1, height / 2 - 0.2], [0, 0, 1]])
    cam = Camera.from_Rt(K, np.eye(3) if R is None else R, np.zeros(3) if t is None else t, width, height)
    return Camera(K=cam.K.to(dtype), viewmat=cam.viewmat.to(dtype), width=width, height=height,
                  center=cam.center.to(dtype))


def make_params(n=5, seed=0, dtype=DT, degree=1, z=2.0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3 + torch.tensor([0.0, 0.0, z], dtype=dtype)
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": torch.log(0.05 + 0.1 * torch.rand(n, 3, generator=g, dtype=dtype)),
        "opacities": torch.randn(n, generator=g, dtype=dtype),
        "sh0": torch.randn(n, 1, 3, generator=g, dtype=dtype) * 0.5,
        "shN": torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g, dtype=dtype) * 0.2,
    }


class TestCamera:
    def test_from_scene_camera_and_center(self):
        rot = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.2], [0.3, 0, -0.1], [-0.2, 0.1, 0]],
                                                   dtype=DT)).numpy()
        scene_cam = SimpleNamespace(K=np.diag([100.0, 100.0, 1.0]), R=rot, t=np.array([1.0, -2.0, 3.0]),
                                    width=40, height=30)
        cam = Camera.from_scene_camera(scene_cam)
        assert cam.K.dtype == torch.float32 and cam.viewmat.shape == (4, 4)
        center = -rot.T @ scene_cam.t
        np.testing.assert_allclose(cam.center.numpy(), center, rtol=1e-6)
        # the centre maps to the camera origin
        np.testing.assert_allclose(rot @ center + scene_cam.t, 0, atol=1e-12)
        half = cam.scaled(2.0)
        assert (half.width, half.height) == (20, 15) and float(half.K[0, 0]) == 50.0

    def test_bad_inputs(self):
        with pytest.raises(ValueError, match="no attribute 'R'"):
            Camera.from_scene_camera(SimpleNamespace(K=np.eye(3), t=np.zeros(3), width=4, height=4))
        with pytest.raises(ValueError, match=r"K must have shape \(3, 3\)"):
            Camera(K=torch.eye(4), viewmat=torch.eye(4), width=4, height=4)


class TestRotationAndSH:
    def test_quat_to_rotmat(self):
        q = torch.tensor([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)],  # 90 deg about z
                          [0.0, 0.0, 0.0, 0.0],  # zero norm -> identity
                          [2.0, 0.0, 0.0, 0.0]], dtype=DT)
        R = quat_to_rotmat(q)
        torch.testing.assert_close(R[0] @ torch.tensor([1.0, 0, 0], dtype=DT), torch.tensor([0.0, 1, 0], dtype=DT))
        torch.testing.assert_close(R[1], torch.eye(3, dtype=DT))
        torch.testing.assert_close(R[2], torch.eye(3, dtype=DT))
        Rr = quat_to_rotmat(torch.randn(50, 4, dtype=DT))
        torch.testing.assert_close(Rr @ Rr.transpose(1, 2), torch.eye(3, dtype=DT).expand(50, 3, 3))
        torch.testing.assert_close(torch.linalg.det(Rr), torch.ones(50, dtype=DT))

    def test_sh_degree_0_and_1(self):
        sh0 = torch.tensor([[[0.4, -3.0, 1.0]]], dtype=DT)
        shn = torch.tensor([[[0.1, 0.2, 0.3], [0.0, 0.5, 0.0], [1.0, 0.0, 0.0]]], dtype=DT)
        d = torch.tensor([[0.6, 0.0, 0.8]], dtype=DT)
        rgb0 = sh_to_rgb(sh0, shn, d, 0)
        torch.testing.assert_close(rgb0, torch.clamp(SH_C0 * sh0[:, 0] + 0.5, min=0))
        assert float(rgb0[0, 1]) == 0.0  # clamped
        rgb1 = sh_to_rgb(sh0, shn, d, 1)
        x, y, z = 0.6, 0.0, 0.8
        expect = SH_C0 * sh0[0, 0] - SH_C1 * y * shn[0, 0] + SH_C1 * z * shn[0, 1] - SH_C1 * x * shn[0, 2] + 0.5
        torch.testing.assert_close(rgb1[0], torch.clamp(expect, min=0))
        with pytest.raises(ValueError, match="needs 9 coefficients"):
            sh_to_rgb(sh0, shn, d, 2)


class TestProjection:
    def test_means_conics_radii_against_direct_formulas(self):
        cam = make_camera()
        params = make_params(n=6, degree=0)
        proj = project_gaussians(params, cam, config=ProjectionConfig(eps2d=0.3))
        K = cam.K
        p = params["means"]  # camera = identity pose
        torch.testing.assert_close(proj.means2d[:, 0], K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2])
        torch.testing.assert_close(proj.means2d[:, 1], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2])
        torch.testing.assert_close(proj.depths, p[:, 2])
        # EWA by brute force: J = d(pixel)/d(point) by autograd, Sigma = R S^2 R^T
        R = quat_to_rotmat(params["quats"])
        S2 = torch.diag_embed(torch.exp(2 * params["scales"]))
        for i in range(6):
            jac = torch.autograd.functional.jacobian(
                lambda x: torch.stack([K[0, 0] * x[0] / x[2] + K[0, 2], K[1, 1] * x[1] / x[2] + K[1, 2]]), p[i])
            cov = jac @ R[i] @ S2[i] @ R[i].T @ jac.T + 0.3 * torch.eye(2, dtype=DT)
            inv = torch.linalg.inv(cov)
            torch.testing.assert_close(proj.conics[i], torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]]))
            mid, det = 0.5 * float(cov[0, 0] + cov[1, 1]), float(torch.linalg.det(cov))
            lam = mid + math.sqrt(max(0.1, mid * mid - det))  # 3DGS's radius rule (floor 0.1)
            assert lam >= float(torch.linalg.eigvalsh(cov)[1])
            assert int(proj.radii[i]) == math.ceil(3 * math.sqrt(lam))
        torch.testing.assert_close(proj.opacities, torch.sigmoid(params["opacities"]))

    def test_culling(self):
        cam = make_camera()
        params = make_params(n=4, degree=0)
        params["means"] = torch.tensor([[0.0, 0.0, 2.0],  # visible
                                        [0.0, 0.0, -1.0],  # behind the camera
                                        [0.0, 0.0, 0.005],  # in front of the near plane
                                        [50.0, 0.0, 2.0]], dtype=DT)  # far outside the image
        params["scales"] = torch.full((4, 3), math.log(0.01), dtype=DT)
        proj = project_gaussians(params, cam)
        assert proj.radii.tolist()[1:] == [0, 0, 0] and int(proj.radii[0]) > 0
        for t in proj[:3] + proj[4:]:
            assert torch.isfinite(t).all()

    def test_world_pose_equivariance(self):
        """Moving the world and the camera together changes nothing in the image."""
        params = make_params(n=8, degree=1)
        shift = torch.tensor([3.0, -1.0, 7.0], dtype=DT)
        moved = dict(params)
        qrot = torch.tensor([math.cos(0.35), 0.3 * math.sin(0.35), 0.0, math.sin(0.35)], dtype=DT)
        qrot = qrot / qrot.norm()
        # rotate the Gaussians' frames by the same rotation: R_g' = rot R_g  (quats: q' = q_rot * q)
        rot = quat_to_rotmat(qrot[None])[0]
        moved["means"] = params["means"] @ rot.T + shift
        w1, x1, y1, z1 = qrot
        w2, x2, y2, z2 = params["quats"].unbind(-1)
        moved["quats"] = torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                                      w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)
        moved["shN"] = torch.zeros_like(params["shN"])  # SH is world-frame; compare without it
        params = dict(params, shN=torch.zeros_like(params["shN"]))
        cam0 = make_camera()
        viewmat = torch.eye(4, dtype=DT)
        viewmat[:3, :3], viewmat[:3, 3] = rot.T, -rot.T @ shift  # x_cam = rot^T (x - shift)
        cam1 = Camera(K=cam0.K, viewmat=viewmat, width=cam0.width, height=cam0.height)
        a, b = project_gaussians(params, cam0), project_gaussians(moved, cam1)
        for name in ("means2d", "conics", "depths", "depth_slopes", "normals", "colors"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name), msg=name)
        assert torch.equal(a.radii, b.radii)

    def test_flat_gaussian_plane_and_guard(self):
        """A flat Gaussian's plane normal is its thin axis; RaDe-GS's guard kicks in below 1e-8 m^2."""
        cam = make_camera(width=64, height=48, f=60.0)
        axis_tilt = 0.6
        R = torch.tensor([[math.cos(axis_tilt), 0, math.sin(axis_tilt)], [0, 1, 0],
                          [-math.sin(axis_tilt), 0, math.cos(axis_tilt)]], dtype=DT)  # camera-frame axes
        p_cam = torch.tensor([[0.2, -0.1, 2.0]], dtype=DT)
        for thin in (1e-3, 1e-5, 1e-7):  # variances 1e-6 (no guard), 1e-10 and 1e-14 (guard)
            log_s = torch.log(torch.tensor([[0.2, 0.1, thin]], dtype=DT))
            slopes, normals = depth_plane_and_normal(R[None], log_s, p_cam, cam, 0.01)
            n = R[:, 2]
            n = -n if float(n @ p_cam[0]) > 0 else n
            torch.testing.assert_close(normals[0], n, atol=2e-5 if thin == 1e-3 else 1e-12, rtol=0)
            # slope = derivative of the ray-plane intersection z w.r.t. the pixel coordinates
            r0 = p_cam[0] / p_cam[0, 2]
            expect = -p_cam[0, 2] * n[:2] / (r0 @ n) / torch.stack([cam.K[0, 0], cam.K[1, 1]])
            torch.testing.assert_close(slopes[0], expect, atol=1e-4 if thin == 1e-3 else 1e-12, rtol=0)


def test_check_params_messages():
    params = make_params(n=3)
    check_params(params)
    bad = dict(params, quats=torch.zeros(3, 3))
    with pytest.raises(ValueError, match=r"params\['quats'\] must have shape \(3, 4\)"):
        check_params(bad)
    with pytest.raises(ValueError, match="miss"):
        check_params({k: v for k, v in params.items() if k != "sh0"})


def test_gradcheck_projection():
    cam = make_camera()
    params = make_params(n=4, degree=1)
    keys = ["means", "quats", "scales", "opacities", "sh0", "shN"]
    leaves = [params[k].clone().requires_grad_() for k in keys]

    def fn(*tensors):
        proj = project_gaussians(dict(zip(keys, tensors)), cam, config=ProjectionConfig(antialiased=True))
        return proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depth_slopes, proj.normals

    assert torch.autograd.gradcheck(fn, leaves, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_a_camera_that_renders_something_else_than_it_says_is_refused():
    """The projection reads fx, fy, cx, cy, R and the centre: a K with skew, a scaled or reflected R,
    a centre that is not viewmat's, a fractional size were rendered in silence (a 2 R doubled every
    depth; a pose edited by dataclasses.replace kept its old centre)."""
    import dataclasses

    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    cam = Camera.from_Rt(K, np.eye(3), np.zeros(3), 16, 12)
    for R, t, match in [(2 * np.eye(3), np.zeros(3), "not a rotation"), (np.diag([1.0, 1, -1]), np.zeros(3), "not a rotation"),
                        (np.full((3, 3), np.nan), np.zeros(3), "non-finite"), (np.eye(3), [0, 0, np.inf], "non-finite")]:
        with pytest.raises(ValueError, match=match):
            Camera.from_Rt(K, R, t, 16, 12)
    for bad_K in (np.zeros((3, 3)), np.array([[20.0, 1, 8], [0, 20, 6], [0, 0, 1]]), np.array([[-20.0, 0, 8], [0, 20, 6], [0, 0, 1]])):
        with pytest.raises(ValueError, match="K must be"):
            Camera.from_Rt(bad_K, np.eye(3), np.zeros(3), 16, 12)
    for bad in (16.5, float("inf"), float("nan"), 0):
        with pytest.raises(ValueError, match="positive whole number"):
            Camera.from_Rt(K, np.eye(3), np.zeros(3), bad, 12)
    vm = cam.viewmat.clone()
    vm[:3, 3] = torch.tensor([0.3, 0.0, 0.5])
    with pytest.raises(ValueError, match="disagrees with viewmat"):
        dataclasses.replace(cam, viewmat=vm)
    moved = dataclasses.replace(cam, viewmat=vm, center=None)  # recomputed: the moved camera
    fresh = Camera.from_Rt(K, np.eye(3), [0.3, 0.0, 0.5], 16, 12)
    torch.testing.assert_close(moved.center, fresh.center)
    vm_scaled = cam.viewmat.clone()
    vm_scaled[:3, :3] *= 2
    with pytest.raises(ValueError, match="not a rotation"):
        Camera(cam.K, vm_scaled, 16, 12)
    with pytest.raises(TypeError, match="Camera viewmat must be a torch.Tensor, got ndarray"):
        Camera(cam.K, np.eye(4), 16, 12)
    # far from the origin (1e4 m) a float32 viewmat and the float64 centre agree within the tolerance
    far = Camera.from_Rt(K, np.eye(3), [1e4, -2e4, 3e4], 16, 12)
    Camera(far.K, far.viewmat, 16, 12, center=far.center)


def test_render_names_bad_params_and_options():
    from splat.rasterize import render

    cam = make_camera(dtype=torch.float32)
    params = make_params(n=5, dtype=torch.float32)
    with pytest.raises(TypeError, match=r"params\['means'\] must be a torch.Tensor, got ndarray"):
        render({k: v.numpy() for k, v in params.items()}, cam)
    with pytest.raises(ValueError, match=r"params\['quats'\] is torch.float64 on cpu, params\['means'\] torch.float32"):
        render({**params, "quats": params["quats"].double()}, cam, backend="torch")
    with pytest.raises(ValueError, match="0 < near < far"):
        render(params, cam, near=10.0, far=1.0)
    with pytest.raises(ValueError, match="max_per_pixel must be an int >= 1"):
        render(params, cam, max_per_pixel=0)
    a = render(params, cam, background=(1.0, 1.0, 1.0))  # a tuple, as TrainConfig.background
    b = render(params, cam, background=torch.ones(3))
    torch.testing.assert_close(a["rgb"], b["rgb"])
