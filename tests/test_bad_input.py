"""Bad input, end to end: one clear error naming the input, exit code != 0, no traceback, no earlier
good output destroyed. One test per row of the table in docs/robustness.md."""

from __future__ import annotations

import shutil
from typing import Annotated

import numpy as np
import pytest
import tyro

from cues_synth import make_room_scene
from geocues.cue_io import CueCloud, write_cues_ply


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    base = tmp_path_factory.mktemp("bad")
    root = make_room_scene(base / "room", n_views=8, w=64, h=48, priors="all")
    write_cues_ply(base / "cues" / "cues.ply", CueCloud.make(np.random.default_rng(0).uniform(0, 3, (200, 3)),
                                                             np.full((200, 3), 0.5), 2))
    return base, root


def _copy(room, name):
    base, root = room
    dst = base / name
    if dst.exists():
        shutil.rmtree(dst)
    return shutil.copytree(root, dst)


def _fails(capsys, main, args, *needles):
    code = main(args)
    err = capsys.readouterr().err
    assert code not in (0, None), err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1, err
    for needle in needles:
        assert needle in errors[0], errors[0]
    assert "Traceback" not in err
    return errors[0]


def geocues(args):
    from cli.geocues_cli import main

    return main(args)


def splat(args):
    from cli.splat_cli import main

    return main(args)


def evaluate(args):
    from cli.evaluate_cli import main

    return main(args)


def test_scene_path_that_is_a_file(room, capsys):
    f = room[0] / "afile"
    f.write_text("x")
    _fails(capsys, geocues, ["info", str(f)], str(f), "is a file")
    _fails(capsys, splat, ["train", str(f), "-c", str(room[0] / "cues"), "-o", str(room[0] / "o1")], "is a file")


def test_missing_scene(room, capsys):
    _fails(capsys, geocues, ["extract", str(room[0] / "nope"), "-o", str(room[0] / "c")], "does not exist")


def test_zero_byte_image(room, capsys):
    root = _copy(room, "zero")
    (root / "images" / "00003.png").write_bytes(b"")
    _fails(capsys, geocues, ["info", str(root)], "00003.png", "empty file")


def test_missing_image(room, capsys):
    root = _copy(room, "missing")
    (root / "images" / "00002.png").unlink()
    _fails(capsys, geocues, ["info", str(root)], "00002.png", "missing")
    for k in (0, 3, 4, 5):  # several: counted, the first three named, the same in every command
        (root / "images" / f"{k:05d}.png").unlink()
    n = len(_model_names(root))
    for cmd in (["info", str(root)], ["sfm", str(root), "-o", str(room[0] / "sfm_missing")]):
        _fails(capsys, geocues, cmd, f"5 of {n} images listed in", "00000.png, ", "00002.png, ", "00003.png and 2 more")


def _model_names(root):
    from geocues.colmap_io import read_model

    return [im.name for im in read_model(root / "sparse" / "0")[0]]


def test_truncated_npy_prior(room, capsys):
    root = _copy(room, "trunc_prior")
    p = root / "priors" / "depth" / "00002.npy"
    p.write_bytes(p.read_bytes()[:200])
    _fails(capsys, geocues, ["extract", str(root), "-o", str(room[0] / "c_trunc")], "00002.npy")


def test_a_prior_that_is_no_npy_file_is_named_so(room, capsys):
    """numpy's own message for a text file named .npy points at unpickling ('allow_pickle=...')."""
    root = _copy(room, "text_prior")
    (root / "priors" / "depth" / "00002.npy").write_text("not an array")
    err = _fails(capsys, geocues, ["extract", str(root), "-o", str(room[0] / "c_text")], "00002.npy")
    assert "it is not a .npy file" in err and "allow_pickle" not in err


def test_wrong_shape_prior(room, capsys):
    root = _copy(room, "shape_prior")
    np.save(root / "priors" / "depth" / "00001.npy", np.ones((48, 64, 2), np.float32))
    _fails(capsys, geocues, ["extract", str(root), "-o", str(room[0] / "c_shape")], "00001.npy", "expected HxW")


