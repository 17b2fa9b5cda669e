"""`evaluate --align-to`: a reconstruction in its own frame (scale, rotation, offset) is moved into the
GT frame through the shared camera centres (Umeyama), optionally refined by ICP, then scored."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from cues_synth import make_room_scene, room_mesh
from evaluation.align import Similarity, align_scenes, evaluate_aligned, umeyama
from geocues.colmap_io import find_model_dir, read_model, write_model


def test_umeyama_recovers_a_similarity_and_refuses_degenerate_sets():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    truth = Similarity(2.5, Rotation.random(random_state=1).as_matrix(), np.array([1.0, -2.0, 0.5]))
    est = umeyama(src, truth.apply(src))
    assert est.s == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(est.R, truth.R, atol=1e-12)
    np.testing.assert_allclose(est.t, truth.t, atol=1e-12)
    assert np.linalg.det(est.R) == pytest.approx(1.0)
    # a mirrored target still gives a rotation (det +1), never a reflection
    assert np.linalg.det(umeyama(src, src * [1, 1, -1]).R) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(src[:2], src[:2])
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(line, line + 1)


def _moved_scene(src_root, dst_root, T: Similarity, noise_m: float = 0.0, seed: int = 0):
    """A copy of the scene whose world is x' = s R x + t (what an images-only SfM might return)."""
    shutil.copytree(src_root, dst_root)
    model = find_model_dir(dst_root)
    images, points = read_model(model)
    rng = np.random.default_rng(seed)
    for im in images:
        R_new = im.R @ T.R.T
        im.t = T.s * im.t - R_new @ T.t + R_new @ rng.normal(0, noise_m, 3) * T.s
        im.R = R_new
    points.xyz = T.apply(points.xyz)
    shutil.rmtree(model)
    write_model(model, images, points)
    return dst_root


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    base = tmp_path_factory.mktemp("align")
    gt_root = make_room_scene(base / "gt", n_views=10, w=64, h=48, priors="none")
    V, F, _ = room_mesh()
    (gt_root / "gt").mkdir(exist_ok=True)
    o3d.io.write_triangle_mesh(str(gt_root / "gt" / "mesh.ply"),
                               o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F)))
    T = Similarity(0.37, Rotation.from_euler("xyz", [20, -35, 110], degrees=True).as_matrix(),
                   np.array([3.0, -1.0, 7.0]))
    pred_root = _moved_scene(gt_root, base / "pred", T)
    gt_mesh = o3d.io.read_triangle_mesh(str(gt_root / "gt" / "mesh.ply"))
    moved = o3d.geometry.TriangleMesh(gt_mesh)
    moved.transform(T.matrix())
    o3d.io.write_triangle_mesh(str(base / "pred_mesh.ply"), moved)
    return base, gt_root, pred_root, T


def _self_score(gt_root):
    from evaluation.mesh_metrics import MeshMetricsConfig, evaluate_with_scene

    return evaluate_with_scene(gt_root / "gt" / "mesh.ply", None, gt_root, MeshMetricsConfig(n_samples=50_000))


def test_align_scenes_inverts_the_frame_change(scenes):
    _, gt_root, pred_root, T = scenes
    a = align_scenes(pred_root, gt_root)
    assert a.transform.s == pytest.approx(1 / T.s, rel=1e-6)
    assert a.residuals_m.max() < 1e-6 and len(a.shared) == 10
    np.testing.assert_allclose(a.transform.apply(T.apply(np.eye(3))), np.eye(3), atol=1e-6)


def test_evaluate_align_to_scores_the_mesh_as_in_the_gt_frame(scenes, capsys):
    from cli.evaluate_cli import main

    base, gt_root, pred_root, _ = scenes
    out = base / "m.json"
    assert main([str(base / "pred_mesh.ply"), str(pred_root), "--align-to", str(gt_root),
                 "-o", str(out), "--n-samples", "50000"]) == 0  # -o OUT as in every command
    m = json.loads(out.read_text())
    same = _self_score(gt_root)  # the GT mesh against itself: the protocol's sampling noise
    assert abs(m["chamfer_l1"] - same.chamfer_l1) < 1e-3 and m["f_score"] > 0.99, (m, same.chamfer_l1)
    assert m["protocol"]["alignment"]["centre_residual_m"]["max"] < 1e-6
    printed = capsys.readouterr().out
    assert "shared images" in printed and "residual RMS 0.0000 m" in printed  # what docs/evaluation.md says it prints
    assert main([str(base / "pred_mesh.ply"), str(pred_root), "--align-to", str(gt_root), "--icp",
                 "--n-samples", "20000"]) == 0
    assert re.search(r"; ICP [\d.]+ deg, [\d.]+ m, scale [\d.]+, fitness [\d.]+, inlier RMSE [\d.]+ m",
                     capsys.readouterr().out)


