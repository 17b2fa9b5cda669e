"""`splat render`: decodable PNGs of every chosen view at the camera's size, panels with GT and priors,
an MP4 with the expected frame count, camera paths and files, and the errors a user meets."""

from __future__ import annotations

import json
import re

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from cues_synth import make_room_scene
from geocues.scene import Scene
from splat.export import camera_to_json
from splat.gaussians import save_ply
from splat.render_run import RenderConfig, ViewCam, camera_path, cameras_from_json, run

W, H = 64, 48


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory):
    """A finished-run folder: Gaussians spread over the room's SfM points, report.json naming the scene."""
    base = tmp_path_factory.mktemp("render")
    root = make_room_scene(base / "room", n_views=8, w=W, h=H, priors="all")
    scene = Scene.load(root, test_every=4, check_priors=False)
    pts = torch.as_tensor(scene.points.xyz, dtype=torch.float32)
    n = len(pts)
    g = torch.Generator().manual_seed(0)
    params = {"means": pts, "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
              "scales": torch.full((n, 3), -2.5), "opacities": torch.full((n,), 2.0),
              "sh0": torch.rand(n, 1, 3, generator=g), "shN": torch.zeros(n, 0, 3)}
    run_dir = base / "run"
    save_ply(run_dir / "point_cloud.ply", params)
    (run_dir / "report.json").write_text(json.dumps({"scene": str(root), "config": {
        "downscale": 1.0, "test_every": 4, "sh_degree": 0, "background": [0.0, 0.0, 0.0]}}))
    return run_dir, scene


def test_views_panels_and_video(fake_run, capsys, monkeypatch):
    import splat.render_run as render_run
    from cli.splat_cli import main

    run_dir, scene = fake_run
    ranges, real_video, real_range = [], render_run._write_video, render_run.depth_range
    monkeypatch.setattr(render_run, "_write_video", lambda *a: ranges.append(a[-1]) or real_video(*a))
    pooled = []  # the maps each depth_range call was given
    monkeypatch.setattr(render_run, "depth_range", lambda *maps: pooled.append(len(maps)) or real_range(*maps))
    assert main(["render", str(run_dir), "--video", "--frames", "10", "--fps", "5"]) == 0
    out = run_dir / "renders"
    names = [p.stem for p in sorted((out / "rgb").glob("*.png"))]
    assert len(names) == len(scene.test_indices) == 2
    for sub in ("rgb", "depth", "normal", "alpha"):
        for name in names:
            img = iio.imread(out / sub / f"{name}.png")
            assert img.shape == (H, W, 3) and img.dtype == np.uint8, (sub, img.shape)
    # GT | render | depth | normals | alpha, then GT depth, depth prior, normal prior where they exist
    i = scene.test_indices[0]
    extra = [(scene.root / "gt" / "depth").is_dir(), scene.depth_prior_path(i) is not None,
             scene.normal_prior_path(i) is not None]
    assert extra[1], "the fixture scene has depth priors"
    panel = iio.imread(out / "panels" / f"{names[0]}.png")
    n_tiles = 5 + sum(extra)
    assert panel.shape == (H + 18, W * n_tiles, 3)  # an 18-px strip names each column
    for k in range(n_tiles):  # white title text over black in every column's strip, the tile below it
        strip = panel[:18, k * W:(k + 1) * W]
        assert strip.max() > 200 and np.median(strip) == 0, k
    np.testing.assert_array_equal(panel[18:, W:2 * W], iio.imread(out / "rgb" / f"{names[0]}.png"))
    assert iio.imread(out / "rgb" / f"{names[0]}.png").std() > 5  # the Gaussians are in view
    frames = iio.imread(out / "video.mp4")  # every frame, decoded by ffmpeg
    assert frames.shape == (10, H + 18, 2 * W, 3)  # render | depth, each under a strip naming it
    # the video's one depth range is the rendered views' (a frame's own range saturated a third of a room's)
    assert len(ranges) == 1 and 0 < ranges[0][0] < ranges[0][1]
    assert pooled[-1] == len(names) == 2  # the video's range: every rendered view's depths pooled
    assert json.loads((out / "views.json").read_text())["video_frames"] == 10
    # a second run into the same folder needs --overwrite; the renders stay
    assert main(["render", str(run_dir)]) == 1
    assert "pass --overwrite" in capsys.readouterr().err
    assert (out / "video.mp4").is_file()


