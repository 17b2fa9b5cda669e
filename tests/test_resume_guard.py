"""Nothing lost, nothing NaN: a killed `splat train` resumes to the uninterrupted result; bad steps
are rolled back; impossible options and finished outputs are clear errors (issue: resumable
training, guarded numerics)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from cues_synth import make_room_scene
from geocues.cue_io import write_cues_ply
from splat.gaussians import load_ply
from test_train import surface_cues

REPO = __import__("pathlib").Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    base = tmp_path_factory.mktemp("resume")
    root = make_room_scene(base / "room", n_views=12, w=64, h=48, priors="all")
    write_cues_ply(base / "cues" / "cues.ply", surface_cues(root, n_plane=1200))
    return base, root, base / "cues"


def _cfg(**kw):
    from splat.mesh import TSDFConfig
    from splat.strategy import IndoorStrategyConfig
    from splat.train import TrainConfig

    base = dict(iters=80, checkpoints=(0.5, 1.0), log_every=5, sh_degree=1, mesh=False,
                strategy=IndoorStrategyConfig(max_gaussians=6000), tsdf=TSDFConfig(voxel_size=0.05))
    base.update(kw)
    return TrainConfig(**base)


def _same_model(a, b) -> float:
    pa, ta = load_ply(a / "point_cloud.ply")
    pb, tb = load_ply(b / "point_cloud.ply")
    assert torch.equal(ta, tb)
    return max(float((pa[k] - pb[k]).abs().max()) for k in pa) if len(ta) else 0.0


@pytest.fixture(scope="module")
def uninterrupted(scene):
    from splat.train import run

    base, root, cues = scene
    return run(_cfg(), root, cues, base / "full")


def _kill_during(monkeypatch, step: int):
    """Make train_step send this process SIGTERM during ``step`` (as a kill would); returns the real
    train_step, for monkeypatch.setattr to put back."""
    import splat.train as train

    real = getattr(train.train_step, "__wrapped__", train.train_step)

    def step_then_kill(*args, **kw):
        out = real(*args, **kw)
        if args[5] == step:
            os.kill(os.getpid(), signal.SIGTERM)
        return out

    step_then_kill.__wrapped__ = real
    monkeypatch.setattr(train, "train_step", step_then_kill)
    return real


def test_a_killed_run_resumes_to_the_uninterrupted_result(scene, uninterrupted, monkeypatch):
    import splat.train as train
    from splat.checkpoint import TrainingInterrupted

    base, root, cues = scene
    real = _kill_during(monkeypatch, 37)  # SIGTERM arrives during step 37
    with pytest.raises(TrainingInterrupted, match="--resume"):
        train.run(_cfg(), root, cues, base / "killed")
    assert (base / "killed.partial" / "ckpt" / "last.pt").is_file()
    assert not (base / "killed").exists()  # nothing published half-way
    monkeypatch.setattr(train, "train_step", real)
    out = train.run(_cfg(), root, cues, base / "killed", resume=True)
    report = json.loads((out / "report.json").read_text())
    assert report["resumed_from_step"] == 38
    t = report["timings"]  # both sessions: the stages add up to no more than the whole
    assert t["total_s"] >= t["train_s"] + t["checkpoints_s"] + t["eval_and_save_s"] > 0
    # the C++ backend reduces gradients per pixel and per Gaussian in a fixed order: bitwise equal
    assert _same_model(out, uninterrupted) == 0.0
    ref = json.loads((uninterrupted / "report.json").read_text())
    assert report["test_metrics"] == ref["test_metrics"]
    log_a = [json.loads(x) for x in (out / "train_log.jsonl").read_text().splitlines()]
    log_b = [json.loads(x) for x in (uninterrupted / "train_log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log_a] == [r["step"] for r in log_b]  # no line lost or doubled
    assert [r["loss"] for r in log_a] == [r["loss"] for r in log_b]
    assert not (base / "killed.partial").exists()


def test_a_run_started_under_the_old_default_budget_resumes_with_it(scene, monkeypatch, caplog):
    """--strategy.max-gaussians defaulted to 0 (no limit) before "auto": a run killed before the
    upgrade and resumed with the same command (the option left out) goes on without a limit, as it
    started, instead of being refused; a budget given differently is refused with both values."""
    import logging

    import splat.train as train
    from splat.checkpoint import TrainingInterrupted
    from splat.strategy import IndoorStrategyConfig

    base, root, cues = scene
    real = _kill_during(monkeypatch, 20)
    with pytest.raises(TrainingInterrupted, match="--resume"):
        train.run(_cfg(strategy=IndoorStrategyConfig(max_gaussians=0)), root, cues, base / "old_default")
    monkeypatch.setattr(train, "train_step", real)
    with pytest.raises(ValueError, match=r"strategy\.max_gaussians.*it has strategy\.max_gaussians=0, this command "
                                         r"strategy\.max_gaussians=5000"):
        train.run(_cfg(strategy=IndoorStrategyConfig(max_gaussians=5000)), root, cues, base / "old_default",
                  resume=True)
    with caplog.at_level(logging.WARNING, logger="splat"):
        out = train.run(_cfg(strategy=IndoorStrategyConfig()), root, cues, base / "old_default", resume=True)
    assert "the default then (now 'auto'); it goes on with 0" in caplog.text
    report = json.loads((out / "report.json").read_text())
    assert report["resumed_from_step"] == 21 and report["gaussian_budget"] == 0
    assert report["config"]["strategy"]["max_gaussians"] == 0


def test_an_auto_budget_resumes_with_the_number_it_started_with(scene, monkeypatch):
    """"auto" is a rule that may change between a kill and the resume: the resumed run keeps the budget
    its first session resolved (kept in the checkpoint), not today's rule's."""
    import splat.strategy as strategy
    import splat.train as train
    from splat.checkpoint import TrainingInterrupted
    from splat.strategy import IndoorStrategyConfig

    base, root, cues = scene
    monkeypatch.setattr(strategy, "AUTO_BUDGET_MIN", 7000)  # 64x48 views: the floor sets it
    real = _kill_during(monkeypatch, 20)
    with pytest.raises(TrainingInterrupted, match="--resume"):
        train.run(_cfg(strategy=IndoorStrategyConfig()), root, cues, base / "rule_change")
    monkeypatch.setattr(strategy, "AUTO_BUDGET_MIN", 9000)  # the rule changed meanwhile
    _kill_during(monkeypatch, 40)
    with pytest.raises(TrainingInterrupted, match="--resume"):  # killed again: its checkpoint still says "auto"
        train.run(_cfg(strategy=IndoorStrategyConfig()), root, cues, base / "rule_change", resume=True)
    monkeypatch.setattr(train, "train_step", real)
    out = train.run(_cfg(strategy=IndoorStrategyConfig()), root, cues, base / "rule_change", resume=True)
    report = json.loads((out / "report.json").read_text())
    assert report["resumed_from_step"] == 41 and report["gaussian_budget"] == 7000
    assert report["config"]["strategy"]["max_gaussians"] == "auto"


def test_a_kill_while_writing_the_outputs_keeps_the_trained_model(scene, uninterrupted, monkeypatch):
    """Ctrl-C after the last step (held-out renders, the mesh) used to lose the whole run: no
    checkpoint, and the next command trained from step 0. Now the trained state is saved and
    --resume writes the outputs without training again: the uninterrupted run's model and log."""
    import splat.train as train
    from splat.checkpoint import TrainingInterrupted

    base, root, cues = scene
    real = train._write_outputs
    monkeypatch.setattr(train, "_write_outputs", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(TrainingInterrupted, match=r"after training \(step 80 of 80\).*--resume"):
        train.run(_cfg(), root, cues, base / "late")
    assert (base / "late.partial" / "ckpt" / "last.pt").is_file() and not (base / "late").exists()
    monkeypatch.setattr(train, "_write_outputs", real)
    monkeypatch.setattr(train, "train_step", lambda *a, **k: pytest.fail("trained again"))
    out = train.run(_cfg(), root, cues, base / "late", resume=True)
    assert json.loads((out / "report.json").read_text())["resumed_from_step"] == 80
    assert _same_model(out, uninterrupted) == 0.0
    rows = [[{k: v for k, v in json.loads(x).items() if k != "train_s"} for x in (run / "train_log.jsonl").read_text()
             .splitlines()] for run in (out, uninterrupted)]
    assert rows[0] == rows[1]  # every row kept, none doubled (seconds aside)


def test_a_stopped_run_is_not_dropped_without_asking(scene):
    """The same command again without --resume used to delete OUT.partial and its checkpoint (a
    warning, then training from step 0): now it is an error naming --resume and --overwrite."""
    from splat.train import run

    base, root, cues = scene
    ckpt = base / "stopped.partial" / "ckpt" / "last.pt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"a checkpoint")
    with pytest.raises(ValueError, match=r"stopped.partial holds an unfinished run with a checkpoint: pass --resume"):
        run(_cfg(iters=4), root, cues, base / "stopped")
    assert ckpt.read_bytes() == b"a checkpoint"
    assert (run(_cfg(iters=4), root, cues, base / "stopped", overwrite=True) / "report.json").is_file()


def test_sigterm_to_the_command_leaves_a_checkpoint_and_one_line(scene):
    base, root, cues = scene
    out = base / "cli"
    env = {**os.environ, "TQDM_DISABLE": "1"}
    cmd = [sys.executable, "-m", "cli.splat_cli", "train", str(root), "-c", str(cues), "-o", str(out),
           "--iters", "4000", "--sh-degree", "0", "--no-mesh", "--strategy.max-gaussians", "3000"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = out.with_name("cli.partial") / "train_log.jsonl"
    deadline = time.time() + 240
    while time.time() < deadline and (not log.is_file() or len(log.read_text().splitlines()) < 3):
        time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err  # 128 + SIGTERM, as a shell reports it
    last = [line for line in err.splitlines() if line.startswith("splat train:")]
    assert len(last) == 1 and "checkpoint" in last[0] and "--resume" in last[0]
    assert "Traceback" not in err
    assert (out.with_name("cli.partial") / "ckpt" / "last.pt").is_file()


def _poison_render(monkeypatch, at_call: int = 30) -> None:
    """The ``at_call``-th training render (test-view renders are not counted) carries a NaN into the
    loss and every gradient."""
    import splat.train as train

    real = train.render_view
    calls = {"n": 0}

    def poisoned(params, view, sh_degree, cfg, maps=True):
        out = real(params, view, sh_degree, cfg, maps=maps)
        calls["n"] += torch.is_grad_enabled()
        return ({**out, "rgb": out["rgb"] * torch.tensor(float("nan"))}
                if calls["n"] == at_call and torch.is_grad_enabled() else out)

    monkeypatch.setattr(train, "render_view", poisoned)


@pytest.mark.parametrize("geometry_until", [1.0, 0.5])  # 0.5: the NaN meets the frozen half's colour step
def test_an_injected_nan_gradient_is_rolled_back_and_the_run_ends_finite(scene, monkeypatch, geometry_until):
    import splat.train as train

    base, root, cues = scene
    _poison_render(monkeypatch, at_call=30 if geometry_until == 1.0 else 60)
    out = train.run(_cfg(geometry_until=geometry_until), root, cues, base / f"nan_{geometry_until}")
    report = json.loads((out / "report.json").read_text())
    assert len(report["guard_events"]) == 1
    event = report["guard_events"][0]
    assert event["reason"] == "non-finite loss" and "rgb" in event["terms"]
    params, _ = load_ply(out / "point_cloud.ply")
    assert all(torch.isfinite(v).all() for v in params.values())
    assert np.isfinite(report["test_metrics"]["psnr"])


def test_without_the_guard_the_same_fault_poisons_the_model(scene, monkeypatch):
    """The guard is what saves the run above: switched off, the NaN lands in the Gaussians."""
    import splat.train as train
    from splat.guard import GuardConfig

    base, root, cues = scene
    _poison_render(monkeypatch)
    with pytest.raises(Exception):
        # non-finite values: the report (allow_nan=False) or the PLY refuses them
        out = train.run(_cfg(guard=GuardConfig(enabled=False)), root, cues, base / "nan_off")
        params, _ = load_ply(out / "point_cloud.ply")
        assert all(torch.isfinite(v).all() for v in params.values())


def test_opacity_resets_are_not_divergence(scene, monkeypatch):
    """After the density control's opacity reset the loss jumps by design (every Gaussian nearly
    transparent); the guard forgets its running level there. A strict guard (2x) over a run with
    resets passes; told nothing of the resets, the same guard takes the first reset for divergence
    (rolls back and cuts the learning rates; a 30k-iteration run at 640x480 on ICL stopped this way
    at its second reset, step 6000)."""
    import splat.train as train
    from splat.guard import GuardConfig, NumericsGuard, TrainingDiverged
    from splat.strategy import IndoorStrategyConfig

    from splat.losses import LossConfig

    base, _, cues = scene
    root = make_room_scene(base / "room_no_priors", n_views=12, w=64, h=48, priors="none")
    # 300 iterations: resets at 30, 60, 90; the RGB loss alone (L_flat off) goes 0.24 -> 0.62 there
    cfg = _cfg(iters=300, strategy=IndoorStrategyConfig(max_gaussians=6000, min_reset_every=1),
               guard=GuardConfig(spike_factor=2.0), loss=LossConfig(lambda_flat=0.0))
    out = train.run(cfg, root, cues, base / "resets")
    rows = [json.loads(x) for x in (out / "train_log.jsonl").read_text().splitlines()]
    resets = [r["step"] for r in rows if r.get("density", {}).get("opacity_reset")]
    assert len(resets) == 3
    assert json.loads((out / "report.json").read_text())["guard_events"] == []

    monkeypatch.setattr(NumericsGuard, "on_opacity_reset", lambda self: None)
    try:  # rolled back (learning rates cut) at the step after the first reset, or stopped
        out = train.run(cfg, root, cues, base / "resets_unnoticed")
        events = json.loads((out / "report.json").read_text())["guard_events"]
    except TrainingDiverged as exc:
        events = [{"step": int(re.search(r"diverged at step (\d+)", str(exc)).group(1)), "reason": str(exc)}]
    assert events and events[0]["step"] == resets[0] + 1 and "running mean" in events[0]["reason"]


def test_learning_rate_1e3_ends_in_a_clear_error_or_a_finite_model(scene, capsys):
    from cli.splat_cli import main

    base, root, cues = scene
    out = base / "lr"
    args = ["train", str(root), "-c", str(cues), "-o", str(out), "--iters", "60", "--sh-degree", "0", "--no-mesh"]
    for name in ("means", "scales", "quats", "opacities", "sh0", "shN"):
        args += [f"--lr.{name}", "1000"]
    code = main(args)
    err = capsys.readouterr().err
    if code == 0:
        params, _ = load_ply(out / "point_cloud.ply")
        assert all(torch.isfinite(v).all() for v in params.values())
    else:
        assert code == 1 and "diverged" in err and "Traceback" not in err


@pytest.mark.parametrize("option,value,message", [
    ("--init.init-opacity", "1.0", "--init.init-opacity must be in (0, 1)"),
    ("--init.init-opacity", "0", "--init.init-opacity must be in (0, 1)"),
    ("--init.min-scale", "0", "--init.min-scale must be a finite number > 0"),
    ("--lr.means", "nan", "--lr.means must be a finite number > 0"),
    ("--loss.lambda-depth", "-1", "--loss.lambda-depth must be a finite number >= 0"),
    ("--device", "tpu", "--device 'tpu': give auto, cpu, cuda or cuda:N"),
])
def test_impossible_options_are_named(scene, capsys, option, value, message):
    from cli.splat_cli import main

    base, root, cues = scene
    assert main(["train", str(root), "-c", str(cues), "-o", str(base / "bad"), option, value]) == 1
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_a_finished_run_is_not_overwritten_without_asking(scene, uninterrupted, capsys):
    from cli.splat_cli import main
    import shutil

    base, root, cues = scene
    out = base / "again"
    shutil.copytree(uninterrupted, out)
    (out / "mesh.ply").write_text("old mesh")  # an earlier run's mesh
    args = ["train", str(root), "-c", str(cues), "-o", str(out), "--iters", "10", "--sh-degree", "0", "--no-mesh"]
    assert main(args) == 1
    assert "holds a finished run; pass --overwrite" in capsys.readouterr().err
    before = (out / "report.json").read_text()
    assert main(args + ["--overwrite"]) == 0
    assert (out / "report.json").read_text() != before
    assert not (out / "mesh.ply").exists()  # no stale mesh beside the new --no-mesh run


def test_config_yaml_repeats_a_run_exactly(scene, capsys):
    from cli.splat_cli import main

    base, root, cues = scene
    a, b = base / "cfg_a", base / "cfg_b"
    assert main(["train", str(root), "-c", str(cues), "-o", str(a), "--iters", "30", "--sh-degree", "1",
                 "--no-mesh", "--loss.lambda-nc", "0.3", "--seed", "4", "--strategy.max-gaussians", "3000"]) == 0
    text = (a / "config.yaml").read_text()
    assert "git_commit" in text and "lambda_nc: 0.3" in text
    assert main(["train", str(root), "-c", str(cues), "-o", str(b), "--load-config", str(a / "config.yaml")]) == 0
    ra, rb = (json.loads((d / "report.json").read_text()) for d in (a, b))
    assert ra["config"] == rb["config"] and ra["test_metrics"] == rb["test_metrics"]
    assert _same_model(a, b) == 0.0
    bad = base / "bad_config.yaml"  # edited by hand: a value of the wrong type is named, not a TypeError
    bad.write_text(text.replace("iters: 30", "iters: abc"))
    assert main(["train", str(root), "-c", str(cues), "-o", str(base / "cfg_c"), "--load-config", str(bad)]) == 1
    err = capsys.readouterr().err
    assert f"{bad}: TrainConfig.iters must be int (like its default 30000), got 'abc'" in err and "Traceback" not in err


def test_quiet_and_verbose_are_in_every_help(capsys):
    from cli.evaluate_cli import main as evaluate
    from cli.geocues_cli import main as geocues
    from cli.splat_cli import main as splat

    for main, cmd in ((splat, "train"), (splat, "ablate"), (geocues, "extract"), (evaluate, "report")):
        assert main([cmd, "--help"]) == 0
        out = capsys.readouterr().out
        assert "-v/--verbose" in out and "-q/--quiet" in out


def test_every_usage_line_names_its_positional_arguments(capsys):
    """`splat ablate --help` said `usage: splat ablate [-h] [OPTIONS] PATH` where the docs say SCENE."""
    from cli.evaluate_cli import COMMANDS as evaluate_commands
    from cli.evaluate_cli import main as evaluate
    from cli.geocues_cli import COMMANDS as geocues_commands
    from cli.geocues_cli import main as geocues
    from cli.splat_cli import COMMANDS as splat_commands
    from cli.splat_cli import main as splat

    for main, commands in ((geocues, geocues_commands), (splat, splat_commands), (evaluate, evaluate_commands)):
        for name in commands:
            assert main([name, "--help"]) == 0
            usage = capsys.readouterr().out.strip().splitlines()[0]
            assert usage.startswith("usage: ") and " PATH" not in usage, usage


def test_an_empty_mesh_is_the_last_warning(scene, monkeypatch, caplog):
    """A run whose Gaussians left the room (--lr.means 1e3 on a benchmark room) fused an empty mesh and
    ended 'done' with one warning deep in its log: now report.json counts the mesh and the last line says."""
    import logging

    import open3d as o3d

    import splat.train_outputs as outputs
    from splat.train import TrainConfig, run

    base, root, cues = scene
    monkeypatch.setattr(outputs, "fuse_mesh", lambda *a, **k: o3d.geometry.TriangleMesh())
    with caplog.at_level(logging.INFO, logger="splat"):
        out = run(TrainConfig(iters=5, sh_degree=0, checkpoints=()), root, cues, base / "empty_mesh")
    assert json.loads((out / "report.json").read_text())["mesh"] == {"vertices": 0, "triangles": 0}
    assert "is EMPTY" in caplog.records[-1].getMessage() and caplog.records[-1].levelname == "WARNING"
    assert "check the cameras" in caplog.records[-1].getMessage()
    import splat.train_outputs as train_outputs  # three photos ended with the same advice: the views are the cause

    monkeypatch.setattr(train_outputs, "FEW_VIEWS", 10_000)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="splat"):
        run(TrainConfig(iters=5, sh_degree=0, checkpoints=()), root, cues, base / "empty_mesh", overwrite=True)
    assert re.search(r"EMPTY .*; \d+ training views are too few to fit a room", caplog.records[-1].getMessage())


def test_quiet_run_prints_no_progress_bars(scene, capsys):
    from cli.splat_cli import main

    base, root, cues = scene
    assert main(["train", str(root), "-c", str(cues), "-o", str(base / "quiet"), "--iters", "10",
                 "--sh-degree", "0", "--no-mesh", "-q"]) == 0
    err = capsys.readouterr().err
    assert "splat train:" not in err and "it/s" not in err
    # before the command too (`splat -q train ...` was "unknown command '-q'")
    assert main(["-q", "train", str(root), "-c", str(cues), "-o", str(base / "quiet2"), "--iters", "10",
                 "--sh-degree", "0", "--no-mesh"]) == 0
    err = capsys.readouterr().err
    assert "splat train:" not in err and "it/s" not in err and "unknown command" not in err


def test_colmap_log_level_follows_quiet_and_verbose(monkeypatch):
    """`-q` left COLMAP's info lines on (about 23 from `geocues undistort`); `-v` shows them all."""
    import logging

    import pycolmap

    from geocues.sfm_steps import quiet_pycolmap

    monkeypatch.setattr(pycolmap.logging, "minloglevel", pycolmap.logging.minloglevel)
    logger = logging.getLogger("geocues")
    before = logger.level
    try:
        for level, want in ((logging.WARNING, 2), (logging.INFO, 1), (logging.DEBUG, 0)):
            logger.setLevel(level)  # clears the logger's cache of isEnabledFor answers
            quiet_pycolmap()
            assert pycolmap.logging.minloglevel == want, (level, want)
    finally:
        logger.setLevel(before)


def test_progress_bars_in_a_log_are_whole_lines(scene, capsys, monkeypatch):
    """stderr redirected to a file (capsys: not a terminal): each bar refresh is a line of its own,
    no carriage returns or cursor moves, which a log file kept as one huge line."""
    import cli._dispatch as dispatch
    from cli.splat_cli import main

    monkeypatch.setattr(dispatch, "LOG_PROGRESS_INTERVAL_S", 0.0)  # every refresh, none held back
    base, root, cues = scene
    assert main(["train", str(root), "-c", str(cues), "-o", str(base / "logged"), "--iters", "10",
                 "--sh-degree", "0", "--no-mesh"]) == 0
    err = capsys.readouterr().err
    bar_lines = [line for line in err.splitlines() if line.startswith("splat train:")]
    assert len(bar_lines) >= 2 and "10/10" in bar_lines[-1]
    assert "\r" not in err and "\x1b[" not in err


def test_short_work_in_a_log_draws_no_bar_and_bars_are_restored_after(capsys):
    import sys

    from tqdm import tqdm

    from cli._dispatch import progress_bars_as_lines

    with progress_bars_as_lines():  # the default interval: work shorter than it draws nothing
        for _ in tqdm(range(3), desc="short work"):
            pass
    assert "short work" not in capsys.readouterr().err
    for _ in tqdm(range(3), desc="after the block", file=sys.stderr):
        pass
    assert "\rafter the block" in capsys.readouterr().err  # tqdm's own redrawing again


def test_an_option_added_after_the_checkpoint_and_left_at_its_default_is_no_difference():
    """A run killed, the toolkit upgraded (new options), the run resumed: options the checkpoint does
    not record and the resume leaves at their defaults train the same, so they do not block it
    (found when an ablation row checkpointed at step 1760 started again after an upgrade)."""
    from dataclasses import asdict, replace

    from splat import checkpoint
    from splat.train import TrainConfig

    cfg, defaults = TrainConfig(), asdict(TrainConfig())
    saved = asdict(cfg)
    del saved["loss"]["plane_anchor"], saved["tsdf"]["max_depth_spread"]  # written before they existed
    assert checkpoint.config_diff(asdict(cfg), saved, defaults) == []
    assert set(checkpoint.config_diff(asdict(cfg), saved)) == {"loss.plane_anchor", "tsdf.max_depth_spread"}
    on = replace(cfg, loss=replace(cfg.loss, plane_anchor=True))
    assert checkpoint.config_diff(asdict(on), saved, defaults) == ["loss.plane_anchor"]
    other = asdict(cfg) | {"iters": cfg.iters + 1}
    assert checkpoint.config_diff(asdict(cfg), other, defaults) == ["iters"]
    gone = asdict(cfg) | {"removed_option": 1}  # an option this version no longer has
    assert checkpoint.config_diff(asdict(cfg), gone, defaults) == ["removed_option"]


def test_resume_refuses_other_inputs_and_allows_bookkeeping_options(scene, monkeypatch, tmp_path):
    """--resume with other cues went on from the checkpoint in silence (report.json naming the new
    cues, config.yaml the old), with another scene it ended in an IndexError; changing only when
    checkpoints are written (--save-every) was refused although it cannot change the training. A run
    moved together with its scene and cues resumes."""
    import splat.train as train
    from splat.checkpoint import TrainingInterrupted

    base, root0, cues0 = scene
    proj = tmp_path / "project"
    root, cues = proj / "room", proj / "cues"
    shutil.copytree(root0, root, symlinks=True)
    shutil.copytree(cues0, cues)
    real = _kill_during(monkeypatch, 9)
    with pytest.raises(TrainingInterrupted):
        train.run(_cfg(iters=20), root, cues, proj / "run")
    monkeypatch.setattr(train, "train_step", real)
    with pytest.raises(ValueError, match=r"--resume: the run in .* started from the cues .*cues.ply, not .*resume0/cues"):
        train.run(_cfg(iters=20), root, cues0, proj / "run", resume=True)
    with pytest.raises(ValueError, match=r"started from the scene .*project/room, not .*resume0/room"):
        train.run(_cfg(iters=20), root0, cues, proj / "run", resume=True)
    moved = tmp_path / "moved"
    proj.rename(moved)  # the run with its inputs
    out = train.run(_cfg(iters=20, save_every=5.0), moved / "room", moved / "cues", moved / "run", resume=True)
    assert json.loads((out / "report.json").read_text())["resumed_from_step"] == 10


def test_progress_lines_hold_their_interval_through_explicit_refreshes(monkeypatch, capsys):
    """README: with stderr in a file a bar writes a line at most every 30 s, none for shorter work. A
    training's bar refreshes itself at each log step (set_postfix), which tqdm's mininterval and delay
    do not hold back: 15 lines in 21 s. The limits are kept per bar, and a bar's last state is written
    when it closes (tqdm then writes a lone newline), whatever its percentage."""
    import cli._dispatch as dispatch

    clock = [0.0]
    monkeypatch.setattr(dispatch, "_clock", lambda: clock[0])
    lines = dispatch._ProgressLines()
    for t, text in [(0, "splat train:   1%|"), (10, "splat train:   5%|"), (31, "splat train:  40%|"),
                    (40, "splat train:  50%|"), (62, "splat train:  80%|"), (70, "splat train:  90%|"),
                    (71, "\n"),  # closed at 90 % (Ctrl-C): its last state is kept
                    (72, "loading views: 100%|"), (72, "\n"),  # a bar that lasted no time: no line
                    (80, "95it [00:03, 25.1it/s]"), (120, "190it [00:43, 4.1it/s]"),  # no description
                    (121, "190it [00:44, 4.0it/s]"), (121, "\n")]:  # closed where it was last written: once
        clock[0] = t
        lines.write(text if text == "\n" else "\r" + text + " 1/2 [00:01<00:01]")
    got = [line.split("|")[0].split(" [")[0] for line in capsys.readouterr().err.splitlines()]
    assert got == ["splat train:  40%", "splat train:  80%", "splat train:  90%", "190it"], got


def test_quiet_silences_bars_that_ask_for_progress(capsys):
    """`splat -q mesh` drew the TSDF bar (its explicit disable=False overrode -q's default)."""
    import numpy as np

    from cli._dispatch import progress_bars_off
    from splat.mesh import fuse_views

    K = np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]])
    views = [(np.full((16, 16), 2.0, np.float32), None, K, np.eye(4))] * 3
    with progress_bars_off():
        fuse_views(views, progress=True)
    err = capsys.readouterr().err  # (the module's INFO line "TSDF fusion: 3 views ..." may be logged)
    assert "view/s" not in err and "%|" not in err, err


def test_keep_ckpt_keeps_the_final_state(scene):
    """--keep-ckpt kept whatever --save-every had last written: nothing for a run shorter than it
    (300 s of training), step 181 of 200 for another."""
    from splat import checkpoint
    from splat.train import run

    base, root, cues = scene
    out = run(_cfg(keep_ckpt=True, save_every=0.0), root, cues, base / "kept")
    saved = checkpoint.load(out / "ckpt" / "last.pt")
    assert saved["step"] == 80 and saved["config"]["keep_ckpt"] is True