def test_icp_refines_a_noisy_camera_alignment(scenes):
    base, gt_root, _, T = scenes
    noisy = _moved_scene(gt_root, base / "noisy", T, noise_m=0.01, seed=3)
    from evaluation.mesh_metrics import MeshMetricsConfig

    cfg = MeshMetricsConfig(n_samples=50_000)
    plain = evaluate_aligned(base / "pred_mesh.ply", noisy, gt_root, cfg=cfg)
    refined = evaluate_aligned(base / "pred_mesh.ply", noisy, gt_root, cfg=cfg, icp=True)
    assert plain.protocol["alignment"]["centre_residual_m"]["rms"] > 0.005
    assert refined.protocol["alignment"]["icp"]["fitness"] > 0.9
    same = _self_score(gt_root)
    assert refined.chamfer_l1 < plain.chamfer_l1 - 0.002, (plain.chamfer_l1, refined.chamfer_l1)
    assert refined.chamfer_l1 < same.chamfer_l1 + 0.002, (refined.chamfer_l1, same.chamfer_l1)
    assert refined.protocol["alignment"]["icp"]["warning"] is None  # a refinement: no word


def test_an_icp_correction_larger_than_a_refinement_is_named(scenes, monkeypatch, caplog, capsys):
    """Regression: ICP turned an images-only mesh 24.7 deg, scaled it 0.72x and moved it 1.2 m after a
    camera alignment good to 7.6 cm, and the flattered figures (precision 0.15 -> 0.91) came without a word."""
    import evaluation.align
    from cli.evaluate_cli import main

    base, gt_root, pred_root, _ = scenes
    R = Rotation.from_euler("z", 24.7, degrees=True).as_matrix()
    slid = Similarity(0.72, R, np.array([0.3, -0.2, 0.1])).matrix()  # what the h36b audit's ICP returned, about

    def bad_icp(points, gt_points, max_dist, iters=100):
        shift = np.linalg.norm(points @ slid[:3, :3].T + slid[:3, 3] - points, axis=1).mean()
        return slid, {"fitness": 0.955, "inlier_rmse_m": 0.03, "scale": 0.72, "rotation_deg": 24.7,
                      "translation_m": float(np.linalg.norm(slid[:3, 3])), "mean_shift_m": float(shift)}

    monkeypatch.setattr(evaluation.align, "icp_refine", bad_icp)
    out = base / "slid.json"
    with caplog.at_level("WARNING", logger="evaluation.align"):
        assert main([str(base / "pred_mesh.ply"), str(pred_root), "--align-to", str(gt_root), "--icp",
                     "--n-samples", "5000", "-o", str(out)]) == 0
    said = [r.getMessage() for r in caplog.records if "ICP turned the mesh" in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0], said
    assert re.search(r"ICP turned the mesh 24\.7 deg, scaled it 0\.720x and moved its surface [\d.]+ m on average "
                     r"after a camera alignment good to 0\.000 m", said[0]), said[0]
    assert "over 3 deg, 5 % scale or 0.1 m" in said[0] and "without --icp" in said[0]
    assert json.loads(out.read_text())["protocol"]["alignment"]["icp"]["warning"] == said[0]
    capsys.readouterr()


def test_too_few_shared_images_is_named(scenes, tmp_path):
    _, gt_root, _, _ = scenes
    other = shutil.copytree(gt_root, tmp_path / "other")
    model = find_model_dir(other)
    images, points = read_model(model)
    for im in images:
        im.name = "renamed_" + im.name
    shutil.rmtree(model)
    write_model(model, images, points)
    for p in (other / "images").iterdir():
        p.rename(p.with_name("renamed_" + p.name))
    with pytest.raises(ValueError, match="at least 3 images registered in both"):
        align_scenes(other, gt_root)


