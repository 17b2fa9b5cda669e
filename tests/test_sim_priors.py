"""`evaluate simulate-priors`: simulated priors for a scene with exact depth, marked simulated,
within the simulated error of the truth once the per-image scale and shift are undone."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cues_synth import make_room_scene, render
from geocues.scene import Scene
from test_ablate import write_gt


def normals_from_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame normals of the exact depth by central differences (0 at borders and edges),
    facing the camera: an oracle independent of the mesh ray casting under test."""
    h, w = depth.shape
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    P = np.stack([(j - K[0, 2]) / K[0, 0] * depth, (i - K[1, 2]) / K[1, 1] * depth, depth], -1)
    n = np.zeros_like(P)
    n[1:-1, 1:-1] = np.cross(P[1:-1, 2:] - P[1:-1, :-2], P[2:, 1:-1] - P[:-2, 1:-1])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n = np.where((np.einsum("hwc,hwc->hw", n, P) > 0)[..., None], -n, n)
    smooth = np.zeros((h, w), bool)
    smooth[1:-1, 1:-1] = np.abs(depth[1:-1, 2:] + depth[1:-1, :-2] - 2 * depth[1:-1, 1:-1]) < 0.01
    return np.where(smooth[..., None], n, 0.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = make_room_scene(tmp_path_factory.mktemp("sim") / "room", n_views=4, w=64, h=48, priors="none")
    write_gt(root)
    return root


def test_priors_follow_the_truth_up_to_the_simulated_errors(scene, tmp_path):
    from evaluation.sim_priors import SimPriorsConfig, simulate_scene_priors

    out = simulate_scene_priors(scene, tmp_path / "sim", SimPriorsConfig(seed=3))
    meta = json.loads((out / "scene.json").read_text())["priors"]
    assert meta["simulated"] is True and meta["seed"] == 3 and len(meta["per_image"]) == 4
    # a source room's own prior settings (make-room's config.priors) are replaced by the ones used
    src = tmp_path / "room_src"
    shutil.copytree(scene, src)
    (src / "scene.json").write_text(json.dumps({"seed": 7, "config": {"seed": 7, "priors": {"depth_warp": 9.0}}}))
    other = json.loads((simulate_scene_priors(src, tmp_path / "sim2", SimPriorsConfig(seed=3)) / "scene.json").read_text())
    assert other["config"]["priors"] == other["priors"]["config"] == SimPriorsConfig().priors.to_dict()
    assert other["seed"] == other["config"]["seed"] == 7  # the room's own seed stays (its layout's)
    loaded = Scene.load(out)
    assert loaded.has_depth_priors and loaded.has_normal_priors
    warp = meta["config"]["depth_warp"]
    for cam in loaded.cameras:
        _, depth, _ = render(cam.K, cam.R, cam.t, cam.width, cam.height)
        normal = normals_from_depth(depth, cam.K)
        prior = np.load(out / "priors" / "depth" / f"{cam.stem}.npy")
        par = meta["per_image"][cam.stem]["depth"]
        valid = (depth > 0) & (prior > 0)
        undone = (prior[valid] - par["shift"]) / par["scale"]
        rel = np.abs(undone / depth[valid] - 1.0)
        assert np.median(rel) < 1.5 * warp and np.percentile(rel, 90) < 3.5 * warp + 0.02
        n = np.load(out / "priors" / "normal" / f"{cam.stem}.npy")
        ok = (np.linalg.norm(n, axis=-1) > 0.5) & (np.linalg.norm(normal, axis=-1) > 0.5)
        assert ok.mean() > 0.7
        angle = np.degrees(np.arccos(np.clip(np.einsum("hwc,hwc->hw", n, normal)[ok], -1, 1)))
        assert np.median(angle) < 10.0  # blur, ~3 degree tilt and noise; a flipped axis gives ~180


def test_a_scene_without_exact_depth_is_a_clear_error(scene, tmp_path):
    from evaluation.sim_priors import SimPriorsConfig, simulate_scene_priors

    with pytest.raises(FileNotFoundError, match="GT depth"):
        simulate_scene_priors(scene, tmp_path / "a", SimPriorsConfig(gt_depth=tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match="GT mesh"):
        simulate_scene_priors(scene, tmp_path / "b", SimPriorsConfig(gt_mesh=tmp_path / "none.ply"))
    (tmp_path / "c").mkdir()
    with pytest.raises(ValueError, match="already exists"):
        simulate_scene_priors(scene, tmp_path / "c")


def test_a_root_reference_mesh_goes_along(scene, tmp_path):
    """ICL-NUIM keeps its GT as reference_mesh.ply at the root: OUT used to lose it (`gt mesh none`,
    and `evaluate cues CUES OUT` asked for --gt), as `geocues sfm -o` and `mvs` did not."""
    import shutil

    from evaluation.sim_priors import SimPriorsConfig, simulate_scene_priors

    icl_like = tmp_path / "icl_like"
    shutil.copytree(scene, icl_like, symlinks=True)
    (icl_like / "gt" / "mesh.ply").rename(icl_like / "reference_mesh.ply")
    out = simulate_scene_priors(icl_like, tmp_path / "sim", SimPriorsConfig(seed=3))
    gt = Scene.load(out).gt_mesh_path
    assert gt is not None and gt.resolve() == (icl_like / "reference_mesh.ply").resolve()
    assert Path(json.loads((out / "scene.json").read_text())["priors"]["gt_depth"]).is_absolute()


def test_the_floor_finds_the_exact_depth_a_simulated_scene_records(scene, tmp_path):
    """ICL keeps its exact depth in depth/, not gt/depth: a simulate-priors scene of it records the
    folder (and its PNG scale), but `splat ablate` looked for gt/depth only and its table had no floor."""
    import shutil

    from evaluation.sim_priors import SimPriorsConfig, simulate_scene_priors
    from splat.floor import find_gt_depth_dir, recorded_gt_depth

    icl_like = tmp_path / "icl_like"
    shutil.copytree(scene, icl_like, symlinks=True)
    (icl_like / "gt" / "depth").rename(icl_like / "depth")
    out = simulate_scene_priors(icl_like, tmp_path / "sim", SimPriorsConfig(seed=3, gt_depth=icl_like / "depth",
                                                                           gt_depth_png_scale=5000.0))
    assert find_gt_depth_dir(out) is None  # not in the scene's own gt/
    folder, png = recorded_gt_depth(out)
    assert folder.resolve() == (icl_like / "depth").resolve() and png == 5000.0
    shutil.rmtree(icl_like / "depth")
    assert recorded_gt_depth(out) is None  # gone: no floor, and a warning says so


def test_impossible_prior_settings_are_named(scene, tmp_path, capsys):
    """A scale min above its max ended with numpy's 'high - low < 0'."""
    from cli.evaluate_cli import main

    assert main(["simulate-priors", str(scene), "-o", str(tmp_path / "sim"), "--priors.depth-scale-min", "2",
                 "--priors.depth-scale-max", "1"]) == 1
    assert "--priors.depth-scale-min must be > 0 and <= --priors.depth-scale-max, got 2.0 and 1.0" in capsys.readouterr().err
    assert main(["make-room", str(tmp_path / "room"), "--priors.depth-noise", "-1"]) == 1
    assert "--priors.depth-noise must be >= 0 and finite" in capsys.readouterr().err
    assert not (tmp_path / "sim").exists() and not (tmp_path / "room").exists()