def test_nan_prior_pixels_are_dropped_and_counted(room, caplog):
    from geocues.scene import Scene

    root = _copy(room, "nan_prior")
    d = np.load(root / "priors" / "depth" / "00002.npy")
    d[:5] = np.nan
    d[5, :7] = np.inf
    np.save(root / "priors" / "depth" / "00002.npy", d)
    np.save(root / "priors" / "depth" / "00003.npy", d)
    scene = Scene.load(root)
    prior = scene.depth_prior(2)
    assert np.isfinite(prior).all() and (prior[:5] == 0).all() and (prior[5, :7] == 0).all()
    assert "327 non-finite pixels set invalid" in caplog.text  # 5 rows x 64 + 7, counted exactly
    # one warning for the scene, not one per file and read: the next file's and a re-read's at debug level
    caplog.clear()
    with caplog.at_level("DEBUG", logger="geocues.scene"):
        scene.depth_prior(3)
        scene.depth_prior(2)
    assert [r.levelname for r in caplog.records if "non-finite" in r.getMessage()] == ["DEBUG"]

def test_truncated_mesh_ply(room, capsys):
    import open3d as o3d

    box = room[0] / "box.ply"
    o3d.io.write_triangle_mesh(str(box), o3d.geometry.TriangleMesh.create_box())
    cut = room[0] / "box_cut.ply"
    cut.write_bytes(box.read_bytes()[:-40])  # inside the face section
    _fails(capsys, evaluate, [str(cut), "--gt", str(box)], "box_cut.ply", "truncated")


def test_unknown_cue_type(room, capsys):
    base, root = room
    cloud = CueCloud.make(np.random.default_rng(1).uniform(0, 3, (30, 3)), np.full((30, 3), 0.5), 0)
    cloud.cue_type[::3] = 7
    write_cues_ply(base / "cues7" / "cues.ply", cloud)
    _fails(capsys, splat, ["train", str(root), "-c", str(base / "cues7"), "-o", str(base / "o7"), "--iters", "5"],
           "cues.ply", "unknown cue_type values [7]")


def test_output_path_is_a_file(room, capsys):
    base, root = room
    f = base / "out_file"
    f.write_text("keep me")
    _fails(capsys, splat, ["train", str(root), "-c", str(base / "cues"), "-o", str(f), "--iters", "5"], "is a file")
    assert f.read_text() == "keep me"


def test_swapped_scene_and_cues_are_named(room, capsys, caplog):
    """The scene given as the cue folder: the missing cue cloud is the one line (a note on the preset that
    read the scene as cues came first); the cue folder given as the scene says what it is."""
    base, root = room
    _fails(capsys, splat, ["train", str(root), "-c", str(root), "-o", str(base / "sw1"), "--preset", "mvs"],
           "no cue cloud at")
    assert "trains as another row" not in caplog.text
    _fails(capsys, splat, ["train", str(base / "cues"), "-c", str(base / "cues"), "-o", str(base / "sw2")],
           "is a cue folder (cues.ply from `geocues extract`): a command takes it with -c/--cues")
    assert not (base / "sw1").exists() and not (base / "sw2").exists()


def test_resume_without_a_checkpoint(room, capsys):
    base, root = room
    _fails(capsys, splat, ["train", str(root), "-c", str(base / "cues"), "-o", str(base / "fresh"), "--resume"],
           "no checkpoint")


def test_paths_with_spaces_and_non_ascii(room, capsys):
    root = _copy(room, "ro om é")
    assert geocues(["info", str(root)]) == 0
    assert "8" in capsys.readouterr().out