def test_cues_of_a_scene_in_its_own_frame_are_warned_about_and_scored_with_align_to(scenes, tmp_path, capsys):
    """Regression: `evaluate cues CUES SCENE --gt GT` of a photos-only scene gave every type ~1.2 m median,
    0 % within 5 cm, rc 0 and no word; now the frame warning of `evaluate mesh`, and --align-to moves the
    cues into the GT's frame by the same camera-centre similarity."""
    from cli.evaluate_cli import main
    from geocues.cue_io import write_cues_ply
    from test_train import surface_cues

    base, gt_root, pred_root, T = scenes
    own = shutil.copytree(pred_root, tmp_path / "own")
    (own / "scene.json").write_text(json.dumps({"frame": "mapped from images", "scale": "arbitrary"}))
    cues = surface_cues(gt_root, n_plane=3000)  # on the GT surface, in the GT's frame
    write_cues_ply(tmp_path / "gt_cues" / "cues.ply", cues)
    cues.xyz = T.apply(cues.xyz)  # the same cues in the scene's own frame
    write_cues_ply(tmp_path / "cues" / "cues.ply", cues)
    gt_mesh = str(gt_root / "gt" / "mesh.ply")

    assert main(["cues", str(tmp_path / "cues"), str(own), "--gt", gt_mesh, "-o", str(tmp_path / "plain.json")]) == 0
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if "mapped from images alone" in line]
    assert len(said) == 1 and f"{own} was mapped from images alone" in said[0], err
    assert "pass --align-to GT_SCENE" in said[0] and said[0].endswith("to score its cues"), said[0]
    assert json.loads((tmp_path / "plain.json").read_text())["per_type"]["PLANE"]["within_5cm"] < 0.5

    out = tmp_path / "aligned.json"
    assert main(["cues", str(tmp_path / "cues"), str(own), "--align-to", str(gt_root), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "mapped from images alone" not in captured.err
    assert "aligned to" in captured.out and "residual RMS 0.0000 m" in captured.out  # evaluate mesh's line
    aligned = json.loads(out.read_text())
    assert aligned["alignment"]["shared_images"] == 10 and aligned["alignment"]["centre_residual_m"]["max"] < 1e-6
    assert aligned["gt"] == gt_mesh and aligned["gt_scene"] == str(gt_root)
    assert main(["cues", str(tmp_path / "gt_cues"), str(gt_root), "-o", str(tmp_path / "in_frame.json")]) == 0
    in_frame = json.loads((tmp_path / "in_frame.json").read_text())
    for t in ("PLANE", "LINE", "SFM"):  # as if the cues had been extracted in the GT's frame
        a, b = aligned["per_type"][t], in_frame["per_type"][t]
        assert a["within_1cm"] == pytest.approx(b["within_1cm"], abs=0.002), t
        assert a["median_m"] == pytest.approx(b["median_m"], abs=1e-5), t
    assert aligned["per_type"]["PLANE"]["within_1cm"] > 0.99
    assert aligned["coverage"]["ALL"] == pytest.approx(in_frame["coverage"]["ALL"], abs=0.01)
    capsys.readouterr()


def _fake_run(run_dir, scene, mesh):
    """A finished-run folder on ``scene`` with two checkpoint meshes (copies of ``mesh``): Gaussians at the
    scene's SfM points, report.json, a training log."""
    import torch

    from geocues.scene import Scene
    from splat.gaussians import save_ply

    pts = torch.as_tensor(Scene.load(scene, check_priors=False).points.xyz, dtype=torch.float32)
    n = len(pts)
    save_ply(run_dir / "point_cloud.ply", {
        "means": pts, "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), "scales": torch.full((n, 3), -3.0),
        "opacities": torch.full((n,), 2.0), "sh0": torch.full((n, 1, 3), 0.5), "shN": torch.zeros(n, 0, 3)})
    (run_dir / "checkpoints").mkdir()
    points = []
    for step in (15, 30):
        shutil.copy(mesh, run_dir / "checkpoints" / f"mesh_{step:06d}.ply")
        points.append({"step": step, "train_s": step / 10, "psnr": 20.0, "ssim": 0.5, "n_gaussians": n,
                       "mesh": f"checkpoints/mesh_{step:06d}.ply"})
    (run_dir / "report.json").write_text(json.dumps({
        "scene": str(scene), "config": {"iters": 30, "downscale": 1.0, "test_every": 4, "sh_degree": 0,
                                        "background": [0.0, 0.0, 0.0]},
        "timings": {"train_s": 3.0}, "test_metrics": {"psnr": 20.0, "ssim": 0.5, "n_views": 2},
        "gaussians_final": {"SFM": n}, "accuracy_vs_time": points}))
    (run_dir / "train_log.jsonl").write_text("".join(json.dumps({"step": s, "loss": 1 / (s + 1), "rgb": 0.5, "n": n,
                                                                 "SFM": n}) + "\n" for s in (0, 15, 30)))
    return run_dir


def test_a_report_of_a_run_in_its_own_frame_leaves_the_mesh_out_or_aligns_it(scenes, tmp_path, caplog, capsys):
    """Regression: `evaluate report RUN --gt GT` of a run on a photos-only scene exited 1 with advice to
    pass --align-to, which `evaluate report` did not have, and wrote no report.md. Now the mesh metrics
    are left out with a warning and a note, the rest is written; --align-to scores them as `evaluate` does."""
    from cli.evaluate_cli import main

    base, gt_root, pred_root, _ = scenes
    own = shutil.copytree(pred_root, tmp_path / "own")
    (own / "scene.json").write_text(json.dumps({"frame": "mapped from images", "scale": "arbitrary"}))
    run = _fake_run(tmp_path / "run", own, base / "pred_mesh.ply")
    with caplog.at_level("WARNING", logger="evaluation.run_report"):
        assert main(["report", str(run), "--gt", str(gt_root / "gt" / "mesh.ply"), "--views", "1"]) == 0
    said = [r.getMessage() for r in caplog.records if "mapped from images alone" in r.getMessage()]
    assert len(said) == 1 and "pass --align-to GT_SCENE" in said[0] and "leaves the mesh metrics out" in said[0]
    for name in ("report.md", "report_losses.png", "report_accuracy.png", "report_views.png", "report_data.json"):
        assert (run / name).is_file(), name
    md, data = (run / "report.md").read_text(), json.loads((run / "report_data.json").read_text())
    assert f"Mesh metrics left out: {own} was mapped from images alone" in md and "Chamfer-L1" not in md
    assert data["mesh_vs_time"] == [] and "--align-to GT_SCENE" in data["mesh_skipped"]

    assert main(["report", str(run), "--align-to", str(gt_root), "--views", "1", "--overwrite"]) == 0
    md, data = (run / "report.md").read_text(), json.loads((run / "report_data.json").read_text())
    assert [p["step"] for p in data["mesh_vs_time"]] == [15, 30] and data["mesh_skipped"] is None
    assert data["mesh_alignment"]["shared_images"] == 10 and data["mesh_alignment"]["centre_residual_m"]["max"] < 1e-6
    assert all(p["f_score"] > 0.99 and p["chamfer_l1"] < 0.02 for p in data["mesh_vs_time"]), data["mesh_vs_time"]
    assert re.search(rf"Final mesh: Chamfer-L1 [\d.]+ cm, F@5cm 1\.000, NC [\d.]+, after aligning the scene to "
                     rf"`{re.escape(str(gt_root))}` by the camera centres of 10 shared images", md), md
    capsys.readouterr()


def test_a_report_asked_to_align_a_run_without_checkpoint_meshes_says_so(scenes, tmp_path, caplog, capsys):
    """`evaluate report RUN --align-to GT_SCENE` of a run that kept no checkpoint meshes (trained without
    --mesh-at-checkpoints) wrote a report without mesh metrics and without a word about the option."""
    from cli.evaluate_cli import main

    base, gt_root, pred_root, _ = scenes
    run = _fake_run(tmp_path / "run", pred_root, base / "pred_mesh.ply")
    shutil.rmtree(run / "checkpoints")
    with caplog.at_level("WARNING", logger="evaluation.run_report"):
        assert main(["report", str(run), "--align-to", str(gt_root), "--views", "1"]) == 0
    assert "kept no checkpoint meshes (`splat train --mesh-at-checkpoints`" in caplog.text
    md, data = (run / "report.md").read_text(), json.loads((run / "report_data.json").read_text())
    assert "Mesh metrics left out:" in md and "kept no checkpoint meshes" in data["mesh_skipped"]
    capsys.readouterr()
