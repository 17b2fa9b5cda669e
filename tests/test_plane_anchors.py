"""Plane anchors (geocues.plane_anchors, `splat train --loss.plane-anchor`): each image's own plane
cues as an anchor for L_a where the image has no depth prior.

What must hold: points fall in the COLMAP pixel containing their projection, nearest first; the file
round-trips and names its fix when missing; `geocues extract` writes anchors that lie on the
surface in the image that made them (a prior-free scene, where L_a had nothing before); the views
of a prior-free scene get anchors from them; and L_a through them pulls a textureless wall rebuilt
in front of itself back, which the RGB loss alone does not. The same points' normals
(`--loss.plane-normals`) become the normal prior of views that have none, facing the camera, and L_n
through them turns tilted textureless Gaussians back flat, which the RGB loss alone does not.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

import geocues.extract as ex
from geocues.plane_anchors import (PlaneAnchors, anchor_depth, anchor_normals, load_plane_anchors,
                                   write_plane_anchors)
from geocues.scene import Scene

from cues_synth import fake_line_cues, make_room_scene, render as render_room


def test_anchor_depth_pixel_convention_zbuffer_and_culling():
    K = np.array([[10.0, 0, 4.0], [0, 10.0, 3.0], [0, 0, 1]])
    R, t = np.eye(3), np.zeros(3)
    pts = np.array([
        [0.0, 0.0, 2.0],     # u = 4.0, v = 3.0 -> pixel (3, 4)
        [0.0, 0.0, 1.5],     # same pixel, nearer: wins
        [-0.0005, 0.0, 1.0],  # u = 3.995 -> column 3 (the pixel containing it), row 3
        [0.0, 0.0, -1.0],    # behind the camera
        [1.0, 0.0, 1.0],     # u = 14: outside an 8-wide image
    ])
    d = anchor_depth(pts, None, K, R, t, 6, 8)
    assert d.shape == (6, 8) and d.dtype == np.float32
    assert d[3, 4] == pytest.approx(1.5) and d[3, 3] == pytest.approx(1.0)
    assert np.count_nonzero(d) == 2
    assert not anchor_depth(np.zeros((0, 3)), None, K, R, t, 6, 8).any()


def test_anchor_depth_with_normals_is_the_planes_depth_at_the_pixel_centre():
    """A floor seen at a slant: z = 2 + x (plane x - z + 2 = 0). A point at u = 4.9 belongs to the
    pixel whose centre is at u = 4.5; its anchor is the plane's depth on that centre's ray."""
    K = np.array([[10.0, 0, 4.0], [0, 10.0, 3.0], [0, 0, 1]])
    n = np.array([[1.0, 0.0, -1.0]]) / np.sqrt(2)
    x = 0.09 * 2 / (1 - 0.09)  # on the plane and on the ray u = 4.9 (x / z = 0.09)
    p = np.array([[x, 0.0, 2 + x]])
    d = anchor_depth(p, n, K, np.eye(3), np.zeros(3), 6, 8)
    z_centre = 2 / (1 - 0.05)  # ray x / z = 0.05 meets x = z - 2
    assert d[3, 4] == pytest.approx(z_centre, rel=1e-6) and abs(z_centre - p[0, 2]) > 0.08
    assert anchor_depth(p, None, K, np.eye(3), np.zeros(3), 6, 8)[3, 4] == pytest.approx(p[0, 2], rel=1e-6)
    grazing = anchor_depth(p, np.array([[0.0, 1.0, 0.0]]), K, np.eye(3),
                           np.zeros(3), 6, 8)  # plane y = 0 holds the ray: the point's own depth
    assert grazing[3, 4] == pytest.approx(p[0, 2], rel=1e-6)


def test_file_round_trip_and_a_folder_without_it(tmp_path):
    xyz = np.arange(15, dtype=np.float32).reshape(5, 3)
    nrm = np.tile(np.float32([0, 0, 1]), (5, 1))
    write_plane_anchors(tmp_path, ["a.png", "b.png", "c.png"], xyz, nrm, np.array([2, 0, 2, 0, 0]))
    pa = load_plane_anchors(tmp_path / "cues.ply")  # a file in the folder works too
    assert pa.counts() == {"a.png": 3, "b.png": 0, "c.png": 2}
    np.testing.assert_array_equal(pa.of("c.png")[0], xyz[[0, 2]])
    np.testing.assert_array_equal(pa.of("c.png")[1], nrm[[0, 2]])
    assert pa.of("b.png")[0].shape == (0, 3) and pa.of("unknown.png")[1].shape == (0, 3)
    with pytest.raises(ValueError, match="view index"):
        PlaneAnchors(["a.png"], xyz, nrm, np.array([0, 1, 0, 0, 0]))
    (tmp_path / "old_cues").mkdir()
    with pytest.raises(FileNotFoundError, match="geocues extract"):
        load_plane_anchors(tmp_path / "old_cues")


@pytest.fixture(scope="module")
def prior_free_cues(tmp_path_factory):
    """A synthetic room without depth priors and its extracted cues (exact room edges as lines)."""
    root = tmp_path_factory.mktemp("plane_anchors")
    scene = make_room_scene(root / "scene", n_views=16, priors="none")
    mp = pytest.MonkeyPatch()
    mp.setattr(ex, "_run_lines", lambda scene, cfg, cache: fake_line_cues(scene.cameras))
    try:
        cues = ex.run(None, scene, root / "cues")
    finally:
        mp.undo()
    return scene, cues


def test_extract_writes_anchors_on_the_surface_in_their_own_image(prior_free_cues):
    scene_dir, cues = prior_free_cues
    scene = Scene.load(scene_dir)
    pa = load_plane_anchors(cues)
    counts = pa.counts()
    assert sorted(counts) == sorted(c.name for c in scene.cameras)
    report = json.loads((cues / "report.json").read_text())
    assert sum(counts.values()) == report["n_plane_anchors"] > 0
    made = {r["name"] for r in report["per_image"] if r.get("plane_points", 0) > 0}
    assert {n for n, c in counts.items() if c} <= made  # an image anchors only points its own planes made
    errs, covered = [], []
    for cam in scene.cameras:
        pts, nrm = pa.of(cam.name)
        if not len(pts):
            continue
        d = anchor_depth(pts, nrm, cam.K, cam.R, cam.t, cam.height, cam.width)
        _, gt, _ = render_room(cam.K, cam.R, cam.t, cam.width, cam.height)
        hit = d > 0
        errs.append(np.abs(d[hit] - gt[hit]))
        covered.append(hit.sum() / len(pts))
    err = np.concatenate(errs)
    assert np.mean(err < 0.03) > 0.9, np.percentile(err, [50, 90])  # what the plane cues promise
    assert min(covered) > 0.5, covered  # they were cut from this image's pixels: they land in it


def test_views_of_a_prior_free_scene_get_plane_anchors(prior_free_cues):
    from splat.views import ViewSet

    scene_dir, cues = prior_free_cues
    scene = Scene.load(scene_dir, downscale=2.0)  # training resolution differs from the extract's
    without = ViewSet(scene, scene.train_indices)
    assert all(without[k].depth_anchor is None for k in range(len(without)))
    pa = load_plane_anchors(cues)
    views = ViewSet(scene, scene.train_indices, plane_anchors=pa)
    anchored = [views[k] for k in range(len(views)) if views[k].depth_anchor is not None]
    assert {v.name for v in anchored} == {views[k].name for k in range(len(views)) if len(pa.of(views[k].name)[0])} != set()
    for v in anchored:
        cam = scene.cameras[v.index]
        assert tuple(v.depth_anchor.shape) == (cam.height, cam.width) and math.isnan(v.anchor_p90)
        _, gt, _ = render_room(cam.K, cam.R, cam.t, cam.width, cam.height)
        a = v.depth_anchor.numpy()
        assert np.median(np.abs(a[a > 0] - gt[a > 0])) < 0.02


def _textureless_room():
    """Flat, opaque, grey Gaussians on the synthetic room's surfaces and prior-free views of them."""
    from splat.bench import surface_gaussians, target_views

    truth = surface_gaussians(3000, sh_degree=0, seed=2)
    truth["sh0"] = torch.full_like(truth["sh0"], 0.3)  # textureless
    truth["opacities"] = torch.full_like(truth["opacities"], 4.0)
    views = target_views(truth, 48, 36, sh_degree=0)
    for v in views:
        v.depth_prior = v.normal_prior = v.depth_anchor = None  # prior-free
    return truth, views


