"""`geocues extract` options a user sweeps (found by a sweep of 150 runs): a NaN, an inf or a value that
gave empty cues or garbage is refused before any work, with one line naming the option."""

from __future__ import annotations

import re

import pytest

from geocues.extract import ExtractConfig
from geocues.extract_checks import check_extract_options
from geocues.presets import EXTRACT_PRESETS, apply_overrides, extract_preset_config


@pytest.mark.parametrize("name", list(EXTRACT_PRESETS))
def test_every_preset_passes(name):
    check_extract_options(extract_preset_config(name))


@pytest.mark.parametrize("change, said", [
    ({"line.support_dist_px": float("inf")}, "--line.support-dist-px must be a finite number, got inf"),  # OverflowError
    ({"plane.cut_px": float("inf")}, "--plane.cut-px must be a finite number, got inf"),
    ({"sor.sor_std_ratio": float("nan")}, "--sor.sor-std-ratio must be a finite number, got nan"),  # removed every point
    ({"line.pair_depths_m": (1.0, float("nan"))}, "--line.pair-depths-m must be a finite number, got nan"),
    ({"line.support_angle_deg": -5.0}, "--line.support-angle-deg is an angle and must be in [0, 180] degrees"),
    ({"sor.sor_neighbors": 1}, "--sor.sor-neighbors must be >= 2, got 1"),  # Open3D removed every point
    ({"texture.work_width": 0}, "--texture.work-width must be >= 16 px, got 0"),  # became 16 in silence
    ({"plane.voxel_size": 0.0}, "--plane.voxel-size must be > 0, got 0.0"),  # divide by zero, 0 planes
    ({"plane.min_ray_cos": 2.0}, "--plane.min-ray-cos is a share and must be in [0, 1], got 2.0"),
    ({"plane.max_planes": 0}, "--plane.max-planes must be >= 1, got 0"),
    ({"line.max_depth_m": -1.0}, "--line.max-depth-m must be > 0, got -1.0"),
    ({"texture.erode_px": -4}, "--texture.erode-px must be >= 0 (0: off), got -4"),
    ({"sfm": False, "lines": False, "planes": False}, "--no-sfm --no-lines --no-planes leave nothing to extract"),
    ({"align.max_anchors": 10}, "--align.max-anchors (10) must be >= --align.min-anchors (20)"),  # "too few anchors"
])
def test_impossible_options_are_refused_naming_the_flag(change, said):
    with pytest.raises(ValueError, match=re.escape(said)):
        check_extract_options(apply_overrides(ExtractConfig(), change))


def test_the_command_refuses_before_any_work(tmp_path, capsys):
    from cli.geocues_cli import main

    assert main(["extract", str(tmp_path), "-o", str(tmp_path / "cues"), "--line.support-dist-px", "inf"]) == 1
    err = capsys.readouterr().err
    assert "--line.support-dist-px must be a finite number" in err and "Traceback" not in err
    assert not (tmp_path / "cues").exists()


def test_lines_leave_out_the_held_out_views_when_asked(tmp_path, monkeypatch):
    """--line.no-use-test-views was ignored (extract reads the scene with every view, so 'the training
    views' were all of them): the views with index % --line.test-every == 0 are left out of the pairs."""
    import geocues.extract as ex
    import geocues.lines.pipeline as pipeline
    from cues_synth import make_room_scene

    root = make_room_scene(tmp_path / "room", n_views=10, w=96, h=72, priors="none")
    used = []
    real = pipeline.select_neighbors
    monkeypatch.setattr(pipeline, "select_neighbors", lambda scene, cfg, use: used.append(list(use)) or real(scene, cfg, use))
    for keep, test_every, out in ((True, 8, "all"), (False, 8, "train8"), (False, 3, "train3")):
        cfg = apply_overrides(ExtractConfig(), {"planes": False, "line.use_test_views": keep,
                                                "line.test_every": test_every})
        ex.run(cfg, root, tmp_path / out)
    assert used == [list(range(10)), [1, 2, 3, 4, 5, 6, 7, 9], [1, 2, 4, 5, 7, 8]]


def test_upsampling_is_named_as_in_training(tmp_path, caplog):
    """--downscale below 1 upsampled the photos for the extraction (4x the work at 0.5) without a word;
    `splat train` already said so: one sentence, geocues.scene.upsampling_warning, for both."""
    import geocues.extract as ex
    from cues_synth import make_room_scene
    from geocues.scene import upsampling_warning

    assert upsampling_warning(1.0, "x", "y") is None and upsampling_warning(2.0, "x", "y") is None
    root = make_room_scene(tmp_path / "room", n_views=4, w=48, h=36, priors="none")
    ex.run(apply_overrides(ExtractConfig(), {"planes": False, "lines": False, "downscale": 0.5}), root, tmp_path / "c")
    assert "--downscale 0.5 is below 1: the photos are UPSAMPLED 2x" in caplog.text
    assert "4x the work per image); --downscale 1 extracts at the photos' own size" in caplog.text


