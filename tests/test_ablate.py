"""`splat ablate` on the tiny synthetic room: every file with its keys, resume after a kill, n/a rows,
the floor, presets, and Ray dispatch against --jobs 1."""

from __future__ import annotations

import json
import re
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from cues_synth import make_room_scene, render, room_mesh
from geocues.cue_io import write_cues_ply
from geocues.scene import Scene
from test_train import surface_cues

TRAIN_ARGS = ["--sh-degree", "0", "--tsdf.voxel-size", "0.05", "--strategy.max-gaussians", "8000",
              "--log-every", "5"]


def png_size(path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR, after checking the whole file decodes (zlib stream)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", path
    w, h = struct.unpack(">II", data[16:24])
    idat, pos = b"", 8
    while pos < len(data):
        n = struct.unpack(">I", data[pos:pos + 4])[0]
        if data[pos + 4:pos + 8] == b"IDAT":
            idat += data[pos + 8:pos + 8 + n]
        pos += 12 + n
    assert len(zlib.decompress(idat)) > 0
    return w, h


def write_gt(root):
    """gt/mesh.ply and exact gt/depth/<stem>.npy for the synthetic room."""
    import open3d as o3d

    V, T, _ = room_mesh()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
    (root / "gt" / "depth").mkdir(parents=True, exist_ok=True)
    o3d.io.write_triangle_mesh(str(root / "gt" / "mesh.ply"), mesh)
    for cam in Scene.load(root, check_priors=False).cameras:
        _, depth, _ = render(cam.K, cam.R, cam.t, cam.width, cam.height)
        np.save(root / "gt" / "depth" / f"{cam.stem}.npy", depth.astype(np.float32))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    base = tmp_path_factory.mktemp("ablate")
    root = make_room_scene(base / "room", n_views=16, w=64, h=48, priors="all")
    write_gt(root)
    write_cues_ply(base / "cues" / "cues.ply", surface_cues(root, n_plane=1500))
    return base, root, base / "cues"


def _run(tiny, out, rows, **kw):
    from evaluation.mesh_metrics import MeshMetricsConfig
    from splat.ablate import AblateConfig, run

    base, root, cues = tiny
    cfg = AblateConfig(rows=tuple(rows), iters=30, checkpoints=(0.5, 1.0),
                       metrics=MeshMetricsConfig(n_samples=20_000), **kw)
    return run(cfg, root, cues, base / out, train_args=TRAIN_ARGS)


@pytest.fixture(scope="module")
def ablation(tiny):
    return _run(tiny, "out", ["full", "no-cues", "no-ln"], num_threads=1)


def test_every_file_with_its_keys(ablation):
    out = ablation
    for name in ("ablation.json", "report.md", "accuracy_vs_time.png"):
        assert (out / name).is_file(), name
    data = json.loads((out / "ablation.json").read_text())
    assert set(data) >= {"scene", "cues", "config", "train_args", "train_keys", "floor", "rows"}
    rows = {r["row"]: r for r in data["rows"]}
    assert list(rows) == ["full", "no-cues", "no-ln"]
    for name in ("full", "no-cues"):
        r = rows[name]
        assert r["status"] == "done" and r["n_seeds"] == 1
        curve = r["runs"][0]["curve"]
        assert [c["step"] for c in curve] == [15, 30]
        for c in curve:
            assert set(c) >= {"train_s", "psnr", "chamfer_l1", "f_score", "normal_consistency"}
            assert np.isfinite(c["chamfer_l1"]) and 0 <= c["f_score"] <= 1
        assert r["mean"]["chamfer_l1"] == pytest.approx(curve[-1]["chamfer_l1"])
    # the synthetic room has depth priors but no normal priors: no-ln would be `full` again
    assert rows["no-ln"]["status"] == "n/a" and "normal" in rows["no-ln"]["reason"]
    md = (out / "report.md").read_text()
    assert "n/a (no normal priors)" in md and "**floor**" in md
    assert "4.0 / 0.776 / 0.877" in md  # the paper's full row beside ours (its C-L1 in cm, as ours)
    assert png_size(out / "accuracy_vs_time.png") == (1080, 720)


def test_the_same_ablation_elsewhere_merges_and_another_training_does_not(tiny, ablation, tmp_path):
    """``train_keys`` hold the training, not where it ran: the room copied to another folder, its cues
    elsewhere, another OUT give the same keys, and the two summaries merge (an ablation finished on two
    machines); another train option gives other keys."""
    from evaluation.ablation_report import merge_summaries
    from evaluation.mesh_metrics import MeshMetricsConfig
    from splat.ablate import AblateConfig, run, train_config
    from splat.ablate_keys import training_keys

    base, root, cues = tiny
    room, elsewhere = shutil.copytree(root, tmp_path / root.name), shutil.copytree(cues, tmp_path / "c2")
    cfg = AblateConfig(rows=("no-cues",), iters=30, checkpoints=(0.5, 1.0), metrics=MeshMetricsConfig(n_samples=20_000),
                       num_threads=1)
    there = json.loads((run(cfg, room, elsewhere, tmp_path / "out", train_args=TRAIN_ARGS) / "ablation.json").read_text())
    here = json.loads((ablation / "ablation.json").read_text())
    assert there["train_keys"] == here["train_keys"] and there["scene"] != here["scene"]
    merged = merge_summaries(here, there)
    assert [r["row"] for r in merged["rows"] if r["status"] == "done"] == ["full", "no-cues"]
    other = training_keys(train_config("full", [*TRAIN_ARGS, "--sh-degree", "1"], 30, 0, (0.5, 1.0)))
    assert not set(other) & set(here["train_keys"])


def test_no_cues_row_is_the_baseline(ablation):
    rows = {r["row"]: r for r in json.loads((ablation / "ablation.json").read_text())["rows"]}
    init = rows["no-cues"]["runs"][0]["gaussians_init"]
    assert init["LINE"] == 0 and init["PLANE"] == 0 and init["SFM"] > 0  # SfM-point init only
    cfg = json.loads((ablation / "rows" / "no-cues_s0" / "train" / "report.json").read_text())["config"]
    assert cfg["init_from"] == "sfm" and cfg["strategy"]["custom_types"] == []
    assert not cfg["loss"]["use_depth"] and cfg["loss"]["lambda_anchor"] == 0 and cfg["loss"]["use_nc"]


def test_floor_is_exact_where_seen_and_the_best_row(ablation):
    data = json.loads((ablation / "ablation.json").read_text())
    floor = data["floor"]
    assert floor["status"] == "done"
    # exact depth: the mesh lies on the GT surface (5 cm voxels, 20k-sample point-to-point bias ~2 cm);
    # completeness is what the 14 training views with weight > 3 cover
    assert floor["final"]["accuracy"] < 0.03 and floor["final"]["precision"] > 0.97
    for row in data["rows"]:
        if row["status"] == "done":
            assert floor["final"]["f_score"] >= row["mean"]["f_score"]


def test_a_killed_ablation_resumes_and_skips_finished_rows(tiny, ablation, monkeypatch):
    import splat.ablate as ablate

    base = tiny[0]
    out = base / "resume"
    shutil.copytree(ablation, out)
    shutil.rmtree(out / "rows" / "no-cues_s0")  # killed while its second row ran
    (out / "rows" / "no-cues_s0" / "train").mkdir(parents=True)  # ... leaving a partial folder
    ran = []
    real = ablate.run_row
    monkeypatch.setattr(ablate, "run_row", lambda spec: ran.append(spec["row"]) or real(spec))
    _run(tiny, "resume", ["full", "no-cues", "no-ln"])
    assert ran == ["no-cues"]
    rows = {r["row"]: r for r in json.loads((out / "ablation.json").read_text())["rows"]}
    assert rows["no-cues"]["status"] == "done"
    # a changed configuration is not a finished row
    ran.clear()
    from splat.ablate import AblateConfig, run

    from evaluation.mesh_metrics import MeshMetricsConfig

    run(AblateConfig(rows=("full",), iters=30, checkpoints=(0.5, 1.0), metrics=MeshMetricsConfig(n_samples=20_000)),
        tiny[1], tiny[2], out, train_args=TRAIN_ARGS + ["--loss.lambda-nc", "0.2"])
    assert ran == ["full"]
    outdated = json.loads((out / "rows" / "full_s0.outdated" / "score.json").read_text())  # kept aside
    assert outdated["key"] != json.loads((out / "rows" / "full_s0" / "score.json").read_text())["key"]
    # options that never change what a run computes (checkpointing, the guard) are not a new row
    ran.clear()
    run(AblateConfig(rows=("full",), iters=30, checkpoints=(0.5, 1.0), metrics=MeshMetricsConfig(n_samples=20_000)),
        tiny[1], tiny[2], out, train_args=TRAIN_ARGS + ["--loss.lambda-nc", "0.2", "--save-every", "7",
                                                        "--guard.max-rollbacks", "2"])
    assert ran == []
    # a second change keeps both earlier runs (the first one set aside was deleted), and going back to
    # earlier options puts their run back instead of training it again
    first_key = outdated["key"]
    run(AblateConfig(rows=("full",), iters=30, checkpoints=(0.5, 1.0), metrics=MeshMetricsConfig(n_samples=20_000)),
        tiny[1], tiny[2], out, train_args=TRAIN_ARGS + ["--loss.lambda-nc", "0.3"])
    assert ran == ["full"]
    aside = {json.loads((p / "score.json").read_text())["key"] for p in (out / "rows").glob("full_s0.outdated*")}
    assert first_key in aside and len(aside) == 2
    ran.clear()
    _run(tiny, "resume", ["full"])  # the first options again
    assert ran == [] and json.loads((out / "rows" / "full_s0" / "score.json").read_text())["key"] == first_key
    with pytest.raises(ValueError, match="give the seeds as `splat ablate --seeds K`"):
        run(AblateConfig(rows=("full",), iters=30), tiny[1], tiny[2], out, train_args=TRAIN_ARGS + ["--seed", "2"])


def test_a_run_of_other_rows_keeps_the_finished_ones_in_the_report(tiny, ablation, monkeypatch):
    """`--rows X` after `--rows Y` in the same OUT: the report lists both (same options), not X only;
    rows finished with other options are not listed."""
    import splat.ablate as ablate

    out = tiny[0] / "subset"
    shutil.copytree(ablation, out)
    ran = []
    monkeypatch.setattr(ablate, "run_row", lambda spec: ran.append(spec["row"]))
    _run(tiny, "subset", ["full"])
    assert ran == []
    rows = {r["row"]: r["status"] for r in json.loads((out / "ablation.json").read_text())["rows"]}
    assert rows == {"full": "done", "no-cues": "done"}  # no-ln was n/a (no normal priors): not finished
    assert "`no-cues`" in (out / "report.md").read_text()
    from evaluation.mesh_metrics import MeshMetricsConfig
    from splat.ablate import AblateConfig, run

    run(AblateConfig(rows=(), iters=30, checkpoints=(0.5, 1.0), metrics=MeshMetricsConfig(n_samples=20_000)),
        tiny[1], tiny[2], out, train_args=TRAIN_ARGS + ["--loss.lambda-nc", "0.2"])
    assert ran == [] and json.loads((out / "ablation.json").read_text())["rows"] == []


def test_overwrite_starts_the_ablation_again_from_nothing(tiny, ablation, monkeypatch, capsys):
    """Without --overwrite a re-run resumes (finished rows skipped); with it, OUT's rows, floor and
    reports are removed first and every row runs again; what else a user put in OUT stays."""
    import splat.ablate as ablate
    from cli.splat_cli import main

    base, root, cues = tiny
    out = base / "again"
    shutil.copytree(ablation, out)
    (out / "notes.txt").write_text("mine")
    ran = []
    real = ablate.run_row
    monkeypatch.setattr(ablate, "run_row", lambda spec: ran.append(spec["row"]) or real(spec))
    args = ["ablate", str(root), "-c", str(cues), "-o", str(out), "--rows", "full", "--iters", "30",
            "--checkpoints", "0.5", "1.0", "--metrics.n-samples", "20000", "--no-floor", *TRAIN_ARGS]
    assert main(args) == 0
    assert ran == []  # the default: resume, `full` is finished
    before = json.loads((out / "rows" / "full_s0" / "score.json").read_text())
    assert main(args + ["--overwrite"]) == 0
    assert ran == ["full"]
    assert sorted(p.name for p in (out / "rows").iterdir()) == ["full_s0"]  # no-cues_s0 removed
    assert not (out / "floor").exists() and (out / "notes.txt").read_text() == "mine"
    after = json.loads((out / "rows" / "full_s0" / "score.json").read_text())
    assert after["wall_s"] != before["wall_s"]  # trained again, not the old score
    assert [r["row"] for r in json.loads((out / "ablation.json").read_text())["rows"]] == ["full"]


def test_a_row_killed_mid_training_continues_from_its_checkpoint(tiny, monkeypatch):
    import os
    import signal

    import splat.train as train
    from splat.checkpoint import TrainingInterrupted

    real = train.train_step

    def step_then_kill(*args, **kw):
        out = real(*args, **kw)
        if args[5] == 12:  # SIGTERM arrives during step 12 of the row
            os.kill(os.getpid(), signal.SIGTERM)
        return out

    monkeypatch.setattr(train, "train_step", step_then_kill)
    with pytest.raises(TrainingInterrupted, match="run the same command again"):
        _run(tiny, "midrow", ["no-lnc"], floor=False)
    row = tiny[0] / "midrow" / "rows" / "no-lnc_s0"
    assert (row / "train.partial" / "ckpt" / "last.pt").is_file()
    monkeypatch.setattr(train, "train_step", real)
    _run(tiny, "midrow", ["no-lnc"], floor=False)
    assert json.loads((row / "train" / "report.json").read_text())["resumed_from_step"] == 13
    assert json.loads((row / "score.json").read_text())["final"]["step"] == 30  # scored like any row
    # a checkpoint written with other options is not resumed: the row starts again
    monkeypatch.setattr(train, "train_step", step_then_kill)
    with pytest.raises(TrainingInterrupted):
        _run(tiny, "midrow2", ["no-lnc"], floor=False)
    monkeypatch.setattr(train, "train_step", real)
    from evaluation.mesh_metrics import MeshMetricsConfig
    from splat.ablate import AblateConfig, run

    run(AblateConfig(rows=("no-lnc",), iters=30, checkpoints=(0.5, 1.0), floor=False,
                     metrics=MeshMetricsConfig(n_samples=20_000)),
        tiny[1], tiny[2], tiny[0] / "midrow2", train_args=TRAIN_ARGS + ["--loss.lambda-nc", "0.2"])
    report = tiny[0] / "midrow2" / "rows" / "no-lnc_s0" / "train" / "report.json"
    assert json.loads(report.read_text())["resumed_from_step"] is None
    # ... but it is kept aside with its checkpoint, and going back to its options resumes it (it was
    # deleted: the kill's work lost)
    aside = tiny[0] / "midrow2" / "rows" / "no-lnc_s0.outdated"
    assert (aside / "train.partial" / "ckpt" / "last.pt").is_file()
    _run(tiny, "midrow2", ["no-lnc"], floor=False)
    assert json.loads(report.read_text())["resumed_from_step"] == 13
    assert (tiny[0] / "midrow2" / "rows" / "no-lnc_s0.outdated-2" / "score.json").is_file()  # the 0.2 run


def test_a_row_killed_while_scoring_keeps_its_finished_training(tiny, ablation, monkeypatch):
    """Killed after `splat train` finished but before score.json: the re-run scores the trained
    model and does not train it again (regression: the finished run was deleted and trained anew)."""
    import splat.ablate as ablate
    from splat import ablate_rows
    import splat.train as train

    out = tiny[0] / "scoring"
    shutil.copytree(ablation, out)
    row = out / "rows" / "no-cues_s0"
    (row / "score.json").unlink()
    before = (row / "train" / "report.json").read_text()
    monkeypatch.setattr(train, "run", lambda *a, **k: pytest.fail("the finished row was trained again"))
    _run(tiny, "scoring", ["full", "no-cues", "no-ln"])
    assert (row / "train" / "report.json").read_text() == before
    score = json.loads((row / "score.json").read_text())
    assert score["final"]["step"] == 30 and score["train_wall_s"] is None
    # a finished training of other options is not this row: it trains again
    assert not ablate_rows.trained(row / "train", {"key": "other", "keys": ["other"], "scene": "", "cues": "",
                                                "gt": None, "metrics": {}})


@pytest.fixture(scope="module")
def seeded(tiny):
    return _run(tiny, "seeds", ["no-lnc"], seeds=2, floor=False)


def test_seeds_give_mean_and_spread(seeded):
    row = json.loads((seeded / "ablation.json").read_text())["rows"][0]
    assert row["n_seeds"] == 2 and [r["seed"] for r in row["runs"]] == [0, 1]
    f = [r["final"]["f_score"] for r in row["runs"]]
    assert row["mean"]["f_score"] == pytest.approx(np.mean(f))
    assert row["std"]["f_score"] == pytest.approx(np.std(f))


def test_a_delta_over_other_seeds_than_fulls_is_marked():
    """`full` over 2 seeds, a row over 1: its Δ (+2.40 cm) compared other seed sets without a mark
    (against the same seed it was -0.01)."""
    from evaluation.ablation_report import _delta

    full = {"row": "full", "status": "done", "mean": {"f_score": 0.6}, "n_seeds": 2}
    assert _delta({"row": "x", "mean": {"f_score": 0.5}, "n_seeds": 1}, full, "f_score") == "-0.100\\*"
    assert _delta({"row": "x", "mean": {"f_score": 0.5}, "n_seeds": 2}, full, "f_score") == "-0.100"


def test_a_run_with_fewer_seeds_keeps_the_finished_seeds(tiny, seeded, monkeypatch):
    """`--seeds 1` (of this row or of other rows) after `--seeds 2` in the same OUT: the report keeps
    seed 1's finished run, with the same mean and spread as before."""
    import splat.ablate as ablate

    before = json.loads((seeded / "ablation.json").read_text())["rows"][0]
    out = tiny[0] / "fewer_seeds"
    shutil.copytree(seeded, out)
    ran = []
    monkeypatch.setattr(ablate, "run_row", lambda spec: ran.append(spec["row"]))
    for rows in (["no-lnc"], []):
        _run(tiny, "fewer_seeds", rows, seeds=1, floor=False)
        data = json.loads((out / "ablation.json").read_text())
        row = data["rows"][0]
        assert ran == [] and row["row"] == "no-lnc" and row["n_seeds"] == 2
        assert [r["seed"] for r in row["runs"]] == [0, 1]
        assert row["mean"] == before["mean"] and row["std"] == before["std"]
        assert "2 seed(s) per row" in (out / "report.md").read_text()


def test_preset_overrides_and_cli_options():
    from splat.ablate import train_config
    from splat.presets import PRESETS, preset_config

    assert preset_config("no-cues-long").iters == 90_000
    cfg = train_config("no-cues-long", ["--loss.lambda-nc", "0.3"], 100, 1, (1.0,))
    assert cfg.iters == 300 and cfg.seed == 1 and cfg.loss.lambda_nc == 0.3 and cfg.init_from == "sfm"
    assert train_config("no-line-adc", [], 10, 0, (1.0,)).strategy.custom_types == ("SFM", "PLANE")
    assert train_config("flat-all", [], 10, 0, (1.0,)).loss.flat_types == (0, 1, 2)  # every CueType
    assert train_config("full", [], 10, 0, (1.0,)).loss.flat_types == (1,)  # the paper: LINE only
    with pytest.raises(ValueError, match="--iters"):
        train_config("full", ["--iters", "5"], 10, 0, (1.0,))
    assert PRESETS["full"].paper == (0.040, 0.776, 0.877)


def test_splat_train_preset_flag_and_later_options_win(tmp_path, monkeypatch):
    import splat.train
    import splat.train_setup
    from cli.splat_cli import main

    seen = {}
    monkeypatch.setattr(splat.train, "run", lambda cfg, *a, **kw: seen.setdefault("cfg", cfg))
    monkeypatch.setattr(splat.train_setup, "cue_cloud_path", lambda cues: cues)  # no cue folder: the options only
    assert main(["train", "S", "-c", "C", "-o", str(tmp_path), "--preset", "no-cues", "--loss.no-use-nc"]) == 0
    cfg = seen["cfg"]
    assert cfg.init_from == "sfm" and cfg.strategy.custom_types == () and not cfg.loss.use_nc
    assert main(["train", "S", "-c", "C", "-o", str(tmp_path), "--preset", "nope"]) == 1


def test_room_preset_is_the_measured_recipe(tmp_path, monkeypatch):
    """`splat train --preset room` is what docs/training.md measured on `geocues extract --preset room`
    cues: the plane-first L_a over every view and PLANE seeds thinned to 90 % of the budget;
    `room-mesh` is that with the geometry frozen from mid-run."""
    import dataclasses

    import splat.train
    import splat.train_setup
    from cli.splat_cli import main
    from splat.presets import PRESETS, preset_config

    cfg = preset_config("room")
    assert cfg.loss.plane_anchor and cfg.loss.plane_first and cfg.loss.plane_views == "all"
    assert cfg.init.plane_share == 0.9 and "plane_anchors" in PRESETS["room"].needs
    assert preset_config("full").init.plane_share == 0.0 and not preset_config("full").loss.plane_first
    mesh = preset_config("room-mesh")  # the room recipe with the geometry frozen from mid-run
    assert mesh.geometry_until == 0.5 and cfg.geometry_until == 1.0
    assert dataclasses.replace(mesh, geometry_until=1.0) == cfg
    seen = []
    monkeypatch.setattr(splat.train, "run", lambda cfg, *a, **kw: seen.append(cfg))
    monkeypatch.setattr(splat.train_setup, "cue_cloud_path", lambda cues: cues)  # no cue folder: the options only
    assert main(["train", "S", "-c", "C", "-o", str(tmp_path), "--preset", "room", "--init.plane-share", "0.8"]) == 0
    assert seen[0].loss.plane_first and seen[0].init.plane_share == 0.8  # later options win


def test_mvs_preset_is_the_measured_photos_recipe():
    """`splat train --preset mvs` is the ICL recipe of docs/training.md ("Photos only"): `mv-plane-normals`,
    hole seeds, the multi-view consistent, smoothed TSDF, PLANE seeds thinned where the cues fill the
    budget and every prior term but L_mv stopped after a quarter of the run; nothing else differs from `full`."""
    import dataclasses

    from splat.presets import preset_config

    cfg, full, mvpn = preset_config("mvs"), preset_config("full"), preset_config("mv-plane-normals")
    assert cfg.init.fill_holes and (cfg.tsdf.consistent_views, cfg.tsdf.max_depth_spread) == (2, 0.02)
    assert (cfg.tsdf.weight_threshold, cfg.tsdf.smooth_iters) == (1.0, 30) and cfg.init.plane_share == 0.9
    assert (cfg.priors_until, cfg.priors_kept) == (0.25, ("mv",))
    assert dataclasses.replace(cfg, init=full.init, tsdf=full.tsdf, priors_until=1.0, priors_kept=()) == mvpn


def test_unknown_row_is_a_clear_error(tiny, capsys):
    from cli.splat_cli import main

    base, root, cues = tiny
    assert main(["ablate", str(root), "-c", str(cues), "-o", str(base / "x"), "--rows", "fulll"]) == 1
    assert "unknown rows ['fulll']" in capsys.readouterr().err


def test_ray_dispatch_gives_the_rows_of_jobs_1(tiny, ablation):
    ray = pytest.importorskip("ray", reason="Ray is an optional extra (pip install .[ray])")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        out = _run(tiny, "ray", ["full", "no-cues", "no-ln"], ray="auto", num_threads=1)
    finally:
        ray.shutdown()
    local = {r["row"]: r for r in json.loads((ablation / "ablation.json").read_text())["rows"]}
    remote = {r["row"]: r for r in json.loads((out / "ablation.json").read_text())["rows"]}
    assert list(local) == list(remote)
    for name in local:
        assert local[name]["status"] == remote[name]["status"]
        if local[name]["status"] == "done":
            a, b = local[name]["runs"][0]["final"], remote[name]["runs"][0]["final"]
            # same seeds, configs and thread count (--num-threads 1): the same numbers
            for key in ("psnr", "f_score", "chamfer_l1", "normal_consistency", "n_gaussians"):
                assert a[key] == b[key], (name, key, a[key], b[key])


def test_jobs_2_gives_the_rows_of_jobs_1_with_a_bar_per_row(tiny, ablation, capsys):
    """Rows in two worker processes: the same numbers as one after another (same seeds, configs and
    thread count), and the parent draws one progress bar per row from the runs' logs."""
    out = _run(tiny, "jobs2", ["full", "no-cues"], jobs=2, num_threads=1)
    err = capsys.readouterr().err
    local = {r["row"]: r for r in json.loads((ablation / "ablation.json").read_text())["rows"]}
    par = {r["row"]: r for r in json.loads((out / "ablation.json").read_text())["rows"]}
    for name in ("full", "no-cues"):
        a, b = local[name]["runs"][0]["final"], par[name]["runs"][0]["final"]
        for key in ("psnr", "f_score", "chamfer_l1", "normal_consistency", "n_gaussians"):
            assert a[key] == b[key], (name, key, a[key], b[key])
        assert f"{name} s0" in err and "30/30" in err, err[-2000:]


def test_sigterm_stops_every_parallel_row_with_its_checkpoint(tiny):
    """`kill PID` of `splat ablate --jobs 2` (the workers never see it): each running row writes its
    checkpoint, a queued row does not start, the command ends with one line and exit 143, and no
    worker is left running (regression: the parent waited while the workers trained on)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    base, root, cues = tiny
    out = base / "killed_jobs2"
    argv = ["ablate", str(root), "-c", str(cues), "-o", str(out), "--rows", "full", "no-cues", "no-lnc",
            "--iters", "4000", "--jobs", "2", "--num-threads", "1", "--no-floor", *TRAIN_ARGS]
    code = f"import sys; from cli.splat_cli import main; sys.exit(main({argv!r}))"
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=repo, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    from splat.ablate_exec import logged_step

    specs = [{"out": str(out / "rows" / f"{r}_s0")} for r in ("full", "no-cues")]
    deadline = time.monotonic() + 240
    while min(logged_step(s) for s in specs) < 20 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
    assert proc.poll() is None, proc.stderr.read()
    workers = [int(p) for p in os.listdir("/proc") if p.isdigit() and _parent(int(p)) == proc.pid
               and "spawn_main" in Path(f"/proc/{p}/cmdline").read_text()]
    os.kill(proc.pid, signal.SIGTERM)
    err = proc.communicate(timeout=240)[1]
    assert proc.returncode == 143, err
    assert err.strip().splitlines()[-1].startswith("splat ablate: ablation stopped by SIGTERM; 0 finished"), err
    for row in ("full", "no-cues"):
        assert (out / "rows" / f"{row}_s0" / "train.partial" / "ckpt" / "last.pt").is_file(), row
    assert not (out / "rows" / "no-lnc_s0" / "train.partial" / "train_log.jsonl").is_file()  # queued: never started
    assert len(workers) == 2 and not [w for w in workers if _state(w) not in (None, "Z")]


def _stat(pid: int) -> list[str]:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()


def _parent(pid: int) -> int | None:
    try:
        return int(_stat(pid)[1])
    except (OSError, ValueError, IndexError):
        return None


def _state(pid: int) -> str | None:
    """R, S, D, ... of a process; Z a zombie (ended, not reaped); None when gone."""
    try:
        return _stat(pid)[0]
    except (OSError, IndexError):
        return None


def test_logged_step_reads_the_tail_of_a_working_run(tmp_path):
    from splat.ablate_exec import logged_step

    spec = {"out": str(tmp_path / "row")}
    assert logged_step(spec) == 0  # nothing started yet
    work = tmp_path / "row" / "train.partial"
    work.mkdir(parents=True)
    lines = [json.dumps({"step": s, "loss": 0.1, "pad": "x" * 200}) for s in range(0, 1000, 50)]
    (work / "train_log.jsonl").write_text("\n".join(lines) + '\n{"step": 10')  # a line half-written
    assert logged_step(spec) == 951
    work.rename(tmp_path / "row" / "train")  # the finished run
    (tmp_path / "row" / "train" / "train_log.jsonl").write_text(json.dumps({"step": 29}) + "\n")
    assert logged_step(spec) == 30


def test_evaluate_report_of_a_run(ablation, tmp_path):
    from cli.evaluate_cli import main

    run = ablation / "rows" / "full_s0" / "train"
    assert main(["report", str(run), "--views", "2"]) == 0
    for name in ("report.md", "report_losses.png", "report_gaussians.png", "report_accuracy.png",
                 "report_views.png", "report_data.json"):
        assert (run / name).is_file(), name
    data = json.loads((run / "report_data.json").read_text())
    log_rows = [json.loads(x) for x in (run / "train_log.jsonl").read_text().splitlines()]
    # the plotted data is the log's
    assert [s for s, _ in data["losses"]["loss"]] == [r["step"] for r in log_rows]
    assert [v for _, v in data["gaussians"]["n"]] == [r["n"] for r in log_rows]
    assert [p["step"] for p in data["mesh_vs_time"]] == [15, 30]  # checkpoint meshes scored against gt/mesh.ply
    assert len(data["views"]) == 2 and len(data["depth_errors"]) == 2  # gt/depth exists: error panel
    assert png_size(run / "report_losses.png") == (720, 405)
    assert png_size(run / "report_gaussians.png") == (720, 405)
    w, h = png_size(run / "report_views.png")
    assert (w, h) == (round(3.2 * 5 * 90), round(2.5 * 2 * 90))  # 5 panels x 2 views
    md = (run / "report.md").read_text()
    assert "report_views.png" in md and "Chamfer-L1" in md
    assert md.startswith("# `splat train` run: full_s0/train")  # the row, not every row's "train"
    assert "test PSNR" in md and "Held-out views: GT" in md
    # a run that held no view out (--test-every 0) said "test PSNR nan dB (0 views)" over training views
    import shutil

    copy = tmp_path / "train_t0"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("report*.png", "report.md", "report_data.json"))
    rep = json.loads((copy / "report.json").read_text())
    rep["config"]["test_every"], rep["test_metrics"] = 0, {"psnr": None, "ssim": None, "n_views": 0}
    (copy / "report.json").write_text(json.dumps(rep))
    assert main(["report", str(copy), "--views", "2"]) == 0
    md = (copy / "report.md").read_text()
    assert "no held-out views (--test-every 0): no test PSNR" in md and "nan" not in md
    assert "Training views (the run held none out): GT" in md
    assert re.search(r"; \d+ Gaussians \(SFM \d+, LINE \d+, PLANE \d+\);", md), md
    # a finished report is replaced only with --overwrite (views=1 would change the contact sheet)
    assert main(["report", str(run), "--views", "1"]) == 1
    assert png_size(run / "report_views.png") == (w, h)
    assert main(["report", str(run), "--views", "1", "--overwrite"]) == 0
    assert png_size(run / "report_views.png") == (w, round(2.5 * 1 * 90))


def test_evaluate_report_names_a_folder_that_is_not_a_run(tmp_path, capsys):
    from cli.evaluate_cli import main

    assert main(["report", str(tmp_path)]) == 1
    assert "no report.json" in capsys.readouterr().err


def test_rows_keyed_under_earlier_key_rules_are_still_finished(tiny, tmp_path):
    """Rows fused with the median depth were keyed without `tsdf.depth` before it existed and with it
    in the days between: both keys name the same row (else a re-run trains them again)."""
    from splat.ablate import AblateConfig, plan
    from splat.ablate_rows import done

    base, root, cues = tiny
    specs, _ = plan(AblateConfig(rows=("full",), iters=30), root, cues, tmp_path, TRAIN_ARGS + ["--tsdf.depth", "median"])
    keys = specs[0]["keys"]
    assert len(keys) == 2 and keys[0] == specs[0]["key"]
    (tmp_path / "row").mkdir()
    (tmp_path / "row" / "score.json").write_text(json.dumps({"key": keys[1]}))
    assert done(tmp_path / "row", keys) is not None and done(tmp_path / "row", keys[:1]) is None
    expected, _ = plan(AblateConfig(rows=("full",), iters=30), root, cues, tmp_path, TRAIN_ARGS)
    assert expected[0]["keys"] == [expected[0]["key"]]  # the default depth has one key


def test_plane_anchor_row_needs_the_anchors_file_and_leaves_other_rows_keys(tiny, tmp_path):
    import shutil

    from geocues.plane_anchors import write_plane_anchors
    from splat.ablate import AblateConfig, plan, row_keys

    base, root, cues = tiny
    cfg = AblateConfig(rows=("full", "plane-anchor"), iters=30)
    specs, na = plan(cfg, root, cues, tmp_path, TRAIN_ARGS)
    assert [s["row"] for s in specs] == ["full"] and "plane anchors" in na["plane-anchor"]
    before = json.loads(json.dumps(specs[0]))  # a row planned before the option existed
    del before["train_config"]["loss"]["plane_anchor"]
    assert row_keys(before) == specs[0]["keys"]
    with_anchors = tmp_path / "cues"
    with_anchors.mkdir()
    shutil.copy(cues / "cues.ply", with_anchors)
    write_plane_anchors(with_anchors, ["00000.png"], np.zeros((1, 3)), np.float32([[0, 0, 1]]), np.zeros(1))
    specs, na = plan(cfg, root, with_anchors, tmp_path, TRAIN_ARGS)
    assert [s["row"] for s in specs] == ["full", "plane-anchor"] and not na
    assert specs[1]["train_config"]["loss"]["plane_anchor"] is True and specs[1]["key"] != specs[0]["key"]


def test_plane_rule_left_at_the_paper_keeps_finished_rows_keys(tiny, tmp_path):
    """Rows planned before strategy.plane_rule existed keep their key; plane-tangent-adc gets its own."""
    from splat.ablate import AblateConfig, plan, row_keys

    base, root, cues = tiny
    specs, _ = plan(AblateConfig(rows=("full", "plane-tangent-adc"), iters=30), root, cues, tmp_path, TRAIN_ARGS)
    before = json.loads(json.dumps(specs[0]))
    del before["train_config"]["strategy"]["plane_rule"]
    assert row_keys(before) == specs[0]["keys"]
    assert specs[1]["train_config"]["strategy"]["plane_rule"] == "tangent" and specs[1]["key"] != specs[0]["key"]


def test_an_auto_budget_row_is_keyed_by_its_rule(tiny, tmp_path, monkeypatch):
    """--strategy.max-gaussians auto (the default) keys a row by the rule it stands for: a toolkit whose
    rule changed trains the row again instead of reporting the old number as today's default; rows
    keyed with no limit (0, the default before auto) are other rows."""
    import splat.strategy as strategy
    from splat.ablate import AblateConfig, plan, row_keys

    base, root, cues = tiny
    args = [a for a in TRAIN_ARGS if a not in ("--strategy.max-gaussians", "8000")]  # the default budget
    specs, _ = plan(AblateConfig(rows=("full",), iters=30), root, cues, tmp_path, args)
    assert specs[0]["train_config"]["strategy"]["max_gaussians"] == "auto"
    unlimited, _ = plan(AblateConfig(rows=("full",), iters=30), root, cues, tmp_path,
                        [*args, "--strategy.max-gaussians", "0"])
    assert unlimited[0]["key"] != specs[0]["key"]
    monkeypatch.setattr(strategy, "AUTO_BUDGET_MIN", 1)
    assert row_keys(specs[0])[-1] != specs[0]["key"]


@pytest.mark.parametrize("field", ["geometry_until", "priors_until"])
def test_fractions_left_at_the_end_keep_finished_rows_keys(tiny, tmp_path, field):
    """Rows planned before --geometry-until / --priors-until existed keep their key; a run that
    freezes the geometry (or stops the prior terms) earlier is a new row."""
    from splat.ablate import AblateConfig, plan, row_keys

    base, root, cues = tiny
    specs, _ = plan(AblateConfig(rows=("full",), iters=30), root, cues, tmp_path, TRAIN_ARGS)
    before = json.loads(json.dumps(specs[0]))
    del before["train_config"][field]
    assert row_keys(before) == specs[0]["keys"]
    early, _ = plan(AblateConfig(rows=("full",), iters=30), root, cues, tmp_path,
                    [*TRAIN_ARGS, "--" + field.replace("_", "-"), "0.5"])
    assert early[0]["train_config"][field] == 0.5 and early[0]["key"] != specs[0]["key"]


def test_mesh_smoothing_left_off_keeps_finished_floor_keys():
    """Floors keyed before tsdf.smooth_iters existed keep their keys; smoothed ones get new ones
    (rows: test_options_left_off_keep_finished_rows_keys)."""
    from dataclasses import asdict, replace

    from splat.ablate import AblateConfig, config_key, floor_key
    from splat.train import TrainConfig

    cfg = AblateConfig(rows=("full",), iters=30)
    example = TrainConfig()
    old_tsdf = {k: v for k, v in asdict(example.tsdf).items() if k != "smooth_iters"}
    old_key = config_key({"views": [example.downscale, example.test_every, example.mesh_every], "tsdf": old_tsdf,
                          "depth": "gt/depth", "png": cfg.gt_depth_png_scale, "metrics": asdict(cfg.metrics),
                          "gt": str(cfg.gt)})
    assert floor_key(cfg, example, Path("gt/depth")) == old_key
    smooth = replace(example, tsdf=replace(example.tsdf, smooth_iters=30))
    assert floor_key(cfg, smooth, Path("gt/depth")) != old_key


@pytest.mark.parametrize("section, field, flag, value", [("tsdf", "smooth_iters", "--tsdf.smooth-iters", 30),
                                                          ("init", "plane_share", "--init.plane-share", 0.7)])
def test_options_left_off_keep_finished_rows_keys(tiny, tmp_path, section, field, flag, value):
    """Rows planned before an option existed keep their key while it is off; set, it gets its own."""
    from splat.ablate import AblateConfig, plan, row_keys

    base, root, cues = tiny
    cfg = AblateConfig(rows=("full",), iters=30)
    specs, _ = plan(cfg, root, cues, tmp_path, TRAIN_ARGS)
    before = json.loads(json.dumps(specs[0]))
    del before["train_config"][section][field]
    assert row_keys(before) == specs[0]["keys"]
    on, _ = plan(cfg, root, cues, tmp_path, TRAIN_ARGS + [flag, str(value)])
    assert on[0]["train_config"][section][field] == value and on[0]["key"] != specs[0]["key"]


def test_a_diverged_row_is_reported_and_the_other_rows_go_on(tiny, monkeypatch):
    """A row whose training diverges (splat.guard gave up) is in the report as diverged with its
    reason, the rows after it still run, and the ablation ends with an error naming it."""
    import splat.train
    from splat.guard import TrainingDiverged

    real_run = splat.train.run

    def run(cfg, *args, **kw):
        if cfg.init_from == "sfm":  # the no-cues row
            raise TrainingDiverged("training diverged at step 7: loss 9 is 23x its running mean")
        return real_run(cfg, *args, **kw)

    monkeypatch.setattr(splat.train, "run", run)
    with pytest.raises(TrainingDiverged, match=r"1 row run diverged: no-cues \(seed 0\)"):
        _run(tiny, "diverged", ["no-cues", "full"], num_threads=1)
    base = tiny[0]
    rows = {r["row"]: r for r in json.loads((base / "diverged" / "ablation.json").read_text())["rows"]}
    assert rows["full"]["status"] == "done"
    assert rows["no-cues"]["status"] == "diverged" and "step 7" in rows["no-cues"]["reason"]
    assert "diverged (seed 0: training diverged at step 7" in (base / "diverged" / "report.md").read_text()


def test_the_floor_does_not_depend_on_the_rows(tiny, ablation):
    """The floor is the default meshing's whatever rows run (it followed the first row's TSDF
    settings); `mvs`, whose preset meshes otherwise, also gets the floor of its own meshing."""
    out = _run(tiny, "mvs_only", ["mvs"], num_threads=1)
    data = json.loads((out / "ablation.json").read_text())
    default = json.loads((ablation / "ablation.json").read_text())
    assert data["floor"]["key"] == default["floor"]["key"] and default["floors"] == {}
    assert data["floor"]["final"]["chamfer_l1"] == pytest.approx(default["floor"]["final"]["chamfer_l1"], rel=1e-3)
    mvs = data["floors"]["mvs"]
    assert mvs["status"] == "done" and mvs["key"] != data["floor"]["key"] and (out / "floor_mvs" / "mesh.ply").is_file()
    assert "**floor** through `mvs`'s meshing" in (out / "report.md").read_text()


def test_a_report_of_a_run_that_rendered_no_depth_is_strict_json(ablation, tmp_path, monkeypatch):
    """A run that rendered nothing where GT has depth (fx 1e6) wrote NaN into report_data.json (not JSON)."""
    import splat.rasterize
    from evaluation.run_report import write_run_report

    run = tmp_path / "run"
    shutil.copytree(ablation / "rows" / "full_s0" / "train", run)
    real = splat.rasterize.render

    def no_depth(*a, **k):
        out = real(*a, **k)
        return {**out, "median_depth": out["median_depth"] * 0}

    monkeypatch.setattr(splat.rasterize, "render", no_depth)
    write_run_report(run, n_views=1, overwrite=True)
    data = json.loads((run / "report_data.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    assert [e["median_abs_depth_error_m"] for e in data["depth_errors"]] == [None]
