"""What a `splat train` run holds before its first iteration: the output folder it works in (and the
checkpoint it resumes from), the scene's views with their priors, the typed Gaussians from the cues,
one Adam per parameter, the per-type density control, the scaled loss schedules, L_mv's neighbours,
the camera refiner and the numerics guard (splat/train.py runs the loop over them)."""

from __future__ import annotations

import json
import logging
import shlex
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from geocues.advice import few_views_warning, fov_warning, normal_axes_warning, registration_warning
from geocues.atomic import check_output_dir, check_replaceable
from geocues.cue_io import read_cue_report, unfinished_extract
from geocues.depth_align import load_alignments, load_prior_kind
from geocues.logs import warn_once
from geocues.plane_anchors import load_plane_anchors
from geocues.rescale import metric_warning
from geocues.scene import Scene
from geocues.types import CueType
from splat import checkpoint, compiled
from splat.camera_opt import CameraRefiner
from splat.checkpoint import publish, staging_dir
from splat.gaussians import scene_scale
from splat.guard import NumericsGuard
from splat.init_gaussians import initial_gaussians, with_budget
from splat.losses import LossConfig, without_priors
from splat.multiview import training_neighbours
from splat.strategy import PAPER_ITERS, IndoorStrategy
from splat.train_config import LearningRates, TrainConfig
from splat.tsdf_config import check_tsdf_resources
from splat.views import ViewSet, warn_large_images

log = logging.getLogger(__name__)


CHANGED_DEFAULTS = {("strategy", "max_gaussians"): (0, "auto")}
"""Options whose default changed (old, new). A checkpoint written under the old default resumes with it
while the option is left at the new one: an upgrade between a kill and the resume keeps the run's training."""


def _as_started(cfg: TrainConfig, ckpt: dict) -> TrainConfig:
    """``cfg`` as the checkpoint ``ckpt``'s run started: the old default of each CHANGED_DEFAULTS
    option its config holds where ``cfg`` has the new one."""
    saved = ckpt["config"]
    for (section, name), (old, new) in CHANGED_DEFAULTS.items():
        part = getattr(cfg, section)
        if saved.get(section, {}).get(name) == old and getattr(part, name) == new:
            log.warning("--resume: the run started with --%s.%s %r, the default then (now %r); it goes on with %r",
                        section, name.replace("_", "-"), old, new, old)
            cfg = replace(cfg, **{section: replace(part, **{name: old})})
    return cfg


def started_budget(cfg: TrainConfig, ckpt: dict | None) -> TrainConfig:
    """``cfg`` with --strategy.max-gaussians auto replaced by the budget the checkpoint's run resolved
    it to (kept in the checkpoint), so a resume trains under the budget the run started with even if
    the rule changed since. For setup_training only: the run's config and its checkpoints keep "auto"."""
    if ckpt is None:
        return cfg
    if cfg.strategy.max_gaussians != "auto" or ckpt.get("gaussian_budget") is None:
        return cfg
    return replace(cfg, strategy=replace(cfg.strategy, max_gaussians=int(ckpt["gaussian_budget"])))


def cue_cloud_path(cues: Path) -> Path:
    """CUES/cues.ply (or CUES itself, a cues.ply given directly); FileNotFoundError naming it when absent."""
    cues_ply = cues / "cues.ply" if cues.is_dir() else cues
    if not cues_ply.is_file():
        raise FileNotFoundError(f"no cue cloud at {cues_ply} (run `geocues extract SCENE -o CUES` first)")
    return cues_ply