def _train(start: dict, views: list, loss_cfg, iters: int = 80) -> tuple[torch.nn.ParameterDict, list[dict]]:
    """``iters`` training steps from the Gaussians ``start`` (no density control); returns them and
    each step's loss terms (every loss finite)."""
    from splat.strategy import IndoorStrategy, IndoorStrategyConfig
    from splat.train import LearningRates, TrainConfig, make_optimizers, train_step

    params = torch.nn.ParameterDict({k: torch.nn.Parameter(t) for k, t in start.items()})
    optimizers = make_optimizers(params, LearningRates(), 3.0)
    strategy = IndoorStrategy(IndoorStrategyConfig(total_iters=iters, refine_stop=0, max_gaussians=0))
    state = strategy.initialize_state(3.0)
    state["cue_type"] = torch.full((len(params["means"]),), 2)
    cfg, g, terms = TrainConfig(iters=iters, sh_degree=0), torch.Generator().manual_seed(0), []
    for step in range(iters):
        loss, t, _ = train_step(params, optimizers, strategy, state, views[step % len(views)], step, 0, cfg, loss_cfg, g)
        assert math.isfinite(float(loss))
        terms.append(t)
    return params, terms


def _moved_towards_the_cameras(truth: dict, dist: float) -> dict:
    """A copy of the Gaussians ``truth`` with every mean moved ``dist`` m towards the training eyes."""
    from splat.bench import TRAIN_EYES

    eye = torch.tensor(TRAIN_EYES, dtype=torch.float32).mean(0)
    start = {k: t.clone() for k, t in truth.items()}
    to_eye = eye - start["means"]
    start["means"] += dist * to_eye / to_eye.norm(dim=1, keepdim=True)
    return start


