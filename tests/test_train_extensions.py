"""`splat train` end to end with the anchor and seeding extensions: `--init.fill-holes` with
`--loss.fused-anchor` on the tiny synthetic room whose only cues are its SfM points (floor and box).

What must hold: the run finishes; it starts from more Gaussians than the cues (the hole seeds); the
held-out views are far better at every checkpoint than in a run without seeds (whose Gaussians,
grown from the floor and the box only, leave the walls black for the whole short run); and a run without depth priors
takes the options without error and seeds nothing.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from cues_synth import make_room_scene
from geocues.cue_io import CueCloud, write_cues_ply
from geocues.scene import Scene
from geocues.types import CueType


def _scene(tmp_path, priors: str):
    root = make_room_scene(tmp_path / f"room_{priors}", n_views=16, w=80, h=60, priors=priors, n_outliers=0)
    scene = Scene.load(root)
    cues = tmp_path / f"cues_{priors}"
    write_cues_ply(cues / "cues.ply", CueCloud.make(scene.points.xyz, scene.points.rgb, CueType.SFM))
    rows = [{"index": c.index, "name": c.name,  # the exact alignment of prior = 0.5 z + 0.3
             "alignment": {"index": c.index, "ok": True, "scale": 2.0, "shift": -0.6, "width": c.width,
                           "height": c.height, "residual_p90_m": 0.005}} for c in scene.cameras]
    (cues / "report.json").write_text(json.dumps({"per_image": rows if priors == "all" else []}))
    return root, cues, len(scene.points.xyz)


def _run(root, cues, out, **init_loss):
    from dataclasses import replace

    from splat.gaussians import InitConfig
    from splat.losses import LossConfig
    from splat.train import TrainConfig, run

    cfg = TrainConfig(iters=200, checkpoints=(0.25, 0.5, 1.0), sh_degree=0, mesh=False, log_every=1,
                      init=replace(InitConfig(), fill_holes=init_loss.get("fill_holes", False)),
                      loss=replace(LossConfig(), fused_anchor=init_loss.get("fused_anchor", False)))
    out = run(cfg, root, cues, out)
    first = json.loads((out / "train_log.jsonl").read_text().splitlines()[0])
    report = json.loads((out / "report.json").read_text())
    return first["n"], report


def test_hole_seeds_with_the_fused_prior_start_fuller_and_see_more_early(tmp_path):
    root, cues, n_cues = _scene(tmp_path, "all")
    n_plain, plain = _run(root, cues, tmp_path / "plain")
    n_seeded, seeded = _run(root, cues, tmp_path / "seeded", fill_holes=True, fused_anchor=True)
    assert n_plain == n_cues and n_seeded > n_cues + 100, (n_cues, n_plain, n_seeded)  # the hole seeds
    a, b = ([c["psnr"] for c in r["accuracy_vs_time"]] for r in (plain, seeded))
    assert all(y > x + 5.0 for x, y in zip(a, b)), (a, b)  # measured 4.6 / 4.8 / 5.1 against 13.4 / 19.5 / 23.5 dB


def test_without_priors_the_options_change_nothing(tmp_path):
    root, cues, n_cues = _scene(tmp_path, "none")
    n, report = _run(root, cues, tmp_path / "out", fill_holes=True, fused_anchor=True)
    assert n == n_cues and report["accuracy_vs_time"]
    with pytest.raises(ValueError, match="hole-voxel"):
        from dataclasses import replace

        from splat.gaussians import InitConfig
        from splat.train import TrainConfig

        TrainConfig(init=replace(InitConfig(), hole_voxel=0.0)).validate()


def test_geometry_until_freezes_the_mesh_and_trains_the_colours(tmp_path):
    """`--geometry-until 0.25`: from a quarter of the run on the Gaussians' geometry does not move, nor
    does density control, which would still run (its stop, 12k of 30k, is later): the final mesh is the
    step-20 checkpoint's, vertex for vertex, while the colours still learn; without it the geometry
    moves on. A fraction outside (0, 1] is refused."""
    import numpy as np
    import open3d as o3d

    from splat.train import TrainConfig, run

    root, cues, _ = _scene(tmp_path, "all")
    runs = {}
    for name, until in (("frozen", 0.25), ("free", 1.0)):
        cfg = TrainConfig(iters=80, checkpoints=(0.25, 1.0), sh_degree=1, mesh_at_checkpoints=True,
                          geometry_until=until, log_every=1)
        out = run(cfg, root, cues, tmp_path / name)
        mid, end = (np.asarray(o3d.io.read_triangle_mesh(str(p)).vertices)
                    for p in (out / "checkpoints" / "mesh_000020.ply", out / "mesh.ply"))
        mid, end = (v[np.lexsort(v.T)] for v in (mid, end))  # the TSDF's block order varies from run to run
        psnr = [c["psnr"] for c in json.loads((out / "report.json").read_text())["accuracy_vs_time"]]
        runs[name] = (mid, end, psnr)
    mid, end, psnr = runs["frozen"]
    assert len(mid) > 100 and mid.shape == end.shape and np.array_equal(mid, end)
    assert psnr[1] > psnr[0]  # the colours trained on
    mid_free, end_free, _ = runs["free"]
    assert mid_free.shape != end_free.shape or not np.allclose(mid_free, end_free)
    with pytest.raises(ValueError, match="geometry-until"):
        TrainConfig(geometry_until=0.0).validate()


def test_frozen_colour_step_equals_the_full_step_with_the_geometry_stopped(tmp_path, monkeypatch):
    """Once the geometry is frozen the trainer takes splat.frozen.colour_step (L_rgb and the colours'
    gradient alone); the full step with the geometry's learning rates at 0 (COLOUR_STEP_WHEN_FROZEN
    False) is its oracle: the same Gaussians, colours included, and the same held-out PSNR at the end.
    The log shows which step ran: after the freeze the colour step logs L_rgb alone."""
    import numpy as np
    from plyfile import PlyData

    import splat.train as train
    from splat.train import TrainConfig, run

    root, cues, _ = _scene(tmp_path, "all")
    runs = {}
    for name, fast in (("colour", True), ("oracle", False)):
        monkeypatch.setattr(train, "COLOUR_STEP_WHEN_FROZEN", fast)
        cfg = TrainConfig(iters=60, checkpoints=(0.5, 1.0), sh_degree=1, mesh=False, geometry_until=0.5, log_every=1)
        out = run(cfg, root, cues, tmp_path / name)
        rows = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
        late = [r for r in rows if r.get("step", 0) >= 30 and "loss" in r]
        ply = PlyData.read(str(out / "point_cloud.ply"))["vertex"].data
        report = json.loads((out / "report.json").read_text())
        colour = [k for k in ply.dtype.names if k.startswith("f_")]
        runs[name] = (late, np.stack([ply[k] for k in ply.dtype.names if k not in colour], 1),
                      np.stack([ply[k] for k in colour], 1), report["test_metrics"]["psnr"])
    (late, geometry, colours, psnr), (late_o, geometry_o, colours_o, psnr_o) = runs["colour"], runs["oracle"]
    assert late and all(set(r) & {"depth", "normal", "anchor", "flat"} == set() for r in late)
    assert all({"depth", "anchor"} <= set(r) for r in late_o)
    assert geometry.shape == geometry_o.shape and np.array_equal(geometry, geometry_o)
    # the colour step's compositing gradient uses the forward's blend weights, the full one recovers
    # them by division: equal to float rounding, which Adam's normalised steps carry on
    assert np.abs(colours - colours_o).max() < 1e-5, np.abs(colours - colours_o).max()  # measured 6e-8
    assert abs(psnr - psnr_o) < 0.01


def test_a_room_or_mvs_preset_on_other_cues_is_named(tmp_path):
    """`splat train --preset room` with plain `geocues extract` cues trained in silence: the preset's
    measured gains need the matching extract preset, so the mismatch is one warning naming it."""
    import json
    from dataclasses import asdict

    from geocues.presets import extract_preset_config
    from splat.presets import cue_preset_mismatch

    for name in ("paper", "room", "mvs"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "report.json").write_text(json.dumps({"config": asdict(extract_preset_config(name))},
                                                                default=str))
    why = cue_preset_mismatch("room", tmp_path / "paper")
    assert why and "`geocues extract --preset room` cues" in why and "floor.lines False" in why
    assert cue_preset_mismatch("room-mesh", tmp_path / "room" / "cues.ply") is None
    assert "--preset mvs" in cue_preset_mismatch("mvs", tmp_path / "room")
    assert cue_preset_mismatch("mvs", tmp_path / "mvs") is None
    assert cue_preset_mismatch("full", tmp_path / "paper") is None  # the paper's recipe takes any cues
    assert cue_preset_mismatch("room", tmp_path / "nowhere") is None  # no record: nothing to say


def _cfg(**top):
    """A TrainConfig with top-level fields, or nested ones as section={field: value}, replaced."""
    from dataclasses import replace

    from splat.train_config import TrainConfig

    cfg = TrainConfig()
    for key, value in top.items():
        cfg = replace(cfg, **{key: replace(getattr(cfg, key), **value) if isinstance(value, dict) else value})
    return cfg


@pytest.mark.parametrize("change, message", [
    (dict(iters="abc"), "TrainConfig.iters must be int (like its default 30000), got 'abc'"),
    (dict(iters=10.5), "TrainConfig.iters must be int (like its default 30000), got 10.5"),
    (dict(sh_degree=True), "TrainConfig.sh_degree must be int"),
    (dict(background=(0.0, 0.0)), "--background must be three finite numbers"),
    (dict(strategy={"max_gaussians": -1}), "--strategy.max-gaussians must be 'auto' or an integer >= 0"),
    (dict(strategy={"max_gaussians": "lots"}), "--strategy.max-gaussians must be 'auto' or an integer >= 0"),
    (dict(strategy={"max_gaussians": 1.5e5}), "IndoorStrategyConfig.max_gaussians must be int or 'auto'"),
    (dict(loss={"lambda_depth": "0.1"}), "LossConfig.lambda_depth must be float"),
    (dict(background=("a", "b", "c")), "TrainConfig.background must hold numbers"),
    (dict(checkpoints=[0.5, "x"]), "TrainConfig.checkpoints must hold numbers"),
    (dict(loss=None), "TrainConfig.loss must be a LossConfig section, got None"),
], ids=["str iters", "fractional iters", "bool sh degree", "two-number background", "negative budget",
        "word budget", "float budget", "str weight",
        "str background", "str checkpoint", "null section"])
def test_a_config_from_python_is_type_checked_before_any_work(change, message):
    """From Python, TrainConfig(iters="abc") failed deep in a run with a TypeError, 10.5 iterations
    trained 11, a two-number background failed nine frames deep after loading the scene."""
    with pytest.raises(ValueError, match=re.escape(message)):
        _cfg(**change).validate()
    _cfg(iters=np.int64(100), downscale=np.float32(2.0), loss={"flat_types": [1, 2]},  # numpy, a list
         strategy={"max_gaussians": np.int64(100_000)}).validate()
