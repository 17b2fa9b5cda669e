"""The fused prior (splat/fused_prior.py, `splat train --loss.fused-anchor`, preset `fused-anchor`).

What must hold (both fusions, the TSDF and the per-pixel median): ray casting gives the z-depth of the first surface on the pixel-centre rays; the
TSDF of exact priors renders back to the true depth; priors each warped differently (a monocular
prior's error after a per-image scale and shift) fuse to an anchor far closer to the truth than any
view's own; pixels the fusion does not cover keep the view's own prior; L_d keeps the view's own
prior while L_a takes the fused one; a single aligned view fuses nothing; NaN, infinite or
negative prior pixels give finite anchors.
"""

from __future__ import annotations

import numpy as np
import pytest

from geocues.scene import Scene
from evaluation.culling import raycasting_scene
from splat.fused_prior import fuse_depths, fused_anchors, median_anchors, raycast_depth

from cues_synth import ExactAlignment, make_room_scene, render as render_room


class _WarpedAlignment:
    """An alignment stand-in whose aligned prior carries a smooth warp of its own: depth x (1 + a w),
    w a random tilt-and-bump field over the image (a different one per view)."""

    residual_p90_m = 0.05

    def __init__(self, seed: int, amplitude: float):
        self.rng, self.a = np.random.default_rng(seed), amplitude

    def apply(self, d: np.ndarray) -> np.ndarray:
        h, w = d.shape
        y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
        c = self.rng.normal(size=4)
        field = c[0] * (x - 0.5) + c[1] * (y - 0.5) + c[2] * np.cos(np.pi * x) * np.cos(np.pi * y) + 0.5 * c[3]
        field /= max(np.abs(field).max(), 1e-9)
        return np.where(d > 0, d * (1.0 + self.a * field), 0.0)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = make_room_scene(tmp_path_factory.mktemp("fused_prior") / "scene", n_views=32, priors="all",
                           prior_scale=1.0, prior_shift=0.0)
    return Scene.load(root, downscale=2.0)


def _errors(scene, anchors: dict) -> np.ndarray:
    errs = []
    for i in scene.train_indices:
        cam = scene.cameras[i]
        _, gt, _ = render_room(cam.K, cam.R, cam.t, cam.width, cam.height)
        a = anchors[cam.name]
        ok = (gt > 0) & (a > 0)
        errs.append(np.abs(a - gt)[ok])
    return np.concatenate(errs)