def _median_depth_error(params: dict, truth: dict, views: list) -> float:
    """Median |median depth of ``params`` - that of ``truth``| over the views' covered pixels (m)."""
    from splat.rasterize import render

    with torch.no_grad():
        errs = []
        for v in views:
            d, t = render(params, v.camera, sh_degree=0)["median_depth"], render(truth, v.camera, sh_degree=0)
            ok = t["alpha"] > 0.5
            errs.append((d - t["median_depth"]).abs()[ok])
        return float(torch.cat(errs).median())


@pytest.mark.parametrize("plane_anchor", [False, True])
def test_a_textureless_wall_in_front_of_itself_comes_back_only_with_plane_anchors(plane_anchor):
    """Flat grey Gaussians on the room's surfaces, all moved 8 cm towards the cameras: the images
    look the same (no texture), so the RGB loss cannot see the error; anchors at the true depth on
    every other pixel (a plane cue's sampling) pull the surface back to within L_a's tolerance."""
    from splat.losses import LossConfig
    from splat.rasterize import render

    truth, views = _textureless_room()
    for v in views:
        if plane_anchor:  # what ViewSet makes of a plane cue sampled on every other pixel
            d = render(truth, v.camera, sh_degree=0)["median_depth"].detach()
            v.depth_anchor = torch.zeros_like(d)
            v.depth_anchor[::2, ::2] = d[::2, ::2]
    start = _moved_towards_the_cameras(truth, 0.08)

    def depth_error(params) -> float:
        return _median_depth_error(params, truth, views)

    before = depth_error(start)
    params, _ = _train(start, views, replace(LossConfig(), use_nc=False, plane_anchor=plane_anchor))
    after = depth_error(params)
    assert before > 0.05
    if plane_anchor:
        assert after < 0.045, (before, after)  # back to within L_a's 3 cm tolerance (+ margin)
    else:
        assert after > 0.8 * before, (before, after)  # RGB alone leaves the wall where it is