def open_run(cfg: TrainConfig, out_dir: Path, cues: Path, overwrite: bool, resume: bool,
             scene_dir: Path | None = None) -> tuple[Path, Path, dict | None, TrainConfig]:
    """Check the inputs and the output folder before any work; return (the staging folder
    ``OUT.partial`` the run works in, the cue cloud's path, the checkpoint to resume from or None,
    the config to train with: ``cfg``, or for a resume ``cfg`` as the checkpoint's run started, see
    _as_started). Without ``resume`` an unfinished staging folder is
    removed."""
    cues_ply = cue_cloud_path(cues)
    cfg.validate()
    if cfg.mesh:  # found after the training, it lost the run
        check_tsdf_resources(cfg.tsdf)
    elif cfg.mesh_at_checkpoints:
        log.warning("--mesh-at-checkpoints with --no-mesh: no mesh is fused at all (--no-mesh wins), so the "
                    "accuracy-against-time curve has no mesh figures")
    work = staging_dir(out_dir)
    if (work / "report.json").is_file() and (work / "cfg_args").is_file() and not (out_dir / "cfg_args").is_file():
        if _publish_finished(work, out_dir) and not overwrite and _same_run(out_dir, cfg, scene_dir, cues_ply):
            raise RunFinished(out_dir)  # this command's run, finished: nothing to train
    # cfg_args: only a run writes it (an extract's folder has a report.json too)
    check_replaceable(out_dir, "cfg_args", "a `splat train` run", {"scene": scene_dir, "cues": cues})
    if (out_dir / "cfg_args").is_file() and not overwrite:  # OUT is published whole: a finished run
        raise ValueError(f"{out_dir} holds a finished run; pass --overwrite to replace it")
    check_output_dir(out_dir)  # a file, or a folder that refuses files: one line, before any work
    ckpt = None
    if resume:
        ckpt = checkpoint.load(work / checkpoint.CKPT_NAME)
        cfg = _as_started(cfg, ckpt)
        if diff := _changed_options(cfg, ckpt["config"]):
            raise ValueError(f"--resume: the options differ from the checkpoint's in {diff} "
                             f"({work / checkpoint.CKPT_NAME}; it has {_values(ckpt['config'], diff)}, "
                             f"this command {_values(asdict(cfg), diff)}); resume with the same options")
        if other := _other_input(work, {"scene": scene_dir, "cues": cues_ply}):
            raise ValueError(f"--resume: the run in {work} started from the {other[0]} {other[1]}, not {other[2]}; "
                             f"resume with the same {other[0]}")
    elif work.exists():
        if (work / checkpoint.CKPT_NAME).is_file() and not overwrite:  # hours of training: never dropped unasked
            raise ValueError(f"{work} holds an unfinished run with a checkpoint: pass --resume to continue it "
                             "(same options), or --overwrite to start again")
        log.warning("removing the unfinished run in %s (%s)", work,
                    "--overwrite" if overwrite else "pass --resume to continue it instead")
        shutil.rmtree(work)
    return work, cues_ply, ckpt, cfg


class RunFinished(Exception):
    """open_run found this command's run finished (published by this call): nothing to train."""


