"""L_mv, the multi-view photometric consistency (splat/multiview.py): a textured plane seen by two
cameras, rendered exactly by ray casting, and the hard cases (flat texture, no overlap, depth at the
near plane, a plane seen edge-on) that must leave pixels out without NaN."""

from __future__ import annotations

import math

import pytest
import torch

from splat.camera import Camera
from splat.losses import LossConfig, total_loss
from splat.multiview import multiview_ncc_loss, plane_homographies, source_view

W, H, F_PX, Z = 64, 48, 60.0, 2.0
K = torch.tensor([[F_PX, 0, W / 2], [0, F_PX, H / 2], [0, 0, 1.0]])


def texture(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return 0.5 + 0.2 * torch.sin(9 * x) * torch.cos(7 * y) + 0.15 * torch.sin(31 * x + 17 * y)


def camera(center=(0.0, 0.0, 0.0), yaw_deg: float = 0.0) -> Camera:
    a = math.radians(yaw_deg)
    R = torch.tensor([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]])
    t = -R @ torch.tensor(center)
    vm = torch.eye(4)
    vm[:3, :3], vm[:3, 3] = R, t
    return Camera(K=K.clone(), viewmat=vm, width=W, height=H)


def photo(cam: Camera, flat: bool = False) -> torch.Tensor:
    """[H, W, 3] image of the textured plane z = Z (world) seen by ``cam`` (ray casting; 0 off the plane)."""
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    rays_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    rays = rays_cam @ cam.R  # R^T applied to each row: world directions
    s = (Z - cam.center[2]) / rays[..., 2]
    pts = cam.center + s[..., None] * rays
    g = torch.full_like(s, 0.5) if flat else texture(pts[..., 0], pts[..., 1])
    g = torch.where(s > 0, g, torch.zeros_like(g))
    return g[..., None].expand(H, W, 3).contiguous()


def ref_maps(offset: float | torch.Tensor = 0.0):
    """Rendered depth and normal of the reference camera (at the origin, looking down +z) for the plane
    moved by ``offset`` along z."""
    depth = torch.full((H, W), Z) + offset
    normal = torch.zeros(H, W, 3)
    normal[..., 2] = -1.0
    return depth, normal


@pytest.fixture
def pair():
    ref, src = camera(), camera((0.25, 0.05, 0.0), yaw_deg=4.0)
    return ref, photo(ref), source_view(ref, src, photo(src))


def test_homography_sends_a_plane_point_where_the_source_camera_sees_it(pair):
    ref, _, src = pair
    depth, normal = ref_maps()
    u, v = torch.tensor([10.5, 40.5]), torch.tensor([7.5, 30.5])
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones(2)], -1)
    Hm, valid = plane_homographies(torch.full((2,), Z), normal[0, :2], rays, src, K)
    assert valid.all()
    q = Hm @ torch.stack([u, v, torch.ones(2)], -1)[..., None]
    uv = q[:, :2, 0] / q[:, 2:, 0]
    X_src = (Z * rays) @ src.R_rel.T + src.t_rel  # the plane points in the source camera
    expected = (X_src @ K.T)[:, :2] / X_src[:, 2:]
    assert torch.allclose(uv, expected, atol=1e-4)


def test_the_true_plane_scores_best_and_the_gradient_points_to_it(pair):
    _, img, src = pair
    gray = img[..., 0]
    losses = {}
    for off in (-0.1, -0.03, 0.0, 0.03, 0.1):
        d, n = ref_maps(off)
        losses[off], stats = multiview_ncc_loss(d, n, gray, K, src, n_samples=2000,
                                                generator=torch.Generator().manual_seed(0))
        assert stats["kept"] > 0.5
    assert losses[0.0] < 0.02
    assert losses[0.0] < min(losses[0.03], losses[-0.03]) < min(losses[0.1], losses[-0.1])
    for off, sign in ((0.03, 1.0), (-0.03, -1.0)):  # dL/d(offset) > 0 in front of... behind, < 0 before
        o = torch.tensor(off, requires_grad=True)
        d, n = ref_maps(o)
        loss, _ = multiview_ncc_loss(d, n, gray, K, src, n_samples=2000, generator=torch.Generator().manual_seed(1))
        loss.backward()
        assert sign * float(o.grad) > 0, (off, float(o.grad))


def _finite_zero(depth, normal, gray, src):
    depth = depth.clone().requires_grad_(True)
    normal = normal.clone().requires_grad_(True)
    loss, stats = multiview_ncc_loss(depth, normal, gray, K, src, n_samples=500,
                                     generator=torch.Generator().manual_seed(0))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(depth.grad).all() and torch.isfinite(normal.grad).all()
    return float(loss.detach()), stats["kept"], depth.grad


def test_flat_texture_is_left_out_not_nan():
    ref, src_cam = camera(), camera((0.25, 0.0, 0.0))
    src = source_view(ref, src_cam, photo(src_cam, flat=True))
    loss, kept, grad = _finite_zero(*ref_maps(), photo(ref, flat=True)[..., 0], src)
    assert loss == 0.0 and kept == 0.0 and float(grad.abs().sum()) == 0.0


def test_views_without_overlap_give_zero():
    ref, away = camera(), camera((0.0, 0.0, 0.0), yaw_deg=180.0)
    src = source_view(ref, away, photo(ref))  # any image: nothing of the plane lands in front of it
    loss, kept, _ = _finite_zero(*ref_maps(), photo(ref)[..., 0], src)
    assert loss == 0.0 and kept == 0.0


@pytest.mark.parametrize("depth_value", [0.0, 1e-5, float("nan"), float("inf")])
def test_depth_at_the_near_plane_or_not_finite_is_left_out(pair, depth_value):
    _, img, src = pair
    d, n = ref_maps()
    d[:] = depth_value
    loss, kept, _ = _finite_zero(d, n, img[..., 0], src)
    assert loss == 0.0 and kept == 0.0


def test_a_plane_seen_edge_on_is_left_out(pair):
    _, img, src = pair
    d, _ = ref_maps()
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    n = torch.nn.functional.normalize(torch.linalg.cross(rays, torch.tensor([0.0, 1.0, 0.0]).expand_as(rays)), dim=-1)
    n[:, : W // 2] = 0.0  # every ray lies in its pixel's plane; and no normal at all on the left half
    loss, kept, grad = _finite_zero(d, n, img[..., 0], src)
    assert loss == 0.0 and kept == 0.0 and float(grad.abs().sum()) == 0.0


def test_total_loss_adds_l_mv_only_when_on_and_from_its_iteration(pair):
    _, img, src = pair
    d, n = ref_maps(0.3)
    out = {"rgb": img, "depth": d, "normal": n, "alpha": torch.ones(H, W)}
    params = {"scales": torch.zeros(3, 3)}
    cue_type = torch.zeros(3, dtype=torch.long)
    base = dict(use_flat=False, use_nc=False, mv_from_iter=100)
    _, off = total_loss(out, img, K, params, cue_type, LossConfig(**base), 500, source=src)
    _, early = total_loss(out, img, K, params, cue_type, LossConfig(lambda_mv=0.15, **base), 50, source=src)
    total, on = total_loss(out, img, K, params, cue_type, LossConfig(lambda_mv=0.15, **base), 500, source=src)
    assert "mv" not in off and "mv" not in early
    assert on["mv"] > 0.05 and on["mv_kept"] > 0.5  # 30 cm off: 1 px of parallax at this baseline
    assert on["total"] == pytest.approx(on["rgb"] + 0.15 * on["mv"], rel=1e-5)