def test_opengl_normal_priors_are_detected_and_converted(room, capsys):
    import json

    from geocues.scene import Scene

    root = _copy(room, "gl_normals")
    scene = Scene.load(root)
    (root / "priors" / "normal").mkdir()
    for i, cam in enumerate(scene.cameras):  # camera-facing normals (OpenCV), written in OpenGL axes
        n = -cam.pixel_rays() / np.linalg.norm(cam.pixel_rays(), axis=-1, keepdims=True)
        np.save(root / "priors" / "normal" / f"{cam.stem}.npy", (n * [1, -1, -1]).astype(np.float32))
    assert Scene.load(root).normals_facing_away() > 0.8  # all but the far off-axis pixels
    assert geocues(["info", str(root)]) == 0
    out = capsys.readouterr().out
    assert "face away from the camera" in out and '"normal_axes": "opengl"' in out
    assert "negated, world-frame or [0, 1]-valued normals look the same" in out  # the other causes, no setting
    (root / "scene.json").write_text(json.dumps({"priors": {"normal_axes": "opengl"}}))
    fixed = Scene.load(root)
    assert fixed.normals_facing_away() < 0.05
    n = fixed.normal_prior(0)
    ref = -scene.cameras[0].pixel_rays() / np.linalg.norm(scene.cameras[0].pixel_rays(), axis=-1, keepdims=True)
    np.testing.assert_allclose(n, ref, atol=1e-5)
    # negated normals with opengl set: still facing away, and said so (the setting had hidden it)
    for cam in scene.cameras:
        n = cam.pixel_rays() / np.linalg.norm(cam.pixel_rays(), axis=-1, keepdims=True)
        np.save(root / "priors" / "normal" / f"{cam.stem}.npy", (n * [1, -1, -1]).astype(np.float32))
    assert geocues(["info", str(root)]) == 0
    assert "although" in (out := capsys.readouterr().out) and "says normal_axes opengl" in out, out


def test_non_finite_sfm_points_are_dropped_and_poses_refused(room, caplog, capsys):
    """pycolmap's text reader refuses NaN itself; a binary model (or a caller's RawPoints) can carry it."""
    from geocues.colmap_io import RawPoints, find_model_dir, read_model
    from geocues.scene import Scene

    base, root = room
    scene = Scene.load(root)
    _, raw = read_model(find_model_dir(root))
    n = len(raw.xyz)
    raw.xyz[:4] = np.nan
    points = Scene._points_from_raw(raw, scene.cameras)
    assert len(points) == n - 4 and np.isfinite(points.xyz).all()
    assert f"4 of {n} points have non-finite coordinates" in caplog.text
    bad = _copy(room, "inf_pose")
    text = (find_model_dir(bad) / "images.txt").read_text().splitlines()
    k = next(i for i, line in enumerate(text) if line and not line.startswith("#"))
    fields = text[k].split()
    fields[5] = "inf"  # TX of the first image
    text[k] = " ".join(fields)
    (find_model_dir(bad) / "images.txt").write_text("\n".join(text) + "\n")
    err = _fails(capsys, geocues, ["info", str(bad)])
    assert "non-finite pose" in err or "could not read COLMAP model" in err


def test_ctrl_c_in_any_command_is_one_line(capsys):
    """A Ctrl-C in a command without a checkpoint of its own (extract, mvs, render, evaluate, ...) ends
    with one line and exit code 130, not a KeyboardInterrupt traceback."""
    from cli._dispatch import dispatch

    def slow() -> int:
        """A command interrupted while it works."""
        raise KeyboardInterrupt

    assert dispatch("tool", {"slow": slow}, argv=["slow"]) == 130
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [
        "tool slow: interrupted; finished outputs are kept, run the same command again to redo the rest"]
    with pytest.raises(KeyboardInterrupt):  # -v keeps the traceback
        dispatch("tool", {"slow": slow}, argv=["slow", "-v"])