def test_views_from_a_cameras_json(fake_run, tmp_path):
    run_dir, scene = fake_run
    cams = [camera_to_json(i, scene.cameras[i]) for i in (0, 3, 5)]
    path = tmp_path / "path.json"
    path.write_text(json.dumps(cams))
    parsed = cameras_from_json(path)
    for c, i in zip(parsed, (0, 3, 5)):
        np.testing.assert_allclose(c.R, scene.cameras[i].R, atol=1e-9)
        np.testing.assert_allclose(c.t, scene.cameras[i].t, atol=1e-9)
        assert (c.width, c.height) == (W, H)
    out = run(RenderConfig(views=str(path)), run_dir, tmp_path / "out")
    assert len(list((out / "rgb").glob("*.png"))) == 3
    assert iio.imread(out / "panels" / f"{cams[0]['img_name']}.png").shape == (H + 18, 4 * W, 3)  # no GT: 4 tiles


def test_camera_path_hits_its_keys_and_stays_a_rotation():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    keys = [ViewCam(f"k{i}", K, Rotation.random(random_state=i).as_matrix(), rng.normal(size=3), W, H)
            for i in range(3)]
    path = camera_path(keys, 9)  # keys at frames 0, 4, 8
    for k, f in ((0, 0), (1, 4), (2, 8)):
        np.testing.assert_allclose(path[f].R, keys[k].R, atol=1e-9)
        np.testing.assert_allclose(-path[f].R.T @ path[f].t, -keys[k].R.T @ keys[k].t, atol=1e-9)
    for v in path:
        np.testing.assert_allclose(v.R @ v.R.T, np.eye(3), atol=1e-9)


def test_bad_inputs_are_named(fake_run, tmp_path):
    run_dir, _ = fake_run
    with pytest.raises(ValueError, match="--views must be"):
        run(RenderConfig(views="every"), run_dir, tmp_path / "a")
    with pytest.raises(FileNotFoundError, match="holds no report.json"):
        run(RenderConfig(), tmp_path, tmp_path / "b")
    with pytest.raises(FileNotFoundError, match=f"no run folder at {tmp_path / 'nope'}"):
        run(RenderConfig(), tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="--views .*none.json: no such camera file"):
        run(RenderConfig(views=str(tmp_path / "none.json")), run_dir, tmp_path / "c")
    (tmp_path / "bad.json").write_text(json.dumps([{"position": [0, 0, 0]}]))
    with pytest.raises(ValueError, match=r"bad.json: camera 0 lacks"):
        cameras_from_json(tmp_path / "bad.json")


def test_a_run_is_found_from_any_folder_and_after_moving_with_its_scene(tmp_path, monkeypatch):
    """A run trained with relative paths (`splat train room -c cues -o run` in its folder) is read from
    another working folder, and still when the run and its scene move together; an old run that
    recorded the relative path alone is found from the folders above it."""
    from splat.render_run import load_run
    from splat.train import TrainConfig
    from splat.train import run as train
    from test_train import surface_cues
    from geocues.cue_io import write_cues_ply

    work = tmp_path / "project"
    root = make_room_scene(work / "room", n_views=6, w=W, h=H, priors="none")
    write_cues_ply(work / "cues" / "cues.ply", surface_cues(root, n_plane=300))
    monkeypatch.chdir(work)
    train(TrainConfig(iters=4, checkpoints=(1.0,), mesh=False, test_every=3), "room", "cues", "outputs/run")
    report = json.loads((work / "outputs" / "run" / "report.json").read_text())
    assert report["scene"] == str(root) and report["scene_from_run"] == "../../room"
    assert report["cues_from_run"] == "../../cues/cues.ply"

    monkeypatch.chdir(tmp_path)  # another working folder
    scene, _, _ = load_run(work / "outputs" / "run")
    assert scene.root == root
    moved = tmp_path / "elsewhere"
    work.rename(moved)  # run and scene moved together: the recorded absolute path is gone
    scene, _, _ = load_run(moved / "outputs" / "run")
    assert scene.root.resolve() == (moved / "room").resolve()

    legacy = {k: v for k, v in report.items() if not k.endswith("_from_run")}
    legacy["scene"] = "room"  # as recorded before: relative to the folder training started in
    (moved / "outputs" / "run" / "report.json").write_text(json.dumps(legacy))
    assert load_run(moved / "outputs" / "run")[0].root.resolve() == (moved / "room").resolve()
    legacy["scene"] = "nowhere"
    (moved / "outputs" / "run" / "report.json").write_text(json.dumps(legacy))
    with pytest.raises(FileNotFoundError, match=r"scene folder nowhere \(recorded in .*report.json\).*--scene"):
        load_run(moved / "outputs" / "run")


