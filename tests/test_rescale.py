"""Metric scale: the extent is reported, a far-from-metric scene is warned about, and `geocues
rescale` makes it metric by a given factor or from metric depth priors (round trip to 1e-9)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from cues_synth import make_room_scene, render
from geocues.rescale import (DEPTH_RANGE, ROOM_RANGE, RescaleConfig, median_view_depth, metric_warning, run,
                             scale_from_priors, scene_extent)
from geocues.scene import Scene


@pytest.fixture(scope="module")
def rooms(tmp_path_factory):
    base = tmp_path_factory.mktemp("rescale")
    root = make_room_scene(base / "room", n_views=6, w=64, h=48, priors="none", n_outliers=0)
    scene = Scene.load(root, check_priors=False)
    (root / "priors" / "depth").mkdir(parents=True)
    for cam in scene.cameras:  # metric priors (a depth sensor): the exact depth
        np.save(root / "priors" / "depth" / f"{cam.stem}.npy",
                render(cam.K, cam.R, cam.t, cam.width, cam.height)[1].astype(np.float32))
    small = run(RescaleConfig(scale=0.01), root, base / "small")  # what an images-only SfM might return
    return base, root, small


def test_extent_and_the_warning(rooms, capsys):
    from cli.geocues_cli import main

    _, root, small = rooms
    big, tiny = Scene.load(root, check_priors=False), Scene.load(small, check_priors=False)
    assert 2 < scene_extent(big) < 6 and scene_extent(tiny) == pytest.approx(scene_extent(big) / 100)
    assert metric_warning(big) is None
    # a copy `geocues rescale` made 0.04 m across: said, with the way back to the original (advising to
    # rescale this copy by the same rule again gave it the same factor, forever)
    said = metric_warning(tiny)
    assert "spans 0.0" in said and " m, not the 0.5-200 m" in said and "`geocues rescale` (--scale 0.01) made it so" in said
    assert f"rescale {root} again with the factor you know (--scale S" in said
    assert main(["info", str(small)]) == 0
    out = capsys.readouterr().out
    assert "extent" in out and "not the 0.5-200 m" in out
    assert re.search(r"extent     [\d.]+ m \(", out)  # rescaled: metres (it said "units" after rescaling)
    assert "geocues rescale " + str(small) not in out  # no step that rescales the copy again
    assert main(["info", str(root)]) == 0
    assert re.search(r"extent     [\d.]+ units \(", capsys.readouterr().out)  # a model's own unit


def test_a_plausible_extent_with_implausible_depths_is_warned(rooms):
    """COLMAP normalises an images-only model to about 10 units: a room 8x too large still spans a
    plausible 16-48 units, but its photos look 12 units far, which no room's do."""
    base, root, _ = rooms
    big = Scene.load(root, check_priors=False)
    x8 = Scene.load(run(RescaleConfig(scale=8.0), root, base / "x8"), check_priors=False)
    assert ROOM_RANGE[0] <= scene_extent(x8) <= ROOM_RANGE[1]
    assert median_view_depth(x8) == pytest.approx(8 * median_view_depth(big))
    assert DEPTH_RANGE[0] <= median_view_depth(big) <= DEPTH_RANGE[1] < median_view_depth(x8)
    assert metric_warning(big) is None and "median depth" in metric_warning(x8)
    # nothing known: a guess of the views' median depth makes it metric to within the guess
    guess = Scene.load(run(RescaleConfig(median_depth=2.0), base / "x8", base / "guess"), check_priors=False)
    assert median_view_depth(guess) == pytest.approx(2.0, rel=1e-6) and metric_warning(guess) is None
    assert "`geocues rescale` (--scale 8) made it so" in metric_warning(x8)
    import shutil

    shutil.copytree(base / "x8", base / "x8_model")  # the same model, not marked as rescaled: a SfM's own unit
    meta = json.loads((base / "x8_model" / "scene.json").read_text())
    (base / "x8_model" / "scene.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "rescaled"}))
    assert "--median-depth 2" in metric_warning(Scene.load(base / "x8_model", check_priors=False))


def test_from_priors_recovers_the_scale_and_round_trips(rooms):
    base, root, small = rooms
    s, used = scale_from_priors(Scene.load(small, check_priors=False))
    assert s == pytest.approx(100, rel=0.01) and used >= 4  # views with 20+ SfM points in view
    back = run(RescaleConfig(from_priors=True), small, base / "back")
    assert json.loads((back / "scene.json").read_text())["rescaled"]["scale"] == pytest.approx(s)
    a, b = Scene.load(root, check_priors=False), Scene.load(back, check_priors=False)
    for ca, cb in zip(a.cameras, b.cameras):
        np.testing.assert_allclose(cb.R, ca.R, atol=1e-9)
        np.testing.assert_allclose(cb.t, ca.t, rtol=0.01, atol=1e-6)
    np.testing.assert_allclose(b.points.xyz, a.points.xyz, rtol=0.01, atol=1e-3)


def test_from_priors_on_simulated_priors_is_warned(rooms, tmp_path, caplog):
    """Simulated priors carry a random scale error per image: the factor they give (1.10 on a metric
    room) measures that, not the scene's unit; it was written without a word."""
    import logging
    import shutil

    base, root, small = rooms
    sim = tmp_path / "sim"
    shutil.copytree(small, sim)
    meta = json.loads((sim / "scene.json").read_text()) if (sim / "scene.json").is_file() else {}
    (sim / "scene.json").write_text(json.dumps({**meta, "priors": {"simulated": True}}))
    with caplog.at_level(logging.WARNING, logger="geocues"):
        run(RescaleConfig(from_priors=True), sim, tmp_path / "out")
    assert "are SIMULATED" in caplog.text


def test_bad_options_are_named(rooms, tmp_path):
    _, root, _ = rooms
    for cfg in (RescaleConfig(), RescaleConfig(scale=2.0, median_depth=2.0), RescaleConfig(scale=2.0, from_priors=True)):
        with pytest.raises(ValueError, match="one of --scale S, --from-priors or --median-depth M"):
            run(cfg, root, tmp_path / "x")
    with pytest.raises(ValueError, match="--median-depth must be a positive"):
        run(RescaleConfig(median_depth=0.0), root, tmp_path / "x")
    with pytest.raises(ValueError, match="positive"):
        run(RescaleConfig(scale=-2.0), root, tmp_path / "x")
    for scale in (1e300, 1e-12):  # accepted: training then failed on an inf camera, the scale unnamed
        with pytest.raises(ValueError, match=r"m across: no scene is; check --scale"):
            run(RescaleConfig(scale=scale), root, tmp_path / "x")
    assert not (tmp_path / "x").exists()
    plain = make_room_scene(tmp_path / "plain", n_views=4, w=64, h=48, priors="none")
    with pytest.raises(ValueError, match="no view of .* has a depth prior"):
        run(RescaleConfig(from_priors=True), plain, tmp_path / "y")


def test_from_priors_takes_the_points_each_view_sees_and_refuses_disparity(rooms, tmp_path):
    """Points behind a wall project into a view too: with them the factor of exact metric priors came
    out 1.3 % low on a benchmark room. Disparity priors have no unit: refused, not read as depth."""
    from dataclasses import replace

    base, root, small = rooms
    scene = Scene.load(small, check_priors=False)
    pts, n = scene.points, len(scene.points)
    cam = scene.cameras[0]
    hidden = cam.center + 1.6 * (pts.xyz - cam.center)  # behind what each point lies on, seen from view 0
    scene.points = replace(pts, ids=np.arange(2 * n), xyz=np.concatenate([pts.xyz, hidden]),
                           rgb=np.concatenate([pts.rgb, pts.rgb]), error=np.concatenate([pts.error, pts.error]),
                           track_length=np.concatenate([pts.track_length, pts.track_length]),
                           visible_in={i: np.arange(n) for i in range(len(scene.cameras))})
    s, _ = scale_from_priors(scene)
    assert s == pytest.approx(100, rel=5e-3), s  # the hidden points alone would give 62.5
    meta = json.loads((small / "scene.json").read_text()) if (small / "scene.json").is_file() else {}
    disp = tmp_path / "disparity"
    import shutil
    shutil.copytree(small, disp, symlinks=True)
    (disp / "scene.json").unlink(missing_ok=True)
    (disp / "scene.json").write_text(json.dumps({**meta, "priors": {"depth_kind": "disparity"}}))
    with pytest.raises(ValueError, match="--from-priors needs metric depth priors; .* are disparity"):
        run(RescaleConfig(from_priors=True), disp, tmp_path / "out")


def test_priors_of_geocues_mvs_are_in_the_scene_unit_and_tell_no_scale(rooms, tmp_path):
    """`geocues mvs` writes depth in the scene's own unit: `--from-priors` rescaled such a scene by
    0.999, dropped its "arbitrary" mark and `geocues info` advised it again, forever."""
    import shutil

    from geocues.advice import next_steps
    from geocues.mvs import MVS_PRIORS

    _, _, small = rooms
    mvs = tmp_path / "mvs"
    shutil.copytree(small, mvs)
    meta = json.loads((mvs / "scene.json").read_text())
    (mvs / "scene.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "rescaled"}
                                               | {"scale": "arbitrary", "priors": MVS_PRIORS}))
    with pytest.raises(ValueError, match=r"--from-priors: the depth priors of .* were written by `geocues mvs` .* "
                                         r"cannot tell its scale; give --scale .* or --median-depth"):
        run(RescaleConfig(from_priors=True), mvs, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    s = Scene.load(mvs, check_priors=False)
    cmd = next_steps(s, not_metric=metric_warning(s) is not None)[0][0]
    assert cmd.startswith(f"geocues rescale {mvs} -o ") and cmd.endswith("--median-depth 2")
    assert "in the scene's unit" in MVS_PRIORS["method"]
    # rescaled after `geocues mvs`, its depth scales with the scene (linked as metric, it was 100x off)
    back = Scene.load(run(RescaleConfig(scale=100.0), mvs, tmp_path / "x100"), check_priors=False)
    assert not (tmp_path / "x100" / "priors").is_symlink()
    for i in (0, 3):
        np.testing.assert_allclose(back.depth_prior(i), 100 * s.depth_prior(i), rtol=1e-6)
