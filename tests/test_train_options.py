"""`splat train` options a user combines (found by a sweep of 170 short runs): each one either acts as
documented, or is refused or named; nothing is ignored in silence."""

from __future__ import annotations

import dataclasses
import json
import logging
import re

import pytest
import torch

from cues_synth import make_room_scene
from splat.train_config import TrainConfig
from test_resume_guard import scene  # noqa: F401  (the fixture: a 12-view room with priors, its cues)


SHORT = ["--iters", "6", "--sh-degree", "0", "--no-mesh", "--checkpoints", "1.0"]


@pytest.mark.parametrize("change, said", [
    ({"loss.lambda_dssim": 3.0}, "--loss.lambda-dssim weighs D-SSIM against L1 and must be in [0, 1]"),
    ({"strategy.total_iters": 120}, "--strategy.total-iters is the run's length, set from --iters"),
    # found by the numerics audit: a NaN threshold trained to the end and failed writing report.json (the
    # model lost), reset-opacity 2 failed at the first reset without naming it, bounds-mult 0 'diverged'
    ({"strategy.grow_grad2d": float("nan")}, "--strategy.grow-grad2d must be a finite number > 0, got nan"),
    ({"strategy.prune_scale3d": -1.0}, "--strategy.prune-scale3d must be a finite number > 0"),
    ({"strategy.line_clone_step": float("nan")}, "--strategy.line-clone-step must be a finite number >= 0"),
    ({"strategy.prune_opa": 1.0}, "--strategy.prune-opa is an opacity and must be in [0, 1), got 1.0"),
    ({"strategy.reset_opacity": 2.0}, "--strategy.reset-opacity is an opacity and must be in (0, 1), got 2.0"),
    ({"strategy.refine_every": 0}, "--strategy.refine-every must be >= 1"),
    ({"guard.spike_factor": float("nan")}, "--guard.spike-factor is a multiple of the loss's running mean"),
    ({"guard.max_outside": -1.0}, "--guard.max-outside is a fraction of the Gaussians and must be in (0, 1]"),
    ({"guard.bounds_mult": 0.0}, "--guard.bounds-mult must be a finite number >= 1"),
    ({"tsdf.weight_threshold": float("nan")}, "--tsdf.weight-threshold must be a finite number, got nan"),
    ({"tsdf.voxel_size": float("inf")}, "--tsdf.voxel-size must be a finite number, got inf"),
])
def test_options_that_acted_wrongly_or_not_at_all_are_refused(change, said):
    """lambda-dssim 3 gave L1 a negative weight (a 1,587-triangle mesh instead of 39,500); a
    total-iters was overwritten by --iters, the config recording the given value."""
    from splat.presets import apply_overrides

    with pytest.raises(ValueError, match=re.escape(said)):
        apply_overrides(TrainConfig(), change).validate()


def test_tsdf_on_cuda_without_cuda_is_refused_before_training(scene, tmp_path):
    """The training ran to its end, then Open3D raised a traceback and the run was lost."""
    import open3d as o3d

    from splat.train import run

    if o3d.core.cuda.is_available():
        pytest.skip("this Open3D has CUDA")
    base, root, cues = scene
    cfg = dataclasses.replace(TrainConfig(iters=2), tsdf=dataclasses.replace(TrainConfig().tsdf, device="cuda"))
    with pytest.raises(ValueError, match="--tsdf.device cuda: this Open3D build has no CUDA"):
        run(cfg, root, cues, tmp_path / "run")
    assert not (tmp_path / "run.partial").exists()


def test_a_preset_iteration_factor_applies_to_the_given_iters(scene, tmp_path, capsys):
    """`--preset no-cues-long --iters 60` trained 60 iterations (the 3x applied to the default 30k,
    then replaced); `splat ablate` gives the row 3x the run's iterations, and so does train now."""
    from cli.splat_cli import main

    base, root, cues = scene
    assert main(["train", str(root), "-c", str(cues), "-o", str(tmp_path / "long"), "--preset", "no-cues-long",
                 *SHORT]) == 0
    assert json.loads((tmp_path / "long" / "report.json").read_text())["config"]["iters"] == 18


def test_a_preset_that_trains_as_another_row_is_named(scene, tmp_path, caplog):
    """A row that cannot be itself here (`paper`, the loss without L_a, on a scene without depth
    priors is `full`; plane-normals where every view has a normal prior) trained without a word,
    where `splat ablate` reports it n/a."""
    from cli.splat_cli import main

    base, _, cues = scene
    bare = make_room_scene(tmp_path / "bare", n_views=12, w=64, h=48, priors="none")
    with caplog.at_level(logging.WARNING, logger="splat"):
        assert main(["train", str(bare), "-c", str(cues), "-o", str(tmp_path / "paper"), "--preset", "paper",
                     *SHORT]) == 0
    assert "--preset paper trains as another row on this scene (no depth priors)" in caplog.text


