"""Hole seeds (splat/hole_seeds.py, `splat train --init.fill-holes`, preset `fill-holes`).

What must hold: only open pixels (alpha below the threshold) with a valid anchor become points, on
the anchor's depth through the pixel centre, in world coordinates, with world normals; points of
many views average per voxel; on the synthetic room, whose cues (its SfM points) leave the walls
open, the seeds close the views (alpha) and lie on the surface; and a view set without anchors
(a prior-free scene, the no-cues baseline) seeds nothing.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geocues.cue_io import CueCloud
from geocues.scene import Scene
from geocues.types import CueType
from splat.gaussians import init_from_cues
from splat.hole_seeds import hole_seeds, view_hole_points, voxel_average

from cues_synth import ExactAlignment, distance_to_surface, make_room_scene


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def test_view_hole_points_takes_open_anchored_grid_pixels_to_the_world():
    h, w = 8, 12
    K = np.array([[10.0, 0, 6.0], [0, 10.0, 4.0], [0, 0, 1]])
    R, t = _rot_z(30.0), np.array([0.5, -1.0, 2.0])
    alpha = np.ones((h, w))
    alpha[:, :6] = 0.2  # the left half is open
    anchor = np.full((h, w), 2.0)
    anchor[1, 1], anchor[1, 3], anchor[5, 1] = 0.0, np.nan, np.inf  # invalid: skipped
    rgb = np.random.default_rng(0).random((h, w, 3))
    normal = np.zeros((h, w, 3))
    normal[..., 2] = -1.0
    xyz, col, nrm = view_hole_points(alpha, anchor, rgb, normal, K, R, t, stride=2, max_alpha=0.5)
    rows, cols = np.mgrid[1:h:2, 1:6:2]  # grid from stride // 2, left half only
    ok = ~(((rows == 1) & (cols == 1)) | ((rows == 1) & (cols == 3)) | ((rows == 5) & (cols == 1)))
    assert len(xyz) == ok.sum() == 9
    Xc = xyz @ R.T + t  # back to the camera: the pixel centres at depth 2
    np.testing.assert_allclose(Xc[:, 2], 2.0, atol=1e-12)
    uv = Xc @ K.T / Xc[:, 2:]
    np.testing.assert_allclose(np.sort(uv[:, 0] - 0.5), np.sort(cols[ok].astype(float)), atol=1e-9)
    np.testing.assert_allclose(np.sort(uv[:, 1] - 0.5), np.sort(rows[ok].astype(float)), atol=1e-9)
    np.testing.assert_allclose(col, rgb[rows[ok], cols[ok]][np.lexsort((cols[ok], rows[ok]))], atol=0)
    np.testing.assert_allclose(nrm @ R.T, np.tile([0, 0, -1.0], (9, 1)), atol=1e-12)  # world normals
    _, _, none = view_hole_points(alpha, anchor, rgb, None, K, R, t, 2, 0.5)
    assert not none.any()
    closed = view_hole_points(np.ones((h, w)), anchor, rgb, normal, K, R, t, 2, 0.5)[0]
    assert closed.shape == (0, 3)
    with pytest.raises(ValueError, match="agree"):
        view_hole_points(alpha, anchor[:4], rgb, normal, K, R, t, 2, 0.5)
    with pytest.raises(ValueError, match="stride"):
        view_hole_points(alpha, anchor, rgb, normal, K, R, t, 0, 0.5)


def test_voxel_average_means_positions_colours_and_normals():
    xyz = np.array([[0.01, 0.01, 0.01], [0.03, 0.05, 0.07], [0.51, 0.0, 0.0], [0.52, 0.0, 0.0]])
    rgb = np.array([[0.0, 0, 0], [1.0, 1, 1], [0.2, 0.2, 0.2], [0.4, 0.4, 0.4]])
    nrm = np.array([[0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0], [-1.0, 0, 0]])  # the second voxel's cancel
    p, c, n = voxel_average(xyz, rgb, nrm, 0.1)
    order = np.argsort(p[:, 0])
    p, c, n = p[order], c[order], n[order]
    np.testing.assert_allclose(p, [[0.02, 0.03, 0.04], [0.515, 0, 0]])
    np.testing.assert_allclose(c, [[0.5] * 3, [0.3] * 3])
    np.testing.assert_allclose(n, [[0, 0, 1.0], [0, 0, 0]])
    assert voxel_average(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), 0.1)[0].shape == (0, 3)
    with pytest.raises(ValueError, match="voxel"):
        voxel_average(xyz, rgb, nrm, 0.0)


@pytest.fixture(scope="module")
def sparse_room(tmp_path_factory):
    """The synthetic room with exact depth priors, and Gaussians from its SfM points only (floor and
    box): the walls and the ceiling are open in every view."""
    root = make_room_scene(tmp_path_factory.mktemp("hole_seeds") / "scene", n_views=8, priors="all",
                           prior_scale=1.0, prior_shift=0.0)
    scene = Scene.load(root, downscale=2.0)
    cloud = CueCloud.make(scene.points.xyz, scene.points.rgb, CueType.SFM)
    params, _ = init_from_cues(cloud, sh_degree=0)
    return scene, params, cloud


def _open_share(params, views) -> float:
    """Share of the views' pixels the Gaussians leave open (alpha < 0.5)."""
    from splat.rasterize import render

    with torch.no_grad():
        return float(np.mean([(render(params, views[k].camera, sh_degree=0)["alpha"] < 0.5).float().mean().item()
                              for k in range(len(views))]))