def test_anchor_depth_hard_cases_stay_finite():
    """NaN or infinite points, zero normals, points on the camera plane or behind it: dropped or
    given their own depth, never NaN in the map."""
    K = np.array([[10.0, 0, 4.0], [0, 10.0, 3.0], [0, 0, 1]])
    pts = np.array([[np.nan, 0, 1], [0, 0, np.inf], [0.1, 0.1, 0.0], [0, 0, -2], [0.0, 0.0, 1.0],
                    [0.01, 0.0, 1.0]])
    nrm = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 0], [np.nan, 0, 0]], float)
    d = anchor_depth(pts, nrm, K, np.eye(3), np.zeros(3), 6, 8)
    assert np.isfinite(d).all()
    assert d[3, 4] == pytest.approx(1.0)  # the zero- and NaN-normal points keep their own depth
    assert np.count_nonzero(d) == 1


def test_anchor_normals_face_the_camera_nearest_first_and_skip_bad_points():
    K = np.array([[10.0, 0, 4.0], [0, 10.0, 3.0], [0, 0, 1]])
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.5], [-0.0005, 0.0, 1.0], [0.0, 0.0, -1.0],
                    [np.nan, 0.0, 1.0], [0.1, 0.1, 1.0], [0.2, 0.2, 1.0]])
    nrm = np.array([[1.0, 0, 0], [0, 0, 2.0], [0, 0, -1.0], [0, 0, 1.0], [0, 0, 1.0], [0, 0, 0], [np.inf, 0, 0]])
    n = anchor_normals(pts, nrm, K, np.eye(3), np.zeros(3), 6, 8)
    assert n.shape == (6, 8, 3) and n.dtype == np.float32 and np.isfinite(n).all()
    np.testing.assert_allclose(n[3, 4], [0, 0, -1])  # the nearer point's normal, unit, turned to the camera
    np.testing.assert_allclose(n[3, 3], [0, 0, -1])  # already facing it: kept
    assert np.count_nonzero(np.abs(n).sum(-1)) == 2  # behind, NaN point, zero and infinite normals: nothing
    # a rotated camera: the normal is expressed in its frame
    R = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # world +x is the camera's viewing direction
    n = anchor_normals(np.array([[2.0, 0, 0]]), np.array([[1.0, 0, 0]]), K, R, np.zeros(3), 6, 8)
    np.testing.assert_allclose(n[3, 4], [0, 0, -1], atol=1e-12)
    with pytest.raises(ValueError, match="normals"):
        anchor_normals(pts, nrm[:2], K, np.eye(3), np.zeros(3), 6, 8)


