"""The default `evaluate PRED_MESH --gt GT_MESH` command: JSON output, scene culling, clean errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from cli.evaluate_cli import main
from evaluation.mesh_metrics import METRIC_KEYS


def write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces))
    assert o3d.io.write_triangle_mesh(filename=str(path), mesh=mesh)
    return path


def rects(*specs) -> tuple[np.ndarray, np.ndarray]:
    """Union of axis-aligned rectangles (x0, x1, y0, y1, z), 2 triangles each."""
    verts, faces = [], []
    for k, (x0, x1, y0, y1, z) in enumerate(specs):
        verts.append([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
        faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k)
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), np.concatenate(faces)


def box_files(tmp_path: Path, shift: float) -> tuple[Path, Path]:
    box = o3d.geometry.TriangleMesh.create_box()
    v, f = np.asarray(box.vertices), np.asarray(box.triangles)
    return (write_mesh(tmp_path / "pred.ply", v + [shift, 0, 0], f), write_mesh(tmp_path / "gt.ply", v, f))


def make_scene(root: Path) -> Path:
    """One 100x100 camera at the origin looking along +z (sees x/z, y/z in [-0.25, 0.25)),
    a COLMAP text model, its image, and gt/mesh.ply: a 2 x 2 m wall at z = 2."""
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 PINHOLE 100 100 200 200 50 50\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 1 00000.png\n\n")
    (model / "points3D.txt").write_text("")
    (root / "images").mkdir()
    cv2.imwrite(str(root / "images" / "00000.png"), np.full((100, 100, 3), 128, np.uint8))
    write_mesh(root / "gt" / "mesh.ply", *rects((-1, 1, -1, 1, 2.0)))
    return root


def test_writes_json_and_table(tmp_path, capsys):
    pred, gt = box_files(tmp_path, 0.01)
    out = tmp_path / "res" / "metrics.json"
    rc = main([str(pred), "--gt", str(gt), "--json", str(out), "--n-samples", "5000", "--mode", "surface"])
    assert rc == 0
    data = json.loads(out.read_text())
    assert set(METRIC_KEYS) <= set(data) and isinstance(data["protocol"], dict)
    assert data["protocol"]["mode"] == "surface" and data["protocol"]["n_samples"] == 5000
    assert data["protocol"]["culling"] == "none" and data["protocol"]["threshold"] == 0.05
    # 1 cm shift: 1/6 of the surface at ~1 cm, the rest at ~0 -> C-L1 about 3.3 mm
    assert 0.002 < data["chamfer_l1"] < 0.005
    assert data["f_score"] == 1.0 and 0.9 < data["normal_consistency"] <= 1.0
    printed = capsys.readouterr().out
    assert "chamfer_l1" in printed and "point-to-surface" in printed and str(out) in printed


def test_point_mode_is_default(tmp_path):
    pred, gt = box_files(tmp_path, 0.0)
    out = tmp_path / "m.json"
    assert main([str(pred), "--gt", str(gt), "--json", str(out), "--n-samples", "20000"]) == 0
    data = json.loads(out.read_text())
    assert data["protocol"]["mode"] == "point" and data["f_score"] == 1.0


def test_missing_file_fails_cleanly(tmp_path, capsys):
    _, gt = box_files(tmp_path, 0.0)
    out = tmp_path / "m.json"
    rc = main([str(tmp_path / "absent.ply"), "--gt", str(gt), "--json", str(out)])
    assert rc == 1 and not out.exists()
    err = capsys.readouterr().err
    assert "absent.ply" in err and "Traceback" not in err
    assert main([str(tmp_path / "absent.ply")]) == 1  # no GT either: the mesh named first is the error
    err = capsys.readouterr().err
    assert "no mesh at" in err and "absent.ply" in err


def test_mixed_up_arguments_are_named_with_the_right_form(tmp_path, capsys):
    """SCENE and MESH swapped, a run folder for its mesh, a GT mesh where SCENE goes, a folder for --gt:
    one line each naming the form that works, nothing scored."""
    pred, gt = box_files(tmp_path, 0.0)
    scene = make_scene(tmp_path / "scene")
    run = tmp_path / "run"
    run.mkdir()
    (run / "mesh.ply").write_bytes(pred.read_bytes())
    cases = [([str(scene), str(pred)], f"the mesh comes first: evaluate {pred} {scene}"),
             ([str(run), str(scene)], f"its mesh is {run / 'mesh.ply'}"),
             ([str(pred), str(gt)], f"a ground-truth mesh is given as --gt {gt}"),
             ([str(pred), "--gt", str(scene)], f"--gt takes the GT mesh file ({scene / 'gt' / 'mesh.ply'}?)")]
    for argv, want in cases:
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert want in err and "Traceback" not in err, (argv, err)


def test_empty_mesh_fails_cleanly(tmp_path, capsys):
    pred, _ = box_files(tmp_path, 0.0)
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\n"
                     "property list uchar int vertex_indices\nend_header\n")
    assert main([str(pred), "--gt", str(empty)]) == 1
    assert "empty.ply" in capsys.readouterr().err


def test_scene_culls_to_its_cameras(tmp_path):
    scene = make_scene(tmp_path / "scene")
    # the wall plus a patch 4 cm in front of it, outside the camera's view
    pred = write_mesh(tmp_path / "pred.ply", *rects((-1, 1, -1, 1, 2.0), (0.6, 0.9, -0.2, 0.2, 1.96)))
    plain, culled = tmp_path / "plain.json", tmp_path / "culled.json"
    args = ["--n-samples", "20000", "--mode", "surface"]
    assert main([str(pred), "--gt", str(scene / "gt" / "mesh.ply"), "--json", str(plain), *args]) == 0
    assert main([str(pred), str(scene), "--json", str(culled), *args]) == 0  # GT from the scene
    plain, culled = json.loads(plain.read_text()), json.loads(culled.read_text())
    assert plain["accuracy"] > 5e-4  # the patch: ~3% of the surface at 4 cm
    assert culled["accuracy"] < 1e-6 and culled["completeness"] < 1e-6
    assert culled["protocol"]["culling"] == "frusta" and culled["protocol"]["n_cameras"] == 1
    assert culled["protocol"]["gt_mesh"].endswith("mesh.ply")


def test_a_scene_mapped_from_images_is_told_to_align(tmp_path, capsys):
    """A mesh of an images-only model (`geocues sfm --mode map` marks scene.json; `geocues rescale`
    keeps the mark) is in its own frame: scored without --align-to it gets one warning naming it."""
    scene = make_scene(tmp_path / "scene")
    pred = write_mesh(tmp_path / "pred.ply", *rects((-1, 1, -1, 1, 2.0)))
    args = ["--n-samples", "2000", "--mode", "surface"]
    assert main([str(pred), str(scene), *args]) == 0
    assert "--align-to" not in capsys.readouterr().err
    (scene / "scene.json").write_text(json.dumps({"frame": "mapped from images"}))
    assert main([str(pred), str(scene), *args]) == 0
    err = capsys.readouterr().err
    assert f"{scene} was mapped from images alone" in err and "pass --align-to GT_SCENE" in err


def test_a_mesh_in_another_unit_or_place_is_named_without_a_scene(tmp_path, capsys):
    """Without SCENE there is no mark to read: the mesh's own extent against the GT's tells."""
    box = o3d.geometry.TriangleMesh.create_box()
    v, f = np.asarray(box.vertices), np.asarray(box.triangles)
    gt = write_mesh(tmp_path / "gt.ply", v, f)
    six = write_mesh(tmp_path / "six.ply", 6.0 * v + [0.5, -2.0, -2.0], f)  # a wall through the GT's box
    out = tmp_path / "six.json"
    assert main([str(six), "--gt", str(gt), "--n-samples", "2000", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "6 times the GT's size" in err and "--align-to GT_SCENE" in err
    assert "6 times" in json.loads(out.read_text())["protocol"]["frame_warning"]
    away = write_mesh(tmp_path / "away.ply", v + [30.0, 0, 0], f)  # nothing left after the crop
    assert main([str(away), "--gt", str(gt), "--n-samples", "2000"]) == 1
    err = capsys.readouterr().err
    assert "none kept" in err and "100 % of" in err and "--align-to" in err and "Traceback" not in err
    assert main([str(gt), "--gt", str(gt), "--n-samples", "2000"]) == 0
    assert "GT's size" not in capsys.readouterr().err


def test_no_gt_anywhere(tmp_path, capsys):
    scene = make_scene(tmp_path / "scene")
    (scene / "gt" / "mesh.ply").unlink()
    pred, _ = box_files(tmp_path, 0.0)
    assert main([str(pred), str(scene)]) == 1
    assert "--gt" in capsys.readouterr().err


def test_scene_is_positional_and_the_old_option_still_works(tmp_path, capsys):
    """SCENE is positional (as in `geocues`/`splat`); `--scene SCENE` gives the same result with a
    deprecation note; renders or an alignment without SCENE, or SCENE twice, are one-line errors."""
    scene = make_scene(tmp_path / "scene")
    pred = write_mesh(tmp_path / "pred.ply", *rects((-1, 1, -1, 1, 2.0), (0.6, 0.9, -0.2, 0.2, 1.96)))
    args = ["--n-samples", "5000", "--mode", "surface"]
    new, old = tmp_path / "new.json", tmp_path / "old.json"
    assert main(["mesh", str(pred), str(scene), "-o", str(new), *args]) == 0
    assert "deprecated" not in capsys.readouterr().err
    assert main([str(pred), "--scene", str(scene), "--json", str(old), *args]) == 0
    assert "--scene is deprecated" in capsys.readouterr().err
    a, b = json.loads(new.read_text()), json.loads(old.read_text())
    assert a["protocol"]["culling"] == "frusta" and a["chamfer_l1"] == b["chamfer_l1"] < 1e-6
    assert main([str(pred), f"--scene={scene}", "-o", str(tmp_path / "eq.json"), *args]) == 0
    assert json.loads((tmp_path / "eq.json").read_text())["chamfer_l1"] == a["chamfer_l1"]
    capsys.readouterr()
    assert main([str(pred), "--gt", str(scene / "gt" / "mesh.ply"), "--renders", str(tmp_path)]) == 1
    assert "--renders needs SCENE" in capsys.readouterr().err
    assert main([str(pred), "--align-to", str(scene)]) == 1
    assert "--align-to needs SCENE" in capsys.readouterr().err
    assert main([str(pred), "--scene", str(scene), "--scene", str(scene)]) == 1
    assert "--scene is given twice" in capsys.readouterr().err


def test_report_and_cues_take_scene_positionally(tmp_path, monkeypatch, capsys):
    import evaluation.cue_metrics
    import evaluation.run_report

    seen = {}
    monkeypatch.setattr(evaluation.run_report, "write_run_report",
                        lambda run, scene, gt, gt_depth, views, overwrite=False, align_to=None: seen.update(
                            run=run, scene=scene, views=views, overwrite=overwrite) or run / "report.md")
    assert main(["report", "R", "S", "--views", "2"]) == 0
    assert seen == {"run": Path("R"), "scene": Path("S"), "views": 2, "overwrite": False}
    assert main(["report", "R", "--overwrite"]) == 0 and seen["scene"] is None and seen["overwrite"]
    assert main(["report", "R", "--scene", "S"]) == 0 and seen["scene"] == Path("S")
    monkeypatch.setattr(evaluation.cue_metrics, "evaluate_cues_dir",
                        lambda cues, scene, gt, cfg: seen.update(cues=cues, cue_scene=scene) or {})
    monkeypatch.setattr(evaluation.cue_metrics, "format_cue_table", lambda result: "")
    assert main(["cues", "C", "S2"]) == 0
    assert (seen["cues"], seen["cue_scene"]) == (Path("C"), Path("S2"))
    with pytest.raises(SystemExit):  # SCENE is required for cues
        main(["cues", "C"])
    capsys.readouterr()


def _strict(text: str) -> dict:
    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


def test_renders_are_checked_first_and_scored_to_strict_json(tmp_path, capsys, monkeypatch, caplog):
    """A render identical to its image wrote "psnr": Infinity; a bad --renders was named only after
    the mesh metrics; a run folder, --test-every 0 and another scene's run were not named at all."""
    import cli.evaluate_cli as cli

    scene = make_scene(tmp_path / "scene")
    pred = write_mesh(tmp_path / "pred.ply", *rects((-1, 1, -1, 1, 2.0)))
    run = tmp_path / "run"
    (run / "test_renders").mkdir(parents=True)
    cv2.imwrite(str(run / "test_renders" / "00000.png"), np.full((100, 100, 3), 128, np.uint8))
    out = tmp_path / "m.json"
    assert main([str(pred), str(scene), "--renders", str(run / "test_renders"), "-o", str(out),
                 "--n-samples", "2000"]) == 0
    images = _strict(out.read_text())["images"]
    assert images["psnr"] == 100.0 and images["n_test_views"] == 1 and images["missing_views"] == []
    assert "PSNR 100.00 dB" in capsys.readouterr().out

    def no_mesh_metrics(*a, **k):
        raise AssertionError("the mesh was scored before --renders was checked")

    monkeypatch.setattr(cli, "evaluate_with_scene", no_mesh_metrics)
    for renders, extra, said in [(run, [], f"{run} is a run folder: its held-out renders are"),
                                 (run / "test_renders", ["--test-every", "0"], "--test-every must be >= 1"),
                                 (tmp_path, [], "holds no PNG/JPEG renders")]:
        assert main([str(pred), str(scene), "--renders", str(renders), *extra]) == 1
        assert said in capsys.readouterr().err
    (run / "report.json").write_text(json.dumps({"scene": str(tmp_path / "another_room")}))
    from evaluation.image_metrics import evaluate_renders

    with caplog.at_level("WARNING", logger="evaluation.image_metrics"):
        evaluate_renders(run / "test_renders", scene)
    assert f"come from a run trained on {tmp_path / 'another_room'}, not {scene}" in caplog.text