def test_exit_code_is_128_plus_the_stopping_signal(capsys):
    """A shell reports a process a signal ended as 128 + its number: 130 for Ctrl-C, 143 for SIGTERM
    (a job scheduler's `kill`). A training stopped by either keeps the code across `splat ablate`'s
    worker processes (the exception is pickled with its signal)."""
    import pickle

    from cli._dispatch import dispatch
    from splat.checkpoint import TrainingInterrupted

    def term() -> int:
        """Stopped by SIGTERM."""
        raise KeyboardInterrupt("SIGTERM")

    def trained(signal_name: str = "SIGINT") -> int:
        """A training stopped after its checkpoint."""
        raise pickle.loads(pickle.dumps(TrainingInterrupted("stopped; checkpoint ckpt/last.pt", signal_name)))

    assert dispatch("tool", {"term": term}, argv=["term"]) == 143
    assert dispatch("tool", {"trained": trained}, argv=["trained", "--signal-name", "SIGTERM"]) == 143
    assert dispatch("tool", {"trained": trained}, argv=["trained"]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "tool trained: stopped; checkpoint ckpt/last.pt"


def test_sigterm_in_any_command_is_one_line_not_a_native_stack_trace():
    """`kill PID` of a command that imported pycolmap (whose glog dumps a native stack trace on
    SIGTERM and exits 0) ends like Ctrl-C with one line, exit code 143 (128 + SIGTERM, as a shell
    reports a process the signal ended; Ctrl-C's is 130)."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import os, signal, time\n"
            "from cli._dispatch import dispatch\n"
            "def work() -> int:\n"
            "    '''Imports pycolmap, then is killed.'''\n"
            "    import pycolmap  # noqa: F401\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    time.sleep(5)\n"
            "    return 0\n"
            "raise SystemExit(dispatch('tool', {'work': work}, argv=['work']))\n")
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 143, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "tool work: interrupted; finished outputs are kept, run the same command again to redo the rest"]


def test_dispatch_restores_the_callers_sigterm_handler():
    import signal

    from cli._dispatch import dispatch

    def quick() -> int:
        """Returns at once."""
        return 0

    before = signal.getsignal(signal.SIGTERM)
    assert dispatch("tool", {"quick": quick}, argv=["quick"]) == 0
    assert signal.getsignal(signal.SIGTERM) is before


def test_help_into_a_closed_pipe_is_quiet():
    """`splat ablate --help | head -2`: the reader leaves early; the command stops without a
    BrokenPipeError traceback (exit 1, as Python's own tools on EPIPE)."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import time\n"
            "from cli._dispatch import dispatch\n"
            "time.sleep(1.0)  # the reader has left by now\n"
            "def work(count: int = 1) -> int:\n"
            "    '''Its help goes to a reader that has left.'''\n"
            "    return 0\n"
            "raise SystemExit(dispatch('tool', {'work': work}, argv=['work', '--help']))\n")
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=repo, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader leaves before the command writes
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) in (0, 1), err
    assert "Traceback" not in err and "BrokenPipe" not in err, err


def _mesh_command(path: Annotated[str, tyro.conf.Positional]) -> int:
    """Score a mesh."""
    print(f"scored {path}")
    return 0


def _report_command(run: Annotated[str, tyro.conf.Positional]) -> int:
    """Plots of a run."""
    return 0


