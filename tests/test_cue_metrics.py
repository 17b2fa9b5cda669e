"""evaluation.cue_metrics: cue distances to a known surface and coverage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from evaluation.cue_metrics import CueMetricsConfig, GroundTruth, coverage, cue_accuracy
from geocues.cue_io import CueCloud
from geocues.scene import Camera
from geocues.types import CueType


def _wall(tmp_path: Path) -> Path:
    """A 2 m x 2 m square in the plane z = 3 (seen head-on by the camera below)."""
    mesh = o3d.geometry.TriangleMesh()
    mesh.vertices = o3d.utility.Vector3dVector(np.array([[-1, -1, 3], [1, -1, 3], [1, 1, 3], [-1, 1, 3.0]]))
    mesh.triangles = o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]]))
    path = tmp_path / "wall.ply"
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def _camera() -> Camera:
    K = np.array([[100.0, 0, 100], [0, 100, 100], [0, 0, 1]])  # 200 x 200 px sees [-3, 3] m at z = 3
    return Camera(index=0, image_id=1, name="a.png", image_path=Path("a.png"), width=200, height=200,
                  K=K, R=np.eye(3), t=np.zeros(3))


def test_known_offsets_and_coverage(tmp_path):
    cfg = CueMetricsConfig(n_gt_samples=5000, coverage_dist=0.05)
    gt = GroundTruth(_wall(tmp_path), [_camera()], cfg)
    assert gt.seen_fraction == pytest.approx(1.0)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, size=(400, 2))
    # LINE points 5 mm off the wall, PLANE points 4 cm off it: exact distances 0.005 and 0.04.
    line = CueCloud.make(np.c_[xy[:200], np.full(200, 3.005)], np.zeros((200, 3)), CueType.LINE)
    plane = CueCloud.make(np.c_[xy[200:], np.full(200, 2.96)], np.zeros((200, 3)), CueType.PLANE)
    res = cue_accuracy(CueCloud.concat([line, plane]), gt, cfg)
    assert res["per_type"]["LINE"]["median_m"] == pytest.approx(0.005, abs=1e-6)
    assert res["per_type"]["LINE"]["within_1cm"] == 1.0
    assert res["per_type"]["PLANE"]["median_m"] == pytest.approx(0.04, abs=1e-6)
    assert res["per_type"]["PLANE"]["within_3cm"] == 0.0
    assert res["per_type"]["PLANE"]["within_5cm"] == 1.0
    assert res["per_type"]["SFM"]["n"] == 0 and res["coverage"]["SFM"] == 0.0
    # 200 random points over 4 m^2 leave gaps wider than 5 cm: coverage strictly between 0 and 1.
    assert 0.0 < res["coverage"]["LINE"] < 1.0
    assert res["coverage"]["ALL"] >= res["coverage"]["LINE"]


def test_coverage_of_a_dense_grid_is_complete():
    g = np.stack(np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41)), -1).reshape(-1, 2)
    pts = np.c_[g, np.full(len(g), 3.0)]  # 5 cm grid: every sample within 3.6 cm of a node
    samples = np.c_[np.random.default_rng(1).uniform(-1, 1, (1000, 2)), np.full(1000, 3.0)]
    assert coverage(pts, samples, 0.05) == 1.0
    assert coverage(pts, samples, 0.01) < 0.5
    assert coverage(np.zeros((0, 3)), samples, 0.05) == 0.0


def test_missing_cues_file_names_the_folder(tmp_path):
    from evaluation.cue_metrics import evaluate_cues_dir

    with pytest.raises(FileNotFoundError, match=str(tmp_path)):
        evaluate_cues_dir(tmp_path, tmp_path)


def _room_and_its_sfm_cues(tmp_path):
    """A 4-view room with GT and a cue folder holding its SfM points as cues: (root, scene, cues)."""
    from cues_synth import make_room_scene
    from geocues.cue_io import write_cues_ply
    from geocues.scene import Scene

    from test_ablate import write_gt

    root = make_room_scene(tmp_path / "room", n_views=4, w=64, h=48, priors="none")
    write_gt(root)
    scene = Scene.load(root)
    cues = tmp_path / "cues"
    write_cues_ply(cues / "cues.ply", CueCloud.make(scene.points.xyz, np.zeros((len(scene.points), 3), np.uint8),
                                                    CueType.SFM))
    return root, scene, cues


def test_cues_of_another_scene_are_scored_with_a_warning(tmp_path, caplog):
    """`evaluate cues CUES SCENE` with cues from a rescaled copy scored them in silence (`splat train`
    warned): the same camera check names the mismatch."""
    import json
    import logging

    from evaluation.cue_metrics import evaluate_cues_dir
    from geocues.camera_signature import camera_signature

    root, scene, cues = _room_and_its_sfm_cues(tmp_path)
    for spread, warned in ((1.0, False), (10.0, True)):  # the scene's own cameras, a copy 10x the size
        sig = camera_signature(scene)
        (cues / "report.json").write_text(json.dumps({"cameras": {**sig, "spread": sig["spread"] * spread}}))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="evaluation"):
            result = evaluate_cues_dir(cues, root)
        assert ("extracted from another scene" in caplog.text) == warned and result["per_type"]


def test_cues_named_by_their_report_as_another_scene_s_are_warned_and_bad_options_refused(tmp_path, caplog):
    """A room's cues scored against ICL gave a 2263 mm median without a word (the cameras' check let
    them pass); --coverage-dist -1 printed 'within -100 cm'."""
    import json
    import logging

    from cues_synth import make_room_scene
    from evaluation.cue_metrics import CueMetricsConfig, evaluate_cues_dir

    root, _, cues = _room_and_its_sfm_cues(tmp_path)
    other = make_room_scene(tmp_path / "other", n_views=4, w=64, h=48, priors="none")
    for source, warned in ((root, False), (other, True)):
        (cues / "report.json").write_text(json.dumps({"scene": str(source)}))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="evaluation"):
            evaluate_cues_dir(cues, root)
        assert (f"were extracted from {other} (its report.json), not" in caplog.text) == warned, caplog.text
    for bad in ({"coverage_dist": -1.0}, {"coverage_dist": float("nan")}, {"occlusion_tolerance": float("inf")}):
        with pytest.raises(ValueError, match="must be a finite distance"):
            evaluate_cues_dir(cues, root, cfg=CueMetricsConfig(**bad))