def test_raycast_depth_is_the_z_depth_of_the_first_surface(room):
    cam = room.cameras[0]
    _, gt, _ = render_room(cam.K, cam.R, cam.t, cam.width, cam.height)
    views = [(render_room(c.K, c.R, c.t, c.width, c.height)[1], c.K, c.world_to_camera) for c in room.cameras]
    mesh = fuse_depths(views, voxel=0.03, trunc=0.09)
    rays = raycasting_scene(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    z = raycast_depth(rays, cam.K, cam.R, cam.t, cam.height, cam.width)
    assert z.shape == (cam.height, cam.width) and z.dtype == np.float32
    ok = (gt > 0) & (z > 0)
    assert ok.mean() > 0.9 and np.median(np.abs(z - gt)[ok]) < 0.01
    away = raycast_depth(rays, cam.K, cam.R, cam.t - np.array([0.0, 0.0, 100.0]), cam.height, cam.width)
    assert not away.any()  # the room is behind this camera: no hit, 0
    with pytest.raises(ValueError, match="voxel"):
        fuse_depths(views, voxel=0.0, trunc=0.1)


def test_exact_priors_fuse_to_the_truth(room):
    idx = room.train_indices
    exact = fused_anchors(room, idx, {room.cameras[i].name: ExactAlignment() for i in idx}, voxel=0.04, trunc=0.3)
    assert set(exact) == {room.cameras[i].name for i in idx} and np.median(_errors(room, exact)) < 0.02


def test_uncovered_pixels_keep_their_own_prior_and_one_view_fuses_nothing(room, monkeypatch):
    import splat.fused_prior as fp

    idx = room.train_indices
    assert fused_anchors(room, idx, {room.cameras[idx[0]].name: ExactAlignment()}) == {}
    real = fp.raycast_depth

    def left_half_uncovered(rays, K, R, t, h, w):
        z = real(rays, K, R, t, h, w)
        z[:, : w // 2] = 0.0
        return z

    monkeypatch.setattr(fp, "raycast_depth", left_half_uncovered)
    warped = {room.cameras[i].name: _WarpedAlignment(k, 0.08) for k, i in enumerate(idx)}
    got = fused_anchors(room, idx, warped)
    for k, i in enumerate(idx[:3]):
        cam = room.cameras[i]
        own = _WarpedAlignment(k, 0.08).apply(room.depth_prior(i))
        np.testing.assert_array_equal(got[cam.name][:, : cam.width // 2], own[:, : cam.width // 2].astype(np.float32))
        assert not np.allclose(got[cam.name][:, cam.width // 2:], own[:, cam.width // 2:])


def test_views_take_the_fused_anchor_for_l_a_and_their_own_prior_for_l_d(room):
    from splat.views import ViewSet

    idx = room.train_indices
    name = room.cameras[idx[0]].name
    override = {name: np.full((room.cameras[idx[0]].height, room.cameras[idx[0]].width), 7.0, np.float32)}
    views = ViewSet(room, idx, alignments={room.cameras[i].name: ExactAlignment() for i in idx}, anchor_override=override)
    assert float(views[0].depth_anchor.max()) == pytest.approx(7.0)
    assert float(views[0].depth_prior.max()) < 6.0  # L_d: the view's own prior
    assert float(views[1].depth_anchor.max()) < 6.0  # views without an override keep their aligned prior


class _Broken:
    """An alignment whose aligned prior has NaN, Inf, negative and zero pixels (a bad prior file)."""

    residual_p90_m = 0.01

    def apply(self, d: np.ndarray) -> np.ndarray:
        out = d.astype(np.float64).copy()
        out[0, :] = np.nan
        out[1, :] = np.inf
        out[2, :] = -1.0
        out[:, :5] = 0.0
        return out


def test_bad_prior_pixels_give_finite_anchors(room):
    idx = room.train_indices
    got = fused_anchors(room, idx, {room.cameras[i].name: _Broken() for i in idx}, voxel=0.04, trunc=0.3)
    assert set(got) == {room.cameras[i].name for i in idx}
    for a in got.values():
        assert np.isfinite(a).all() and (a >= 0).all()
        assert (a[3:, 5:] > 0).mean() > 0.9  # the good pixels still have a depth


@pytest.mark.parametrize("method", ["tsdf", "median"])
def test_both_fusions_beat_the_views_own_warped_priors(room, method):
    idx = room.train_indices
    warped = {room.cameras[i].name: _WarpedAlignment(k, 0.08) for k, i in enumerate(idx)}
    own = {room.cameras[i].name: _WarpedAlignment(k, 0.08).apply(room.depth_prior(i)) for k, i in enumerate(idx)}
    fused = fused_anchors(room, idx, warped, voxel=0.04, trunc=0.3, method=method, neighbours=16)
    e_own, e_fused = _errors(room, own), _errors(room, fused)
    # measured: 4.4 -> 2.2 cm median (tsdf); without fusion the ratio is 1
    assert np.median(e_fused) < 0.6 * np.median(e_own), (method, np.median(e_own), np.median(e_fused))


def test_median_anchors_fall_back_to_the_own_prior_without_votes(room):
    i, j = room.train_indices[:2]
    far = {i: room.depth_prior(i).astype(np.float32), j: np.zeros_like(room.depth_prior(j), np.float32)}
    got = median_anchors(room, far, neighbours=4, min_votes=3)  # one real vote per pixel at most
    np.testing.assert_array_equal(got[room.cameras[i].name], far[i])
    with pytest.raises(ValueError, match="method"):
        fused_anchors(room, room.train_indices, {room.cameras[k].name: ExactAlignment() for k in room.train_indices},
                      method="mean")