def test_init_ply_names_the_options_it_overrides(scene, tmp_path, caplog):
    """--cue-types / --init-from / --init.fill-holes with --init-ply changed nothing, without a word;
    a degree too low for its SH named `sh_degree=None`, an argument of the Python function."""
    from splat.train import run

    base, root, cues = scene
    first = run(TrainConfig(iters=4, sh_degree=1, mesh=False, checkpoints=(1.0,)), root, cues, tmp_path / "a")
    ply = str(first / "point_cloud.ply")
    with caplog.at_level(logging.WARNING, logger="splat"):
        run(TrainConfig(iters=2, sh_degree=1, mesh=False, checkpoints=(1.0,), init_ply=ply, cue_types=("SFM",)),
            root, cues, tmp_path / "b")
    assert "the settings --cue-types SFM are not applied" in caplog.text
    with pytest.raises(ValueError, match=r"above degree 0; train with --sh-degree \d") as e:
        run(TrainConfig(iters=2, sh_degree=0, mesh=False, checkpoints=(1.0,), init_ply=ply), root, cues, tmp_path / "c")
    assert "sh_degree=None" not in str(e.value)


def test_a_backend_fallback_is_said_once(caplog, monkeypatch):
    """`--backend cuda` on the CPU warned at every render: 109 lines in 60 steps."""
    import torch

    import geocues.logs as once
    from splat.composite import resolve_backend

    monkeypatch.setattr(once, "_SAID", set())
    with caplog.at_level(logging.WARNING, logger="splat"):
        for _ in range(5):
            assert resolve_backend("cuda", torch.device("cpu")) == "torch"
    assert caplog.text.count("backend 'cuda' needs CUDA tensors") == 1


def test_final_warnings_name_rollbacks_and_a_runaway_camera_refinement(monkeypatch):
    """A run whose guard rolled back steps (--lr.means 1e3: a 38-triangle mesh) or whose focal went
    to x114 (--focal-lr 1) ended 'done' without a word."""
    from types import SimpleNamespace

    from splat.train_outputs import final_warnings

    refiner = SimpleNamespace(summary=lambda: {"focal_factor": 114.0, "rotation_deg": {"max": 122.0}})
    s = SimpleNamespace(guard=SimpleNamespace(events=[{}] * 4), refiner=refiner, train_views=[0] * 28)
    said = final_warnings(TrainConfig(), s, {"triangles": 38}, "4.0 dB", "RUN")
    assert any("has only 38 triangles" in w and "4 steps rolled back" in w and "--lr.*" in w for w in said)
    said = final_warnings(TrainConfig(), s, {"triangles": 38_000}, "4.0 dB", "RUN")
    assert any("rolled back 4 steps" in w for w in said) and not any("triangles" in w for w in said)
    assert any("camera refinement went far (focal x114" in w and "--focal-lr" in w for w in said)
    tsdf = dataclasses.replace(TrainConfig().tsdf, weight_threshold=1000.0)
    empty = final_warnings(dataclasses.replace(TrainConfig(), tsdf=tsdf),
                           SimpleNamespace(guard=SimpleNamespace(events=[]), refiner=None, train_views=[0] * 28),
                           {"triangles": 0}, "20 dB", "RUN")
    assert len(empty) == 1 and "EMPTY" in empty[0] and "settings in use (--tsdf.weight-threshold 1000.0)" in empty[0]
    coarse = final_warnings(dataclasses.replace(TrainConfig(), tsdf=dataclasses.replace(tsdf, weight_threshold=3.0,
                                                                                         voxel_size=0.5)),
                            SimpleNamespace(guard=SimpleNamespace(events=[]), refiner=None, train_views=[0] * 28),
                            {"triangles": 1}, "20 dB", "RUN")  # --tsdf.voxel-size 0.5 on a room: one triangle
    assert len(coarse) == 1 and "has only 1 triangle (a room" in coarse[0] and "(--tsdf.voxel-size 0.5)" in coarse[0]
    mm = SimpleNamespace(guard=SimpleNamespace(events=[]), refiner=None, train_views=[0] * 28,
                         scene=SimpleNamespace(root="ROOM_MM"))
    import geocues.rescale as rescale

    # a scene in millimetres: the unit is named, not the cameras and learning rates
    monkeypatch.setattr(rescale, "metric_warning", lambda scene: f"the scene spans 3500 units: make {scene.root} metric")
    unit = final_warnings(TrainConfig(), mm, {"triangles": 0}, "20 dB", "RUN")
    assert len(unit) == 1 and unit[0].endswith("the scene spans 3500 units: make ROOM_MM metric")


def test_the_iteration_factor_follows_the_flag_not_its_value(scene, tmp_path, monkeypatch):
    """--iters equal to the preset's own default (90000 for no-cues-long) was taken for no --iters."""
    import splat.train as train
    from cli.splat_cli import main

    base, root, cues = scene
    seen = []
    monkeypatch.setattr(train, "run", lambda cfg, *a, **k: seen.append(cfg.iters))
    for extra in (["--iters", "90000"], []):
        assert main(["train", str(root), "-c", str(cues), "-o", str(tmp_path / "x"), "--preset", "no-cues-long",
                     *extra]) == 0
    assert seen == [270_000, 90_000]


