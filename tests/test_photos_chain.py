"""README's "Your own photos" chain, run as a user runs it: a folder of photos alone (12 ICL frames at
320x240) through every command's CLI, from `geocues sfm` to `evaluate --align-to`. Each step must
exit 0 and leave what the next one reads; the marks of an images-only model must travel with it;
the guessed unit must land near metres; the short training's mesh must lie on the room."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

FRAMES = list(range(0, 120, 10))  # 12 frames along ~1.5 m of the ICL trajectory


pytestmark = pytest.mark.usefixtures("restore_log_handlers")  # conftest.py


def test_a_folder_of_photos_to_a_scored_mesh(icl_dir: Path, tmp_path: Path, capsys):
    from cli.evaluate_cli import main as evaluate
    from cli.geocues_cli import main as geocues
    from cli.splat_cli import main as splat
    from geocues.rescale import median_view_depth
    from geocues.scene import Scene

    photos = tmp_path / "photos"
    (photos / "images").mkdir(parents=True)
    names = sorted(p.name for p in (icl_dir / "images").iterdir())
    for k in FRAMES:
        img = cv2.imread(str(icl_dir / "images" / names[k]))
        cv2.imwrite(str(photos / "images" / names[k]), cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA))
    m, u, metric, scene = (tmp_path / n for n in ("map", "und", "metric", "scene"))
    cues, run = tmp_path / "cues", tmp_path / "run"

    assert geocues(["sfm", str(photos), "-o", str(m)]) == 0
    mark = json.loads((m / "scene.json").read_text())
    assert mark["scale"] == "arbitrary"
    registered = json.loads((m / "sfm_report.json").read_text())["registered_images"]
    assert mark["sfm_registered"] == {"images": registered, "photos": len(FRAMES)}  # travels to the scene below
    capsys.readouterr()
    assert geocues(["info", str(m)]) == 0  # distorted and not metric: summarised, both named
    out = capsys.readouterr().out
    assert "SIMPLE_RADIAL" in out and "geocues undistort" in out and "mapped from images alone" in out
    assert geocues(["undistort", str(m), "-o", str(u)]) == 0
    assert geocues(["rescale", str(u), "-o", str(metric), "--median-depth", "2"]) == 0
    s = Scene.load(metric)
    assert median_view_depth(s) == pytest.approx(2.0, rel=1e-6) and "scale" not in s.metadata
    assert s.metadata["frame"] == "mapped from images" and (s.points.track_length >= 2).all()
    assert geocues(["mvs", str(metric), "-o", str(scene)]) == 0
    assert Scene.load(scene).metadata["sfm_registered"] == mark["sfm_registered"]
    assert geocues(["extract", str(scene), "-o", str(cues), "--preset", "mvs"]) == 0
    assert splat(["train", str(scene), "-c", str(cues), "-o", str(run), "--preset", "mvs", "--iters", "150",
                  "--tsdf.weight-threshold", "0"]) == 0
    capsys.readouterr()
    assert evaluate([str(run / "mesh.ply"), str(scene), "--align-to", str(icl_dir),
                     "--gt", str(icl_dir / "reference_mesh.ply"), "-o", str(tmp_path / "eval.json")]) == 0
    ev = json.loads((tmp_path / "eval.json").read_text())
    a = ev["protocol"]["alignment"]
    # ICL's photos are 1.7 m from what they show: a 2 m guess is within 30 % of metres
    assert 0.7 < a["scale"] < 1.0 and a["centre_residual_m"]["median"] < 0.03, a
    assert ev["accuracy"] < 0.15 and ev["precision"] > 0.4, ev  # the mesh lies on the room