def _depth_normals(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame normals of a z-depth map by central differences (zeros on edges / invalid)."""
    h, w = depth.shape
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    P = np.stack([(j - K[0, 2]) / K[0, 0], (i - K[1, 2]) / K[1, 1], np.ones_like(j)], -1) * depth[..., None]
    n = np.zeros_like(P)
    n[1:-1, 1:-1] = np.cross(P[1:-1, 2:] - P[1:-1, :-2], P[2:, 1:-1] - P[:-2, 1:-1])
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    return np.where(np.sum(n * P, -1, keepdims=True) > 0, -n, n)


def test_views_without_a_normal_prior_get_their_plane_normals(prior_free_cues):
    from splat.views import ViewSet

    scene_dir, cues = prior_free_cues
    scene = Scene.load(scene_dir, downscale=2.0)
    pa = load_plane_anchors(cues)
    without = ViewSet(scene, scene.train_indices)
    assert all(without[k].normal_prior is None for k in range(len(without)))
    views = ViewSet(scene, scene.train_indices, plane_normals=pa)
    got = [views[k] for k in range(len(views)) if views[k].normal_prior is not None]
    assert {v.name for v in got} == {views[k].name for k in range(len(views)) if len(pa.of(views[k].name)[0])} != set()
    assert all(v.depth_anchor is None for v in got)  # normals only: L_a's anchors are a separate option
    cos = []
    for v in got:
        cam = scene.cameras[v.index]
        n = v.normal_prior.numpy()
        assert n.shape == (cam.height, cam.width, 3)
        _, gt, _ = render_room(cam.K, cam.R, cam.t, cam.width, cam.height)
        ref = _depth_normals(gt, cam.K)
        hit = (np.abs(n).sum(-1) > 0) & (np.abs(ref).sum(-1) > 0)
        np.testing.assert_allclose(np.linalg.norm(n[hit], axis=-1), 1.0, atol=1e-3)
        cos.append(np.sum(n[hit] * ref[hit], -1))
    cos = np.concatenate(cos)
    assert np.median(cos) > np.cos(np.radians(3)) and np.mean(cos > np.cos(np.radians(15))) > 0.9


@pytest.mark.parametrize("plane_normals", [False, True])
def test_tilted_textureless_gaussians_turn_flat_only_with_plane_normals(plane_normals):
    """Flat grey Gaussians on the room's surfaces, each turned 40 degrees about a random axis: without
    texture the images barely change, so the RGB loss leaves the tilt; the plane normals on every
    other pixel (what ViewSet makes of a plane cue) turn them back through L_n."""
    from splat.losses import LossConfig
    from splat.rasterize import render

    truth, views = _textureless_room()
    for v in views:
        if plane_normals:
            n = render(truth, v.camera, sh_degree=0)["normal"].detach()
            v.normal_prior = torch.zeros_like(n)
            v.normal_prior[::2, ::2] = n[::2, ::2]
    g = torch.Generator().manual_seed(1)
    axis = torch.randn(len(truth["quats"]), 3, generator=g)
    axis = axis / axis.norm(dim=1, keepdim=True)
    half = math.radians(40) / 2
    w1, v1 = torch.full((len(axis), 1), math.cos(half)), math.sin(half) * axis  # the turn, wxyz
    q = truth["quats"] / truth["quats"].norm(dim=1, keepdim=True)
    w2, v2 = q[:, :1], q[:, 1:]
    start = {k: t.clone() for k, t in truth.items()}
    start["quats"] = torch.cat([w1 * w2 - (v1 * v2).sum(1, keepdim=True),
                                w1 * v2 + w2 * v1 + torch.cross(v1, v2, dim=1)], 1)

    def normal_error(params) -> float:
        with torch.no_grad():
            errs = []
            for v in views:
                out, ref = render(params, v.camera, sh_degree=0), render(truth, v.camera, sh_degree=0)
                cos = (out["normal"] * ref["normal"]).sum(-1).clamp(-1, 1)[ref["alpha"] > 0.5]
                errs.append(torch.rad2deg(torch.acos(cos)))
            return float(torch.cat(errs).median())

    before = normal_error(start)
    params, terms = _train(start, views, replace(LossConfig(), use_nc=False, lambda_anchor=0.0))
    assert all(("normal" in t) == plane_normals for t in terms)
    after = normal_error(params)
    assert before > 15
    if plane_normals:
        assert after < 0.5 * before, (before, after)  # measured: 17.8 -> 3.0 degrees
    else:
        assert after > 0.8 * before, (before, after)  # RGB alone leaves the tilt (17.8 -> 16.5)


def test_plane_normal_rows_are_na_where_every_view_has_a_normal_prior():
    """`splat ablate` does not train `plane-normals` where it would be `full` again under another name."""
    from splat.presets import get_preset, missing_needs

    for row in ("plane-normals", "mv-plane-normals"):
        p = get_preset(row)
        assert missing_needs(p, True, True, True, all_normal_priors=False) is None  # some views lack one
        assert missing_needs(p, False, False, True) is None  # prior-free: what it is for
        assert "every view has a normal prior" in missing_needs(p, True, True, True, all_normal_priors=True)
        assert "plane anchors" in missing_needs(p, False, False, False)
