"""Plane cues first (`splat train --loss.plane-anchor --loss.plane-first --loss.plane-views all`,
preset `plane-first`): where plane cues lie, their depth replaces the aligned prior's as L_a's
anchor and is held at the least tolerance; with ``plane_views="all"`` a view takes every training
view's plane points, not only its own.

What must hold: L_a takes a per-pixel tolerance map and the plane pixels get anchor_tol_min; a
biased prior gives way to the plane depth only with plane_first; "all" covers pixels a view's own
planes miss and keeps occluded points out (nearest first); and a textureless wall rebuilt in front
of itself, whose prior agrees with the wrong place, comes back only with the plane pixels first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch

from geocues.plane_anchors import PlaneAnchors, anchor_depth
from geocues.scene import Scene
from splat.losses import LossConfig, anchored_depth_loss, total_loss

from cues_synth import make_room_scene, render as render_room
from test_plane_anchors import _median_depth_error, _moved_towards_the_cameras, _textureless_room, _train


def test_anchored_depth_loss_takes_a_tolerance_map():
    depth = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    anchor = torch.tensor([[1.1, 1.1], [0.8, 0.0]], dtype=torch.float64)
    valid = torch.ones(2, 2, dtype=torch.bool)
    tol = torch.tensor([[0.03, 0.2], [0.05, 0.03]], dtype=torch.float64)
    got = anchored_depth_loss(depth, anchor, valid, tol)
    assert float(got) == pytest.approx((0.07 + 0.0 + 0.15) / 3)  # the anchor-less pixel is not counted
    uniform = anchored_depth_loss(depth, anchor, valid, torch.full((2, 2), 0.05, dtype=torch.float64))
    assert float(uniform) == pytest.approx(float(anchored_depth_loss(depth, anchor, valid, 0.05)))
    with pytest.raises(ValueError, match=">= 0"):
        anchored_depth_loss(depth, anchor, valid, -tol)
    with pytest.raises(ValueError, match="tolerance"):
        anchored_depth_loss(depth, anchor, valid, tol[:1])


def test_total_loss_holds_the_plane_pixels_at_the_least_tolerance():
    h, w = 4, 6
    out = {"rgb": torch.zeros(h, w, 3), "depth": torch.full((h, w), 2.0), "normal": torch.zeros(h, w, 3),
           "alpha": torch.ones(h, w)}
    anchor = torch.full((h, w), 2.1)  # 10 cm off everywhere
    tight = torch.zeros(h, w, dtype=torch.bool)
    tight[:, :3] = True
    cfg = replace(LossConfig(), use_depth=False, use_normal=False, use_flat=False, use_nc=False)
    K, params, types = torch.eye(3), {"scales": torch.zeros(1, 3)}, torch.zeros(1, dtype=torch.long)
    args = (out, out["rgb"], K, params, types, cfg, 0)
    _, loose = total_loss(*args, depth_anchor=anchor, anchor_p90=0.4)  # τ = 0.2: nothing pulls
    _, held = total_loss(*args, depth_anchor=anchor, anchor_p90=0.4, anchor_tight=tight)
    assert loose["anchor"] == pytest.approx(0.0)
    assert held["anchor"] == pytest.approx(0.5 * (0.1 - cfg.anchor_tol_min), rel=1e-5)  # half the pixels, τ 3 cm
    _, none_tight = total_loss(*args, depth_anchor=anchor, anchor_p90=0.4, anchor_tight=torch.zeros_like(tight))
    assert none_tight["anchor"] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="anchor_tight"):
        total_loss(*args, depth_anchor=anchor, anchor_p90=0.4, anchor_tight=tight[:2])


@dataclass
class _BiasedAlignment:
    """A stand-in for a cue alignment whose aligned prior sits ``bias`` metres behind the truth."""

    bias: float
    residual_p90_m: float = 0.2

    def apply(self, d: np.ndarray) -> np.ndarray:
        return np.where(d > 0, d + self.bias, 0.0)


@pytest.fixture(scope="module")
def room_with_planes(tmp_path_factory):
    """The synthetic room with exact depth priors and plane points on the true surface: each view
    gets those of every 4th pixel of its left half (its right half: none of its own)."""
    root = make_room_scene(tmp_path_factory.mktemp("plane_first") / "scene", n_views=8, priors="all",
                           prior_scale=1.0, prior_shift=0.0)
    scene = Scene.load(root, downscale=2.0)
    xyz, nrm, view = [], [], []
    for k, cam in enumerate(scene.cameras):
        _, gt, _ = render_room(cam.K, cam.R, cam.t, cam.width, cam.height)
        i, j = np.mgrid[0:cam.height:4, 0:cam.width // 2:4]
        z = gt[i, j]
        ok = z > 0
        rays = np.stack([(j + 0.5 - cam.K[0, 2]) / cam.K[0, 0], (i + 0.5 - cam.K[1, 2]) / cam.K[1, 1],
                         np.ones_like(z)], -1)[ok] * z[ok, None]
        xyz.append((rays - cam.t) @ cam.R)  # camera -> world
        nrm.append(np.full((len(rays), 3), np.nan))  # no plane normal: the points' own depth
        view.append(np.full(len(rays), k))
    pa = PlaneAnchors([c.name for c in scene.cameras], np.concatenate(xyz), np.concatenate(nrm), np.concatenate(view))
    return scene, pa


def test_plane_first_replaces_a_biased_prior_and_all_views_cover_more(room_with_planes):
    from splat.views import ViewSet

    scene, pa = room_with_planes
    idx = scene.train_indices
    biased = {scene.cameras[i].name: _BiasedAlignment(0.15) for i in idx}
    fill = ViewSet(scene, idx, alignments=biased, plane_anchors=pa)
    first = ViewSet(scene, idx, alignments=biased, plane_anchors=pa, plane_first=True)
    every = ViewSet(scene, idx, alignments=biased, plane_anchors=pa, plane_first=True, plane_views="all")
    own_cov, all_cov = [], []
    for k, i in enumerate(idx):
        cam = scene.cameras[i]
        _, gt, _ = render_room(cam.K, cam.R, cam.t, cam.width, cam.height)
        ok = gt > 0
        assert fill[k].anchor_tight is None  # the prior covers every pixel: nothing to fill
        assert np.median(np.abs(fill[k].depth_anchor.numpy()[ok] - gt[ok] - 0.15)) < 0.01  # (prior: downsampled)
        for vs, cov in ((first, own_cov), (every, all_cov)):
            v = vs[k]
            tight, a = v.anchor_tight.numpy(), v.depth_anchor.numpy()
            on = tight & ok
            assert np.median(np.abs(a[on] - gt[on])) < 0.01  # the plane depth, not the prior's
            off = ~tight & ok
            assert np.median(np.abs(a[off] - gt[off] - 0.15)) < 0.01  # the prior elsewhere
            cov.append(on.mean())
        assert not first[k].anchor_tight.numpy()[:, cam.width // 2 + 1:].any()  # its own points: left half only
    assert np.mean(all_cov) > 1.3 * np.mean(own_cov), (own_cov, all_cov)
    with pytest.raises(ValueError, match="plane_views"):
        ViewSet(scene, idx, plane_anchors=pa, plane_views="every")


def test_every_views_points_keep_the_nearest_surface():
    """A point behind a nearer one in the same pixel (seen by another view through a gap) loses."""
    K = np.array([[10.0, 0, 4.0], [0, 10.0, 3.0], [0, 0, 1]])
    pa = PlaneAnchors(["a.png", "b.png", "c.png"], np.array([[0.0, 0, 3.0], [0.0, 0, 1.0], [5.0, 5.0, 1.0]]),
                      np.full((3, 3), np.nan), np.array([0, 1, 2]))
    xyz, nrm = pa.of_views(["a.png", "b.png"])
    assert len(xyz) == 2 and len(nrm) == 2  # c.png is not among the views: its point stays out
    d = anchor_depth(xyz, nrm, K, np.eye(3), np.zeros(3), 6, 8)
    assert d[3, 4] == pytest.approx(1.0) and np.count_nonzero(d) == 1


@pytest.mark.parametrize("plane_first", [False, True])
def test_a_wall_whose_prior_agrees_with_the_wrong_place_comes_back_only_with_plane_first(plane_first):
    """Flat grey Gaussians moved 8 cm towards the cameras, and an aligned prior that says the wall is
    there (a mono prior's error; its residual gives τ = 10 cm, so L_a holds the wrong place). Plane
    cues at the true depth on every other pixel, first, pull it back to within their 3 cm."""
    from splat.rasterize import render

    truth, views = _textureless_room()
    start = _moved_towards_the_cameras(truth, 0.08)
    for v in views:
        true_d = render(truth, v.camera, sh_degree=0)["median_depth"].detach()
        v.depth_anchor = render(start, v.camera, sh_degree=0)["median_depth"].detach()  # the wrong place
        v.anchor_p90 = 0.2
        if plane_first:  # what ViewSet(plane_first=True) makes of plane cues on every other pixel
            tight = torch.zeros_like(true_d, dtype=torch.bool)
            tight[::2, ::2] = true_d[::2, ::2] > 0
            v.depth_anchor = torch.where(tight, true_d, v.depth_anchor)
            v.anchor_tight = tight

    def depth_error(params) -> float:
        return _median_depth_error(params, truth, views)

    before = depth_error(start)
    params, terms = _train(start, views, replace(LossConfig(), use_nc=False))
    after = depth_error(params)
    assert before > 0.05 and all(math.isfinite(t["anchor"]) for t in terms)
    if plane_first:
        assert after < 0.045, (before, after)
    else:
        assert after > 0.8 * before, (before, after)  # the prior's anchor holds the wall where it is


def test_plane_options_that_would_do_nothing_are_refused():
    """--loss.plane-first without --loss.plane-anchor (or --loss.plane-views all without either plane
    option) changed nothing and said nothing: a run measured with it was the plain run."""
    from splat.train_config import TrainConfig

    for loss, match in (({"plane_first": True}, "plane-first .* needs --loss.plane-anchor"),
                        ({"plane_views": "all"}, "plane-views .* needs one of them")):
        cfg = TrainConfig()
        cfg.loss = replace(cfg.loss, **loss)
        with pytest.raises(ValueError, match=match):
            cfg.validate()
    cfg = TrainConfig()
    cfg.loss = replace(cfg.loss, plane_anchor=True, plane_first=True, plane_views="all")
    cfg.validate()
    cfg.loss = replace(cfg.loss, plane_anchor=False, plane_first=False, plane_normals=True)
    cfg.validate()