def test_a_run_with_the_reference_layout_only_is_rendered(fake_run, tmp_path):
    """A run copied without RUN/point_cloud.ply (the top-level link) but with the reference layout's
    point_cloud/iteration_N/point_cloud.ply renders from the highest N, as SIBR finds it; with neither
    the error names both."""
    import shutil

    from splat.run_paths import gaussians_ply

    run_dir, _ = fake_run
    copy = tmp_path / "copied"
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns("renders"))
    for it in (7, 30):
        (copy / "point_cloud" / f"iteration_{it}").mkdir(parents=True)
        shutil.move(str(copy / "point_cloud.ply"), copy / "point_cloud" / f"iteration_{it}" / "point_cloud.ply")
        shutil.copy(copy / "point_cloud" / f"iteration_{it}" / "point_cloud.ply", copy / "point_cloud.ply")
    (copy / "point_cloud.ply").unlink()
    (copy / "point_cloud" / "iteration_x").mkdir()  # not a number: not a candidate
    assert gaussians_ply(copy) == copy / "point_cloud" / "iteration_30" / "point_cloud.ply"
    out = run(RenderConfig(), copy, tmp_path / "out")
    assert len(list((out / "rgb").glob("*.png"))) == 2
    shutil.rmtree(copy / "point_cloud")
    with pytest.raises(FileNotFoundError, match="no point_cloud.ply nor point_cloud/iteration_N"):
        gaussians_ply(copy)


def test_a_cameras_json_s_names_cannot_leave_the_output_folder(fake_run, tmp_path):
    """img_name "../../evil" wrote every render of the view outside -o (each kind overwriting the last),
    "a/b" failed naming the hidden staging folder, two equal names kept one render, a width of 160.5
    rendered at 160: each is refused naming the camera."""
    run_dir, scene = fake_run
    good = [camera_to_json(i, scene.cameras[i]) for i in (0, 3)]
    for change, said in ((lambda c: c[0].update(img_name="../../evil"), "has img_name '../../evil': a file name"),
                         (lambda c: c[0].update(img_name="a/b"), "has img_name 'a/b'"),
                         (lambda c: c[1].update(img_name=c[0]["img_name"]), "cameras 0 and 1 share the img_name"),
                         (lambda c: c[0].update(width=c[0]["width"] + 0.5), "whole pixels")):
        cams = json.loads(json.dumps(good))
        change(cams)
        path = tmp_path / "path.json"
        path.write_text(json.dumps(cams))
        with pytest.raises(ValueError, match=re.escape(said)):
            run(RenderConfig(views=str(path)), run_dir, tmp_path / "out")
    assert not (tmp_path / "out").exists() and not list(tmp_path.parent.glob("evil*"))


def test_views_that_see_nothing_and_idle_video_options_are_named(fake_run, tmp_path, caplog):
    """A camera at (100, 100, 100) rendered black images with a 'depth 0.00-1.00 m' strip without a
    word; --frames / --fps without --video were ignored in silence."""
    import logging

    run_dir, scene = fake_run
    far = camera_to_json(0, scene.cameras[0])
    far["position"] = [100.0, 100.0, 100.0]
    path = tmp_path / "far.json"
    path.write_text(json.dumps([far, camera_to_json(3, scene.cameras[3])]))
    with caplog.at_level(logging.WARNING, logger="splat"):
        run(RenderConfig(views=str(path), frames=5), run_dir, tmp_path / "out")
    assert "1 of 2 views see no Gaussian (00000)" in caplog.text
    assert "--frames / --fps shape the video: without --video they do nothing" in caplog.text
    (tmp_path / "keep.txt").write_text("a user's file")
    with pytest.raises(ValueError, match="is a file; the renders go into a folder"):
        run(RenderConfig(), run_dir, tmp_path / "keep.txt", overwrite=True)
    assert (tmp_path / "keep.txt").read_text() == "a user's file"