def test_seeds_close_the_open_views_on_the_surface(sparse_room):
    from splat.views import ViewSet

    scene, params, cloud = sparse_room
    names = {scene.cameras[i].name: ExactAlignment() for i in scene.train_indices}
    views = ViewSet(scene, scene.train_indices, alignments=names)
    seeds = hole_seeds(params, views, stride=4, max_alpha=0.5, voxel=0.1)
    assert len(seeds) > 100 and (seeds.cue_type == CueType.SFM.value).all()
    d = distance_to_surface(seeds.xyz)
    assert np.median(d) < 0.02 and np.mean(d < 0.05) > 0.9, np.percentile(d, [50, 90])
    assert not views.has_normal_priors and not seeds.normal.any()  # no normal prior: round seeds
    seeded, _ = init_from_cues(CueCloud.concat([cloud, seeds]), sh_degree=0)
    before, after = _open_share(params, views), _open_share(seeded, views)
    assert before > 0.3 and after < 0.25 * before, (before, after)


def test_views_without_anchors_seed_nothing(sparse_room):
    from splat.views import ViewSet

    scene, params, _ = sparse_room
    views = ViewSet(scene, scene.train_indices)  # no alignments: no L_a anchor
    assert len(hole_seeds(params, views)) == 0


def test_seeds_stay_within_the_gaussian_budget(sparse_room, caplog):
    """--strategy.max-gaussians N holds from the first step: seeds beyond the room the cues leave are
    dropped at random (a scene in another unit made 23k seeds on top of a 135k init under a 150k cap)."""
    import logging

    from splat.init_gaussians import _with_hole_seeds
    from splat.strategy import IndoorStrategyConfig
    from splat.train_config import InitConfig, TrainConfig
    from splat.views import ViewSet

    scene, params, cloud = sparse_room
    views = ViewSet(scene, scene.train_indices,
                    alignments={scene.cameras[i].name: ExactAlignment() for i in scene.train_indices})
    n_seeds = len(hole_seeds(params, views))
    free = TrainConfig(init=InitConfig(fill_holes=True), strategy=IndoorStrategyConfig(max_gaussians=0))
    p_free, _ = _with_hole_seeds(free, cloud, params, torch.zeros(len(cloud)), views)
    assert len(p_free["means"]) == len(cloud) + n_seeds
    cap = len(cloud) + n_seeds // 3
    tight = TrainConfig(init=InitConfig(fill_holes=True), strategy=IndoorStrategyConfig(max_gaussians=cap))
    with caplog.at_level(logging.INFO, logger="splat.init_gaussians"):
        p_tight, types = _with_hole_seeds(tight, cloud, params, torch.zeros(len(cloud)), views)
    assert len(p_tight["means"]) == cap == len(types)
    assert f"{n_seeds // 3} of {n_seeds} hole seeds kept" in caplog.text