def test_lpips_without_renders_is_refused_naming_it(tmp_path, capsys):
    """Regression: `evaluate MESH SCENE --lpips FILE` without --renders ignored the network without a word."""
    scene = make_scene(tmp_path / "scene")
    pred = write_mesh(tmp_path / "pred.ply", *rects((-1, 1, -1, 1, 2.0)))
    assert main([str(pred), str(scene), "--lpips", str(tmp_path / "lpips.pt"), "--n-samples", "2000"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert f"--lpips {tmp_path / 'lpips.pt'}" in err and "pass --renders DIR" in err


def test_a_render_of_another_size_is_named(tmp_path):
    from evaluation.image_metrics import evaluate_images

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((20, 30, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((40, 60, 3), np.uint8))
    with pytest.raises(ValueError, match=r"b.png is 60x40 and its reference .*a.png 30x20"):
        evaluate_images([tmp_path / "b.png"], [tmp_path / "a.png"])


@pytest.mark.parametrize("option", [["--threshold", "nan"], ["--threshold", "inf"], ["--crop-margin", "nan"],
                                    ["--seed", "-1"]])
def test_non_finite_options_are_refused(tmp_path, capsys, option):
    """--threshold nan gave F 0 and "threshold": NaN in the JSON, inf F 1; a nan crop margin blamed the
    mesh's frame."""
    pred, gt = box_files(tmp_path, 0.0)
    assert main([str(pred), "--gt", str(gt), *option]) == 1
    err = capsys.readouterr().err
    assert option[0][2:].replace("-", "_") in err and "Traceback" not in err


def test_a_mesh_the_scene_barely_sees_is_named(tmp_path, caplog):
    """A mesh scored with another scene's cameras kept 8 % of its surface and scored C-L1 36 cm without a
    word: the share the cameras see is named below 30 % (the scene's camera sees 1 of the wall's 4 m^2)."""
    scene = make_scene(tmp_path / "scene")
    wall = write_mesh(tmp_path / "wall.ply", *rects((-1, 1, -1, 1, 2.0)))
    seen = write_mesh(tmp_path / "seen.ply", *rects((-0.45, 0.45, -0.45, 0.45, 2.0)))
    with caplog.at_level("WARNING", logger="evaluation.mesh_metrics"):
        assert main([str(seen), str(scene), "-o", str(tmp_path / "a.json"), "--n-samples", "5000"]) == 0
        assert "is seen by the" not in caplog.text
        assert main([str(wall), str(scene), "-o", str(tmp_path / "b.json"), "--n-samples", "5000"]) == 0
    assert re.search(r"only 2\d % of .*wall.ply is seen by the 1 cameras", caplog.text)
    assert "is SCENE the scene" in json.loads((tmp_path / "b.json").read_text())["protocol"]["seen_warning"]


def test_renders_named_as_the_reference_render_py_names_them_are_matched():
    """The 3DGS reference render.py writes test/ours_N/renders/00000.png ... (the index in its test list,
    the test views in name order): they were refused ('renders [...] are not test views'); they map to
    the test views in name order, and only when they are exactly 00000..T-1 for T test views."""
    from pathlib import Path

    from evaluation.image_metrics import _reference_names

    tests = ["frame_016", "frame_000", "frame_008"]
    index_named = {f"{k:05d}": Path(f"r/{k:05d}.png") for k in range(3)}
    assert _reference_names(index_named, tests, Path("r")) == {
        "frame_000": Path("r/00000.png"), "frame_008": Path("r/00001.png"), "frame_016": Path("r/00002.png")}
    own = {"frame_000": Path("r/frame_000.png")}  # named like the views (some missing): unchanged
    assert _reference_names(own, tests, Path("r")) is own
    two = {k: v for k, v in index_named.items() if k != "00002"}  # not all T: unchanged (then refused)
    assert _reference_names(two, tests, Path("r")) is two
    rooms = ["00000", "00008", "00016"]  # a benchmark room's own names overlap the indices
    assert _reference_names(index_named, rooms, Path("r")) == {
        "00000": Path("r/00000.png"), "00008": Path("r/00001.png"), "00016": Path("r/00002.png")}
    assert _reference_names({"00000": Path("r/00000.png"), "00008": Path("r/00008.png")}, rooms, Path("r")) == {
        "00000": Path("r/00000.png"), "00008": Path("r/00008.png")}  # the room's own names win


def test_the_downscale_of_renders_of_odd_sized_photos_is_found():
    """321x239 photos trained at --downscale 2 render 160x120 (each side rounded); the width ratio 2.006
    read the photos at 160x119 and refused the run ('an image and its reference must have one size')."""
    from evaluation.image_metrics import render_downscale

    assert render_downscale(321, 239, 160, 120) == 2.0
    assert render_downscale(640, 480, 640, 480) == 1.0
    assert render_downscale(640, 480, 213, 160) == 3.0
    assert render_downscale(1000, 750, 400, 300) == 2.5  # a fractional factor: the ratio
    assert render_downscale(640, 480, 100, 100) is None  # no downscale of the photo


def test_renders_larger_than_the_photos_are_refused_unless_the_run_trained_so(tmp_path):
    """320x240 renders of 160x120 photos were scored (the photos enlarged into references, 'downscale': 0.5)
    while docs/evaluation.md calls a render of no downscale of the photos an error (researcher audit); a
    run trained with --downscale 0.5 (warned about) records it and keeps its renders scoreable."""
    from evaluation.image_metrics import render_downscale

    assert render_downscale(160, 120, 320, 240) is None
    assert render_downscale(160, 120, 320, 240, tmp_path / "test_renders") is None
    (tmp_path / "report.json").write_text(json.dumps({"config": {"downscale": 0.5}}))
    assert render_downscale(160, 120, 320, 240, tmp_path / "test_renders") == 0.5