def _same_run(run: Path, cfg: TrainConfig, scene_dir: Path, cues_ply: Path) -> bool:
    """Whether the finished ``run`` trained with ``cfg`` (but for options that cannot change it) on the
    same scene and cues (its config.yaml's paths)."""
    try:
        done = json.loads((run / "report.json").read_text())["config"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return ((run / "config.yaml").is_file() and not _changed_options(cfg, done)
            and _other_input(run, {"scene": scene_dir, "cues": cues_ply}) is None)


def _publish_finished(work: Path, out_dir: Path) -> bool:
    """``work`` holds a finished run (its report.json, written last, is there) and ``out_dir`` none: the
    run was killed between its report and the rename onto OUT, or between the two renames of an
    --overwrite (geocues.atomic.replace_dir). It is published, not removed as an unfinished run (the
    rerun deleted it and trained again: kill audit); the run it replaced, left aside, goes."""
    backup = out_dir.with_name(f".{out_dir.name}.old")  # replace_dir's name for the run being replaced
    if out_dir.exists() and any(out_dir.iterdir()):
        return False  # not a run's folder: check_replaceable says so
    if out_dir.exists():
        out_dir.rmdir()
    publish(work, out_dir)
    try:
        keep = bool(json.loads((out_dir / "report.json").read_text())["config"]["keep_ckpt"])
    except (OSError, ValueError, KeyError, TypeError):
        keep = True  # unreadable: nothing removed
    if not keep:  # killed before the checkpoint of the finished run was removed
        shutil.rmtree(out_dir / "ckpt", ignore_errors=True)
    shutil.rmtree(backup, ignore_errors=True)
    log.warning("%s held a finished run (killed while it was moved into place): published to %s", work, out_dir)
    return True


def _values(config: dict, dotted: list[str]) -> str:
    """``config``'s values of the ``dotted`` options ("strategy.max_gaussians"), as "name=value, ..."."""
    return ", ".join(f"{k}={checkpoint.config_value(config, k)!r}" for k in dotted)


RESUME_FREE = {"save_every", "log_every", "keep_ckpt"}
"""Options a resumed run may change: when checkpoints are written and how often the log is, not the training."""


def _changed_options(cfg: TrainConfig, saved: dict) -> list[str]:
    """The options (dotted) in which ``cfg`` differs from the ``saved`` config of a run, but for those
    that cannot change the training (:data:`RESUME_FREE`)."""
    return [k for k in checkpoint.config_diff(asdict(cfg), saved, asdict(TrainConfig())) if k not in RESUME_FREE]


def _other_input(run: Path, inputs: dict[str, Path | None]) -> tuple[str, str, Path] | None:
    """(name, recorded, given) of the first input (SCENE, CUES) given other than the one the run started
    from (its config.yaml names them), else None. --resume with another is refused: other cues went on
    silently from the checkpoint (the report naming the new ones, the config the old), another scene
    failed with an IndexError. A run moved together with its inputs is the same run: the recorded path
    is gone, or the one recorded relative to the run is the one given."""
    import yaml

    try:
        started = yaml.safe_load((run / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return None
    if not isinstance(started, dict):
        return None
    for name, given in inputs.items():
        was, rel = started.get(name), started.get(f"{name}_from_run")
        if given is None or not isinstance(was, str):
            continue
        given = Path(given).resolve()
        same = Path(was).resolve() == given or (isinstance(rel, str) and (run / rel).resolve() == given)
        if not same and Path(was).exists():
            return name, was, given
    return None


def make_optimizers(params: torch.nn.ParameterDict, lr: LearningRates, scale: float,
                    adam: str = "fused") -> dict[str, torch.optim.Adam]:
    """One Adam per parameter (gsplat layout), eps 1e-15 as 3DGS. ``adam="fused"`` takes torch's
    single-kernel implementation (one pass over the moments instead of ~8 element-wise ops: about 5x
    faster on the CPU), ``"torch"`` torch's default implementation; the same update up to rounding."""
    rates = {"means": lr.means * scale, "scales": lr.scales, "quats": lr.quats,
             "opacities": lr.opacities, "sh0": lr.sh0, "shN": lr.shN}
    if adam not in ("fused", "torch"):
        raise ValueError(f"adam must be 'fused' or 'torch', got {adam!r}")
    impl = {"fused": True} if adam == "fused" else {}
    return {k: torch.optim.Adam([{"params": [params[k]], "lr": rates[k], "name": k}], eps=1e-15, **impl)
            for k in params}


def cue_report_priors(cfg: TrainConfig, scene: Scene, cues_ply: Path) -> tuple[dict, str]:
    """(per-image depth alignments for L_a — empty when it is off —, the depth priors' kind) from
    CUES/depth_alignments.json that `geocues extract` wrote beside the cues (older cue folders: their
    report.json; the kind, where unrecorded: scene.json's)."""
    try:
        kind = load_prior_kind(cues_ply.parent, default=scene.depth_kind)
    except FileNotFoundError:  # a bare cues.ply without its extract folder
        kind = scene.depth_kind
    chosen = read_cue_report(cues_ply).get("config", {}).get("prior_kind", "scene")  # --prior-kind of the extract
    if scene.has_depth_priors and kind != scene.depth_kind and chosen == "scene":  # scene.json changed since
        raise ValueError(f"the cues in {cues_ply.parent} were extracted with the depth priors read as {kind}, "
                         f"but {scene.root} now says {scene.depth_kind} (scene.json priors.depth_kind): run "
                         f"`geocues extract {shlex.quote(str(scene.root))} -o {shlex.quote(str(cues_ply.parent))} --overwrite` again")
    alignments = {}
    if cfg.loss.lambda_anchor > 0 or kind == "disparity":  # L_a, or depth for L_d from disparity
        try:
            alignments = load_alignments(cues_ply.parent)
        except FileNotFoundError:
            alignments = {}
        if not alignments and scene.has_depth_priors and cfg.loss.lambda_anchor > 0:
            log.warning("%s records no depth alignments (the extract ran without priors?): the "
                        "anchored-depth term L_a is off", cues_ply.parent)
    return alignments, kind  # with lambda_anchor 0 the anchors cost nothing: L_a is skipped


def type_counts(cue_type: Tensor) -> dict[str, int]:
    """Gaussians per cue type ({"SFM": n, "LINE": n, "PLANE": n})."""
    return {t.name: int((cue_type == t.value).sum()) for t in CueType}


@dataclass
class TrainingSetup:
    """Everything the loop reads or steps; ``params`` and ``state`` are changed in place by it."""

    scene: Scene
    train_views: ViewSet
    test_views: ViewSet
    params: torch.nn.ParameterDict
    optimizers: dict[str, torch.optim.Adam]
    strategy: IndoorStrategy
    state: dict  # the density control's state, with "cue_type" [N]
    init_counts: dict[str, int]  # Gaussians per cue type at the start
    scale: float  # the scene's scale (m): means' learning rate, guard bounds
    loss_cfg: LossConfig  # iteration counts scaled to the run
    late_loss_cfg: LossConfig  # from priors_step on: the priors not kept switched off
    priors_step: int
    neighbours: list[list[int]] | None  # L_mv's neighbours of each training view, or None when it is off
    refiner: CameraRefiner | None
    guard: NumericsGuard


def _load_views(cfg: TrainConfig, scene: Scene, scene_dir: Path, cues_ply: Path, device: torch.device
                ) -> tuple[ViewSet, ViewSet]:
    """The training views with the priors, alignments and plane anchors the losses use, and the test views."""
    alignments, prior_kind = cue_report_priors(cfg, scene, cues_ply)
    plane_depths = cfg.loss.plane_anchor and cfg.loss.lambda_anchor > 0
    plane_normals = cfg.loss.plane_normals and cfg.loss.use_normal
    planes = load_plane_anchors(cues_ply) if plane_depths or plane_normals else None
    fused = None
    if cfg.loss.fused_anchor and cfg.loss.lambda_anchor > 0 and alignments:
        from splat.fused_prior import fused_anchors

        fused = fused_anchors(scene, scene.train_indices, alignments, cfg.loss.fused_voxel, cfg.loss.fused_trunc,
                              cfg.loss.fused_method, cfg.loss.fused_neighbours)
    elif cfg.loss.fused_anchor:
        log.warning("--loss.fused-anchor: no aligned depth priors (or --loss.lambda-anchor 0): L_a has no fused prior")
    train_views = ViewSet(scene, scene.train_indices, device, desc="training views", alignments=alignments,
                          prior_kind=prior_kind, plane_anchors=planes if plane_depths else None,
                          plane_normals=planes if plane_normals else None, plane_first=cfg.loss.plane_first,
                          plane_views=cfg.loss.plane_views, anchor_override=fused)
    test_views = ViewSet(scene, scene.test_indices, device, load_priors=False, desc="test views")
    if len(train_views) == 0:
        raise ValueError(f"the scene {scene_dir} has no training views (test_every={cfg.test_every} holds out "
                         f"every {cfg.test_every}th of its {len(scene)} images): --test-every 0 trains on all of them")
    if few := few_views_warning(len(train_views), "training views"):
        warn_once(log, f"{scene_dir}: {few}")
    if cfg.loss.use_depth and not train_views.has_depth_priors:
        warn_once(log, f"{scene_dir} has no depth priors: L_d and L_a are off. From photos alone, `geocues mvs` "
                       "computes them without a network; train its scene with `geocues extract --preset mvs` cues "
                       "and `splat train --preset mvs` (docs/training.md, \"Photos only\")")
    return train_views, test_views


def setup_training(cfg: TrainConfig, scene_dir: Path, cues_ply: Path, device: torch.device) -> TrainingSetup:
    """Load the scene and its views, initialise the typed Gaussians from the cues (§4.2) and make
    what steps them. Every iteration count of the paper's schedule is scaled to ``cfg.iters``."""
    scene = Scene.load(scene_dir, downscale=cfg.downscale, test_every=cfg.test_every)
    warn_large_images(scene, cfg.downscale)
    # what is said of the scene is said once per process (not once per row of `splat ablate`)
    said = [fov_warning(scene), registration_warning(scene.metadata),
            normal_axes_warning(scene) if cfg.loss.use_normal else None,  # L_n would pull towards them as they are
            metric_warning(scene)]  # the TSDF's depth_max, voxels and hole seeds are in metres
    for sentence in filter(None, said):  # named by the scene: another scene in this process is warned again
        warn_once(log, sentence if sentence.startswith(str(scene_dir)) else f"{scene_dir}: {sentence}")
    if unfinished := unfinished_extract(cues_ply):
        warn_once(log, unfinished)
    train_views, test_views = _load_views(cfg, scene, scene_dir, cues_ply, device)
    cfg = with_budget(cfg, scene)
    init_params, cue_type, seeds = initial_gaussians(cfg, scene, cues_ply, train_views)
    scale = scene_scale(train_views.camera_centers(), seeds)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.to(device)) for k, v in init_params.items()})
    optimizers = make_optimizers(params, cfg.lr, scale, cfg.adam)
    compiled.enable(cfg.compile and device.type == "cuda")
    refiner = (CameraRefiner(len(train_views), scale, cfg.pose_opt, cfg.focal_opt, cfg.pose_lr, cfg.focal_lr, device)
               if cfg.pose_opt or cfg.focal_opt else None)
    strategy = IndoorStrategy(replace(cfg.strategy, total_iters=cfg.iters,  # no density control on frozen geometry
                                      refine_stop=min(cfg.strategy.refine_stop, round(cfg.geometry_until * PAPER_ITERS))))
    loss_cfg = replace(cfg.loss, nc_from_iter=round(cfg.loss.nc_from_iter * cfg.iters / PAPER_ITERS),
                       mv_from_iter=round(cfg.loss.mv_from_iter * cfg.iters / PAPER_ITERS))
    neighbours = training_neighbours(scene, train_views.indices, cfg.loss.mv_neighbours) if cfg.loss.lambda_mv > 0 else None
    if neighbours is not None:
        log.info("L_mv: %d of %d training views have a neighbour (%.1f on average)", sum(map(bool, neighbours)),
                 len(neighbours), float(np.mean([len(n) for n in neighbours])))
    state = strategy.initialize_state(scale)
    state["cue_type"] = cue_type.to(device)
    strategy.check_sanity(params, optimizers)
    guard = NumericsGuard(cfg.guard, torch.as_tensor(np.median(seeds, 0), dtype=torch.float32, device=device),
                          scale)
    return TrainingSetup(scene, train_views, test_views, params, optimizers, strategy, state, type_counts(cue_type),
                         scale, loss_cfg, without_priors(loss_cfg, cfg.priors_kept), round(cfg.priors_until * cfg.iters),
                         neighbours, refiner, guard)