def test_a_prior_term_that_never_acted_is_named(tmp_path):
    """At 40x30 px L_d found no patch with enough valid pixels: its term was 0.0 at every step, and an
    ablation's `no-ld` row scored exactly as `full`, without a word."""
    from splat.train_outputs import idle_terms

    log = tmp_path / "train_log.jsonl"
    log.write_text("".join(json.dumps({"step": k, "rgb": 0.3, "depth": 0.0, "normal": 0.2 if k else 0.0}) + "\n"
                           for k in range(5)))
    assert idle_terms(log) == ["depth"]
    assert idle_terms(tmp_path / "absent.jsonl") == []


def test_an_empty_model_is_an_error_with_its_cause(scene, tmp_path, capsys, caplog):
    """A run that ended with 0 Gaussians (--init.min-scale 1000) or with Gaussians no view sees (a scene
    in millimetres: all within the 0.01 m near plane) printed "done ... 4.49 dB" and exited 0; with the
    mesh on, the only warning blamed the TSDF settings. Now: exit 1, the files kept, the cause named."""
    from types import SimpleNamespace

    from cli.geocues_cli import main as geocues
    from cli.splat_cli import main
    from splat.train_outputs import empty_result, final_warnings

    base, root, cues = scene
    assert geocues(["rescale", str(root), "-o", str(tmp_path / "mm"), "--scale", "0.001"]) == 0
    capsys.readouterr()
    with caplog.at_level(logging.WARNING, logger="splat"):
        assert main(["train", str(tmp_path / "mm"), "-c", str(cues), "-o", str(tmp_path / "run"), "--init-from", "sfm",
                     *SHORT]) == 1
    assert "splat train: error: the trained model is empty" in capsys.readouterr().err
    said = caplog.records[-1].getMessage()
    assert "is EMPTY: the held-out views render nothing (mean alpha 0" in said and "not the 0.5-200 m" in said
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["test_metrics"]["alpha"] == 0 and report["empty_result"].startswith("the held-out views render")

    cfg = dataclasses.replace(TrainConfig(), init=dataclasses.replace(TrainConfig().init, min_scale=1000.0))
    s = SimpleNamespace(state={"cue_type": []}, guard=SimpleNamespace(events=[]), refiner=None, train_views=[0] * 28)
    empty = empty_result(cfg, s, {"psnr": 4.49, "alpha": 0.0})
    assert empty == "the run ended with 0 Gaussians: every one was pruned; check the settings in use (--init.min-scale 1000.0)"
    said = final_warnings(cfg, s, {"triangles": 0}, "4.49 dB", "RUN", empty)
    assert said == [f"the model of RUN is EMPTY: {empty}"]  # not the TSDF settings, nor idle loss terms
    s.state["cue_type"] = [0] * 10
    assert empty_result(cfg, s, {"psnr": 30.0, "alpha": 0.9}) is None


def test_a_divergence_names_what_to_change_from_its_cause():
    """Every divergence advised lowering the learning rates, also when a prior of 1e30 or
    --loss.lambda-depth 1e38 made a loss term non-finite: the terms that went bad first are named with
    their weights and inputs; a loss spike names the weights; the rest the learning rates first."""
    from splat.guard import GuardConfig, NumericsGuard, TrainingDiverged, divergence_hint

    said = divergence_hint({"reason": "non-finite loss", "terms": ["depth"]})
    assert said.startswith("The loss term depth went bad first: check their weights (--loss.lambda-*)")
    assert "depth/normal priors" in said
    assert "--guard.spike-factor" in divergence_hint({"reason": "loss 9 is 40x its running mean 0.2", "terms": []})
    assert divergence_hint({"reason": "non-finite gradients", "terms": []}).startswith("Lower their learning rates")
    guard = NumericsGuard(GuardConfig(max_rollbacks=1), torch.zeros(3), 1.0)
    event = {"step": 7, "reason": "non-finite loss", "terms": ["depth", "normal"], "params": ["means"], "gaussians": {}}
    guard.on_rollback(event)
    with pytest.raises(TrainingDiverged, match=r"The loss terms depth, normal went bad first"):
        guard.on_rollback(event)


def test_checkpoint_meshes_without_meshing_are_named(scene, tmp_path, caplog):
    """--no-mesh --mesh-at-checkpoints made no checkpoint mesh without a word (evaluate report then had
    no mesh-against-time plot)."""
    from splat.train import run

    base, root, cues = scene
    cfg = dataclasses.replace(TrainConfig(), iters=4, sh_degree=0, mesh=False, mesh_at_checkpoints=True,
                              checkpoints=(1.0,))
    with caplog.at_level(logging.WARNING, logger="splat"):
        run(cfg, root, cues, tmp_path / "run")
    assert "--mesh-at-checkpoints with --no-mesh: no mesh is fused at all" in caplog.text

