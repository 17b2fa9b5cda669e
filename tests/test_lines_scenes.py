"""End-to-end tests of extract_line_cues on small rendered scenes (tests/lines_synth.py), with
the hard cases of issue 3: lines parallel to the epipolar direction, lines seen in only two
views, images without lines, edges that only the normal priors show, and the per-image cache."""

from __future__ import annotations

import logging

import numpy as np
import pytest

import lines_synth as synth
from geocues.lines import LineConfig, extract_line_cues
from geocues.scene import Scene


def _check_well_formed(cues, cfg: LineConfig) -> None:
    L = len(cues)
    assert np.isfinite(cues.segments).all() and np.isfinite(cues.points).all()
    assert cues.colors.shape == (L, 3) and ((cues.colors >= 0) & (cues.colors <= 1)).all()
    assert (cues.n_views >= cfg.min_views).all()
    assert all(len(v) == n and len(np.unique(v)) == n for v, n in zip(cues.views, cues.n_views))
    assert set(np.unique(cues.point_line)) == set(range(L))
    assert not cues.normals.any()
    for k in range(L):
        p = cues.points[cues.point_line == k]
        assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() <= cfg.sample_step + 1e-9


@pytest.fixture(scope="module")
def arc_scene(tmp_path_factory):
    return synth.make_scene(tmp_path_factory.mktemp("arc"), n_views=12)


def test_lines_on_the_walls_are_accurate(arc_scene, tmp_path):
    cfg = LineConfig()
    cues = extract_line_cues(Scene.load(arc_scene), cfg, tmp_path / "cache")
    _check_well_formed(cues, cfg)
    d = synth.distances_to_mesh(cues.points)
    # the painted rectangles give 16 edges, the floor tiles more
    assert len(cues) >= 10, cues.rejected
    assert np.median(d) <= 0.01 and (d <= 0.02).mean() >= 0.8, (np.median(d), (d <= 0.02).mean())
    # colour = mean over views of the image colour along the segment: check it in one view
    scene = Scene.load(arc_scene)
    for k in range(len(cues)):
        v = int(cues.views[k][0])
        uv, _ = scene.cameras[v].project(cues.points[cues.point_line == k])
        img = scene.load_image(v)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < img.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < img.shape[0])
        along = img[uv[inside, 1].astype(int), uv[inside, 0].astype(int)].mean(0)
        assert np.abs(cues.colors[k] - along).max() < 0.12, (k, cues.colors[k], along)
    assert set(cues.timings) >= {"lines_detect", "lines_pairs", "lines_match", "lines_score"}


def test_second_run_reuses_the_2d_cache(arc_scene, tmp_path):
    scene = Scene.load(arc_scene)
    first = extract_line_cues(scene, LineConfig(), tmp_path)
    assert first.per_image["cached_2d"] == 0
    assert len(list((tmp_path / "lines2d").glob("*.npz"))) == len(scene.cameras)
    second = extract_line_cues(scene, LineConfig(), tmp_path)
    assert second.per_image["cached_2d"] == len(scene.cameras)
    assert np.array_equal(first.segments, second.segments)
    third = extract_line_cues(scene, LineConfig(min_length_px=30), tmp_path)  # new key, no reuse
    assert third.per_image["cached_2d"] == 0


def test_lines_parallel_to_the_epipolar_direction_are_rejected(tmp_path):
    # cameras translate along x only and see horizontal and vertical stripes on the far wall
    root = synth.make_scene(tmp_path, n_views=8, pattern="stripes", path="x_only")
    cfg = LineConfig()
    cues = extract_line_cues(Scene.load(root), cfg)
    _check_well_formed(cues, cfg)
    assert cues.rejected["parallel_epipolar"] > 0
    u = cues.segments[:, 1] - cues.segments[:, 0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    assert len(cues) >= 4  # the vertical stripe edges
    assert (np.abs(u[:, 0]) < np.cos(np.deg2rad(20))).all(), u  # nothing along the baseline (x)
    assert np.median(synth.distances_to_mesh(cues.points)) <= 0.01


def test_lines_seen_in_only_two_views_are_rejected(tmp_path, caplog):
    root = synth.make_scene(tmp_path, n_views=2)
    cfg = LineConfig()
    with caplog.at_level(logging.INFO, logger="geocues.lines"):
        cues = extract_line_cues(Scene.load(root), cfg)
    _check_well_formed(cues, cfg)
    assert len(cues) == 0
    assert cues.rejected["few_views"] > 0  # two-view hypotheses exist, none has a third view
    assert "supporting views" in caplog.text


def test_images_without_lines(tmp_path, caplog):
    root = synth.make_scene(tmp_path, n_views=10, blank_views=(3, 7))
    cfg = LineConfig()
    with caplog.at_level(logging.INFO, logger="geocues.lines"):
        cues = extract_line_cues(Scene.load(root), cfg)
    _check_well_formed(cues, cfg)
    seg = cues.per_image["segments"]
    assert seg[3] == 0 and seg[7] == 0 and min(seg[:3]) > 0
    assert cues.rejected["images_without_segments"] == 2
    assert "has no 2D segments" in caplog.text
    assert len(cues) >= 5 and not any(3 in v or 7 in v for v in cues.views)


def test_no_lines_at_all_gives_empty_cues(tmp_path):
    root = synth.make_scene(tmp_path, n_views=4, width=160, height=120, pattern="blank", shading=False)
    cues = extract_line_cues(Scene.load(root), LineConfig())
    assert len(cues) == 0 and cues.points.shape == (0, 3)
    assert cues.rejected["images_without_segments"] == 4


def test_edges_only_visible_in_normal_priors(tmp_path):
    # blank walls without shading: the room's corner edges show in the normal maps only
    root = synth.make_scene(tmp_path, n_views=14, pattern="blank", shading=False, normals=True,
                            path="corner")
    scene = Scene.load(root)
    assert scene.has_normal_priors
    without = extract_line_cues(scene, LineConfig(use_normal_priors=False))
    assert len(without) == 0 and sum(without.per_image["segments"]) == 0
    cfg = LineConfig()
    cues = extract_line_cues(scene, cfg)
    _check_well_formed(cues, cfg)
    assert sum(cues.per_image["segments_normal"]) > 0
    assert len(cues) >= 3  # the vertical corner and the two floor edges
    d = synth.distances_to_mesh(cues.points)
    assert np.median(d) <= 0.01 and (d <= 0.02).mean() >= 0.8