def test_a_kill_among_the_writes_of_an_overwrite_leaves_no_finished_mix(tmp_path, monkeypatch):
    """A kill right after cues.ply of an --overwrite run was renamed into place left the old report.json
    (the finished marker) beside the new cues: the rerun with the first options skipped, 'already holds
    this run', and returned the other run's cues."""
    import geocues.extract as ex
    from cues_synth import make_room_scene

    root = make_room_scene(tmp_path / "room", n_views=6, w=96, h=72, priors="none")
    out = tmp_path / "cues"
    first = apply_overrides(ExtractConfig(), {"planes": False})
    ex.run(first, root, out)
    wanted = (out / "cues.ply").read_bytes()

    def killed(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ex, "write_cues_by_type_ply", killed)  # after cues.ply is in place
    with pytest.raises(KeyboardInterrupt):
        ex.run(apply_overrides(first, {"sor.sor_std_ratio": 0.3}), root, out, overwrite=True)
    assert (out / "cues.ply").read_bytes() != wanted and not (out / "report.json").exists()
    monkeypatch.undo()
    ex.run(first, root, out)  # no --overwrite: extracted again, not skipped as finished
    assert (out / "cues.ply").read_bytes() == wanted and (out / "report.json").is_file()


def test_preset_mistakes_and_a_skipped_rerun_are_said(tmp_path, capsys):
    """`--preset room --preset paper` ran room (the first); `--preset room --floor.no-lines` blamed
    --floor.walls, a flag the user never typed; a rerun that did nothing printed the old run's seconds
    as if it had run, and with -q nothing said it was skipped."""
    from cli.geocues_cli import main
    from cues_synth import make_room_scene

    root = make_room_scene(tmp_path / "room", n_views=6, w=96, h=72, priors="none")
    out = tmp_path / "cues"
    assert main(["extract", str(root), "-o", str(out), "--preset", "room", "--preset", "paper"]) == 1
    assert "--preset is given 2 times (room, paper): give it once" in capsys.readouterr().err
    assert main(["extract", str(root), "-o", str(out), "--preset", "room", "--floor.no-lines"]) == 1
    assert "(--preset room turns on --floor.lines, --floor.walls" in capsys.readouterr().err
    assert main(["-q", "extract", str(root), "-o", str(out), "--no-planes"]) == 0
    assert '"seconds"' in capsys.readouterr().out
    assert main(["-q", "extract", str(root), "-o", str(out), "--no-planes"]) == 0
    said = capsys.readouterr().out
    assert said.startswith(f"{out} already holds these cues (same options and scene): nothing redone")
    assert '"seconds"' not in said


def test_options_of_a_stage_that_is_off_are_named():
    from geocues.extract_checks import idle_options

    assert idle_options(ExtractConfig()) == []
    said = idle_options(apply_overrides(ExtractConfig(), {"floor.min_views": 10, "plane.surface_angle_deg": 1.0}))
    assert said == ["--floor.min-views does nothing: floor lines are off (--floor.lines)"]
    said = idle_options(apply_overrides(ExtractConfig(), {"planes": False, "plane.voxel_size": 0.05,
                                                          "align.inlier_rel": 0.05}))
    assert said == ["--plane.voxel-size does nothing: the plane stage is off (--no-planes)",
                    "--align.inlier-rel does nothing: depth priors are not read (--no-planes or --no-priors)"]
    assert idle_options(extract_preset_config("room")) == []


def test_a_refused_rerun_says_what_changed(tmp_path):
    """'holds cues of another configuration or scene (config A vs B)' did not say which: the options that
    differ, or else that the scene's files changed (a prior touched)."""
    import os

    import geocues.extract as ex
    from cues_synth import make_room_scene

    root = make_room_scene(tmp_path / "room", n_views=6, w=96, h=72, priors="all")
    first = apply_overrides(ExtractConfig(), {"planes": False})
    ex.run(first, root, tmp_path / "cues")
    with pytest.raises(ValueError, match=r"options --sor\.sor-std-ratio, --line\.min-views differ\); pass --overwrite"):
        ex.run(apply_overrides(first, {"line.min_views": 4, "sor.sor_std_ratio": 3.0}), root, tmp_path / "cues")
    prior = sorted((root / "priors" / "depth").iterdir())[0]
    os.utime(prior, (2e9, 2e9))
    with pytest.raises(ValueError, match=r"the same options: the scene's images/, priors/, sparse/ or scene.json changed"):
        ex.run(first, root, tmp_path / "cues")