def test_a_mistyped_command_is_named_not_taken_for_a_path(tmp_path, capsys, monkeypatch):
    """`evaluate views --help` showed `mesh`'s usage ('views' taken for PRED_MESH), `evaluate reprt RUN`
    said "no mesh at reprt": a bare word that is no file is an unknown command, with the nearest one;
    a file of that name (or any path) still goes to the default command."""
    from cli._dispatch import dispatch

    commands = {"mesh": _mesh_command, "report": _report_command}
    assert dispatch("tool", commands, default="mesh", argv=["reprt", "x"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tool: unknown command 'reprt' (did you mean 'report'?); `tool PATH ...` runs `mesh`")
    assert dispatch("tool", commands, default="mesh", argv=["views", "--help"]) == 2
    assert "unknown command 'views';" in capsys.readouterr().err
    monkeypatch.chdir(tmp_path)
    (tmp_path / "views").write_text("a mesh without a suffix")
    for word in ("views", "a.ply", "sub/b"):
        assert dispatch("tool", commands, default="mesh", argv=[word]) == 0
        assert capsys.readouterr().out == f"scored {word}\n"
    assert dispatch("tool", {"mesh": _mesh_command}, argv=["mseh"]) == 2  # no default: the nearest command too
    assert "unknown command 'mseh' (did you mean 'mesh'?)" in capsys.readouterr().err


def test_a_scene_sfm_left_most_photos_out_of_is_named_at_every_step(room, capsys, caplog):
    """`geocues sfm` put 15 of 40 photos of a bare room into the model: it warned once, and undistort,
    rescale, mvs, extract, train and evaluate went on without a word to a mesh scoring 1 m (new-user
    audit). scene.json keeps the counts; info, extract, train and evaluate name them."""
    import json

    from geocues.advice import registration_warning

    assert registration_warning({}) is None and registration_warning({"sfm_registered": "x"}) is None
    assert registration_warning({"sfm_registered": {"images": 36, "photos": 40}}) is None  # 90 %: no word
    few = registration_warning({"sfm_registered": {"images": 15, "photos": 40}})
    assert "only 15 of the 40 photos" in few
    base, _ = room
    root = _copy(room, "few_registered")
    (root / "scene.json").write_text(json.dumps({"sfm_registered": {"images": 15, "photos": 40}}))
    assert geocues(["info", str(root)]) == 0
    assert "warning    `geocues sfm` put only 15 of the 40 photos" in capsys.readouterr().out
    shutil.copyfile(next((root / "images").iterdir()), root / "images" / "zz_unposed.png")  # a photo not in the model
    assert "could not register them" in (geocues(["info", str(root)]), capsys.readouterr().out)[1]
    (root / "scene.json").write_text(json.dumps({"sfm_registered": {"images": "15", "photos": 40}}))  # by hand
    assert geocues(["info", str(root)]) == 0  # was a TypeError traceback
    assert "photos added after SfM" in capsys.readouterr().out
    (root / "images" / "zz_unposed.png").unlink()
    (root / "scene.json").write_text(json.dumps({"sfm_registered": {"images": 15, "photos": 40}}))
    with caplog.at_level("WARNING"):
        assert geocues(["extract", str(root), "-o", str(base / "few_cues"), "--no-lines", "--no-planes"]) == 0
    assert "only 15 of the 40 photos" in caplog.text
    import torch

    from splat.train_config import TrainConfig
    from splat.train_setup import setup_training

    caplog.clear()
    with caplog.at_level("WARNING"):
        setup_training(TrainConfig(iters=10), root, base / "cues" / "cues.ply", torch.device("cpu"))
    assert "only 15 of the 40 photos" in caplog.text  # what `splat train` meets before its first step
    import open3d as o3d

    o3d.io.write_triangle_mesh(str(base / "few.ply"), o3d.geometry.TriangleMesh.create_box())
    capsys.readouterr()
    assert evaluate([str(base / "few.ply"), str(root), "--gt", str(base / "few.ply")]) == 0
    assert "warning: `geocues sfm` put only 15 of the 40 photos" in capsys.readouterr().err


def test_a_warning_line_says_it_is_one(capsys):
    """In a run's many info lines a warning looked like the others ('[time module] message'): warnings and
    errors say so after the module (researcher audit); info lines are unchanged."""
    import logging

    import re

    from cli._dispatch import setup_logging

    setup_logging()
    log = logging.getLogger("evaluation.test_format")
    log.info("an info line")
    log.warning("a warning line")
    err = capsys.readouterr().err
    assert re.search(r"^\[\d\d:\d\d:\d\d evaluation\.test_format\] an info line$", err, re.M), err
    assert re.search(r"^\[\d\d:\d\d:\d\d evaluation\.test_format\] warning: a warning line$", err, re.M), err
