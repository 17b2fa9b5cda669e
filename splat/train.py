"""`splat train`: typed Gaussians from the cues, optimised with the IndoorGS losses, then a TSDF mesh.

One stage, one entry: ``run(cfg, scene_dir, cues, out_dir) -> Path`` (hloc style). The loop is the
3DGS loop (Adam per parameter, exponentially decaying position learning rate, one random training
view per iteration, SH degree raised step by step); what is IndoorGS's lives in other modules:
initialisation from typed cues (splat/gaussians.py, §4.2), the per-type density control
(splat/strategy.py, §4.2), the losses (splat/losses.py, §4.3) and RaDe-GS depth and normals
(splat/rasterize.py, §3.2). Meshing is splat/mesh.py (TSDF fusion of the rendered expected or median depth, `--tsdf.depth`).

Every iteration count of the paper's 30k-iteration schedule scales with ``iters`` (the strategy's
``total_iters``, the SH degree steps), so a short CPU run keeps the schedule's shape.

Outputs in OUT: ``point_cloud.ply`` (3DGS format + cue_type), ``mesh.ply``, ``test_renders/*.png``,
``train_log.jsonl`` (loss terms, Gaussian counts per type, seconds), ``report.json`` (config, counts,
timings per stage, test-view PSNR/SSIM at each checkpoint against training seconds).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import time
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from geocues.atomic import atomic_path, check_output_dir
from geocues.depth_align import load_alignments, load_prior_kind
from geocues.plane_anchors import load_plane_anchors
from geocues.rescale import metric_warning
from geocues.scene import Scene
from geocues.types import CueType
from splat import checkpoint, compiled
from splat.camera_opt import CameraRefiner
from splat.checkpoint import SignalCatcher, TrainingInterrupted, publish, staging_dir
from splat.composite import describe_backend
from splat.export import write_3dgs_run
from splat.frozen import GEOMETRY_KEYS, colour_step
from splat.gaussians import cue_type_path, scene_scale
from splat.guard import NumericsGuard, TrainingDiverged
from splat.losses import LossConfig, total_loss, without_priors
from splat.mesh import write_mesh
from splat.mesh_run import fuse_cameras
from splat.multiview import SourceView, source_view, training_neighbours
from splat.rasterize import render
from splat.strategy import PAPER_ITERS, IndoorStrategy
from splat.init_gaussians import initial_gaussians, load_init_cloud  # noqa: F401  (re-exported)
from splat.train_config import LearningRates, TrainConfig  # noqa: F401  (re-exported)
from splat.views import View, ViewSet, warn_large_images

log = logging.getLogger(__name__)

COLOUR_STEP_WHEN_FROZEN = True
"""Once the geometry is frozen (TrainConfig.geometry_until), train with splat.frozen.colour_step (the
colours' gradient alone); False: the full step with the geometry's learning rates at 0, its oracle."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} asked for, but torch sees no CUDA device")
    return torch.device(name)


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


def means_lr(step: int, total: int, lr: LearningRates, scale: float) -> float:
    """Log-linear decay from lr.means to lr.means_final over the run (3DGS expon_lr_func)."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return scale * math.exp((1 - t) * math.log(lr.means) + t * math.log(lr.means_final))


_BACKGROUNDS: dict[tuple, Tensor] = {}


def render_view(params, view: View, sh_degree: int, cfg: TrainConfig, maps: bool = True) -> dict[str, Tensor]:
    key = (tuple(cfg.background), view.rgb.device)  # made once: a copy to a GPU waits for it each time
    if key not in _BACKGROUNDS:
        _BACKGROUNDS[key] = torch.tensor(cfg.background, dtype=torch.float32, device=view.rgb.device)
    return render(params, view.camera, sh_degree=sh_degree, backend=cfg.backend, background=_BACKGROUNDS[key],
                  maps=maps)


def _link_or_copy(src: Path, dst: Path) -> None:
    """``dst`` as a hard link to ``src`` (a copy where the file system has none)."""
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def train_step(params, optimizers: dict, strategy: IndoorStrategy, state: dict, view: View, step: int,
               sh_degree: int, cfg: TrainConfig, loss_cfg: LossConfig,
               generator: torch.Generator | None = None, guard: NumericsGuard | None = None,
               stage_s: dict[str, float] | None = None, source: SourceView | None = None,
               refiner: CameraRefiner | None = None) -> tuple[Tensor, dict, dict]:
    """One iteration on one view: render, IndoorGS loss, backward, Adam, per-type density control.

    ``loss_cfg`` is the run's loss config with its iteration counts already scaled (see run()).
    With a ``guard``, a step whose loss or gradients are not sound takes no optimizer step and no
    density control; its report is returned under ``density["guard"]``. With ``stage_s`` (a dict),
    the seconds of each stage (render, loss, backward, optimizer, density) are added to it (the
    per-stage breakdown of bench/train_step_bench.py; CUDA work is synchronised at each boundary).
    ``source``: the neighbouring training view of L_mv (splat/multiview.py), if it is on.
    ``refiner``: the camera corrections (splat/camera_opt.py) that ``view``'s camera carries, stepped with the Gaussians.
    Returns the loss, its terms and what the density control did at this step (empty if nothing).
    """
    clock = _StageClock(stage_s, params["means"].device)
    out = render_view(params, view, sh_degree, cfg)
    clock("render")
    loss, terms = total_loss(out, view.rgb, view.camera.K, params, state["cue_type"], loss_cfg, step,
                             depth_prior=view.depth_prior, normal_prior=view.normal_prior, generator=generator,
                             depth_anchor=view.depth_anchor, anchor_p90=view.anchor_p90, source=source,
                             anchor_tight=view.anchor_tight)
    info = {**out, "width": view.camera.width, "height": view.camera.height,
            "camera_center": view.camera.center, "viewmat": view.camera.viewmat}
    strategy.step_pre_backward(params, optimizers, state, step, info)
    clock("loss")
    loss.backward()
    clock("backward")
    if guard is not None:
        event = guard.check_step(step, float(loss.detach()), terms, params)
        if event is not None:
            for opt in optimizers.values():
                opt.zero_grad(set_to_none=True)
            if refiner is not None:
                refiner.zero_grad()
            return loss.detach(), terms, {"guard": event}
    for opt in optimizers.values():
        opt.step()
    if refiner is not None:
        refiner.step()
    clock("optimizer")
    density = strategy.step_post_backward(params, optimizers, state, step, info)
    for opt in optimizers.values():
        opt.zero_grad(set_to_none=True)
    clock("density")
    return loss.detach(), terms, density


class _StageClock:
    """Adds the seconds since the previous call to ``stage_s[name]``; a no-op when stage_s is None."""

    def __init__(self, stage_s: dict[str, float] | None, device: torch.device) -> None:
        self.stage_s, self.cuda = stage_s, device.type == "cuda"
        self.t = self._now() if stage_s is not None else 0.0

    def _now(self) -> float:
        if self.cuda:
            torch.cuda.synchronize()
        return time.perf_counter()

    def __call__(self, name: str) -> None:
        if self.stage_s is not None:
            t = self._now()
            self.stage_s[name] = self.stage_s.get(name, 0.0) + t - self.t
            self.t = t


@torch.no_grad()
def evaluate_views(params, views: ViewSet, sh_degree: int, cfg: TrainConfig, out_dir: Path | None = None,
                   refiner: CameraRefiner | None = None) -> dict:
    """Mean PSNR / SSIM of the renders of held-out ``views`` (with the refined shared focal when a
    ``refiner`` is given); PNGs to ``out_dir`` when given."""
    from evaluation.image_metrics import psnr, ssim

    rows = []
    for k in range(len(views)):
        view = refiner.test_view(views[k]) if refiner is not None else views[k]
        rgb = render_view(params, view, sh_degree, cfg, maps=False)["rgb"].clamp(0, 1)  # colour alone: the same image
        rows.append({"name": view.name, "psnr": psnr(rgb.cpu(), view.rgb.cpu()), "ssim": ssim(rgb.cpu(), view.rgb.cpu())})
        if out_dir is not None:
            import cv2
            out_dir.mkdir(parents=True, exist_ok=True)
            img = (rgb.cpu().numpy()[:, :, ::-1] * 255.0 + 0.5).astype(np.uint8)
            cv2.imwrite(str(out_dir / (Path(view.name).stem + ".png")), img)
    if not rows:
        return {"psnr": None, "ssim": None, "n_views": 0}
    return {"psnr": float(np.mean([r["psnr"] for r in rows])), "ssim": float(np.mean([r["ssim"] for r in rows])),
            "n_views": len(rows), "per_view": rows}


@torch.no_grad()
def fuse_mesh(params, views: ViewSet, sh_degree: int, cfg: TrainConfig, refiner: CameraRefiner | None = None):
    """TSDF fusion of the rendered depth (``cfg.tsdf.depth``; alpha > 0.5) and colour of every
    mesh_every-th training view (with its refined camera when a ``refiner`` is given), cleaned
    (:func:`fuse_cameras`)."""
    ks = range(0, len(views), max(cfg.mesh_every, 1))
    cams = [views.scene.cameras[views.indices[k]] for k in ks]
    if refiner is not None:
        cams = [refiner.refined_scene_camera(k, cam) for k, cam in zip(ks, cams)]
    return fuse_cameras(params, cams, sh_degree, cfg.tsdf, backend=cfg.backend, background=cfg.background,
                        device=views[0].rgb.device if len(views) else "cpu")


def _type_counts(cue_type: Tensor) -> dict[str, int]:
    return {t.name: int((cue_type == t.value).sum()) for t in CueType}


def _live_view(cfg: TrainConfig, scene: Scene):
    """The `--view` server (splat/viewer.py), or None."""
    if not cfg.view:
        return None
    from splat.viewer import LiveView

    return LiveView(scene, port=cfg.view_port)


def cue_report_priors(cfg: TrainConfig, scene: Scene, cues_ply: Path) -> tuple[dict, str]:
    """(per-image depth alignments for L_a — empty when it is off —, the depth priors' kind) from
    CUES/depth_alignments.json that `geocues extract` wrote beside the cues (older cue folders: their
    report.json; the kind, where unrecorded: scene.json's)."""
    try:
        kind = load_prior_kind(cues_ply.parent, default=scene.depth_kind)
    except FileNotFoundError:  # a bare cues.ply without its extract folder
        kind = scene.depth_kind
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


def _db(psnr: float | None) -> str:
    return "none (no test views)" if psnr is None else f"{psnr:.2f} dB"


def run(cfg: TrainConfig, scene_dir: str | Path, cues: str | Path, out_dir: str | Path, *,
        overwrite: bool = False, resume: bool = False) -> Path:
    """Train on the scene in ``scene_dir`` from the cue cloud ``cues`` (a cues.ply or the folder
    holding it); write the outputs (module docstring) to ``out_dir``; return ``out_dir``.

    The run works in ``OUT.partial`` and renames it to OUT when everything is written, so OUT is
    never a mix of two runs. ``OUT.partial/ckpt/last.pt`` is written every ``save_every`` seconds
    of training and on SIGINT / SIGTERM (then :class:`TrainingInterrupted` is raised);
    ``resume=True`` continues from it. A finished OUT is only replaced with ``overwrite=True``.
    """
    out_dir, cues = Path(out_dir), Path(cues)
    cues_ply = cues / "cues.ply" if cues.is_dir() else cues
    if not cues_ply.is_file():
        raise FileNotFoundError(f"no cue cloud at {cues_ply} (run `geocues extract SCENE -o CUES` first)")
    cfg.validate()
    work = staging_dir(out_dir)
    if (out_dir / "report.json").is_file() and not overwrite:
        raise ValueError(f"{out_dir} holds a finished run; pass --overwrite to replace it")
    check_output_dir(out_dir)  # a file, or a folder that refuses files: one line, before any work
    ckpt = None
    if resume:
        ckpt = checkpoint.load(work / checkpoint.CKPT_NAME)
        diff = checkpoint.config_diff(asdict(cfg), ckpt["config"], asdict(TrainConfig()))
        if diff:
            raise ValueError(f"--resume: the options differ from the checkpoint's in {diff} "
                             f"({work / checkpoint.CKPT_NAME}); resume with the same options")
    elif work.exists():
        log.warning("removing the unfinished run in %s (pass --resume to continue it instead)", work)
        shutil.rmtree(work)
    device = resolve_device(cfg.device)
    rasterizer = describe_backend(cfg.backend, device)  # builds the kernels now, with a message, not in the first step
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)  # CPU: the loss patches are drawn on the CPU
    t_start = time.perf_counter()
    timings: dict[str, float] = {}

    scene = Scene.load(scene_dir, downscale=cfg.downscale, test_every=cfg.test_every)
    warn_large_images(scene, cfg.downscale)
    if far := metric_warning(scene):  # the TSDF's depth_max, voxels and hole seeds are in metres
        log.warning("%s", far)
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
        raise ValueError(f"the scene {scene_dir} has no training views (test_every={cfg.test_every})")
    if cfg.loss.use_depth and not train_views.has_depth_priors:
        log.warning("%s has no depth priors: L_d and L_a are off. From photos alone, `geocues mvs` computes "
                    "them without a network; train its scene with `geocues extract --preset mvs` cues and "
                    "`splat train --preset mvs` (docs/training.md, \"Photos only\")", scene_dir)
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
    late_loss_cfg, priors_step = without_priors(loss_cfg, cfg.priors_kept), round(cfg.priors_until * cfg.iters)
    neighbours = training_neighbours(scene, train_views.indices, cfg.loss.mv_neighbours) if cfg.loss.lambda_mv > 0 else None
    if neighbours is not None:
        log.info("L_mv: %d of %d training views have a neighbour (%.1f on average)", sum(map(bool, neighbours)),
                 len(neighbours), float(np.mean([len(n) for n in neighbours])))
    state = strategy.initialize_state(scale)
    state["cue_type"] = cue_type.to(device)
    strategy.check_sanity(params, optimizers)
    guard = NumericsGuard(cfg.guard, torch.as_tensor(np.median(seeds, 0), dtype=torch.float32, device=device),
                          scale)
    timings["load_and_init_s"] = time.perf_counter() - t_start
    log.info("training %d iterations on %d views (%d test), %d Gaussians %s, scene scale %.2f m, rasterizer %s",
             cfg.iters, len(train_views), len(test_views), len(cue_type), _type_counts(cue_type), scale, rasterizer)

    work.mkdir(parents=True, exist_ok=True)
    if ckpt is None:
        from splat.presets import write_config_file

        write_config_file(work / "config.yaml", cfg, {"scene": str(scene_dir), "cues": str(cues_ply)})
    checkpoints = sorted({max(1, min(cfg.iters, round(f * cfg.iters))) for f in cfg.checkpoints})
    sh_every = max(1, round(1000 * cfg.iters / PAPER_ITERS))
    freeze_step = round(cfg.geometry_until * cfg.iters)
    base_lr = {k: opt.param_groups[0]["lr"] for k, opt in optimizers.items()}
    curve, order, train_s, step0, log_bytes = [], [], 0.0, 0, 0
    log_path = work / "train_log.jsonl"

    def snapshot(step: int) -> dict:
        return checkpoint.capture(params, optimizers, state, {
            "step": step, "order": [int(i) for i in order], "numpy_rng": checkpoint.numpy_rng_state(rng),
            "gen": gen.get_state(), "curve": curve, "train_s": train_s, "log_bytes": log_bytes,
            "lr_mult": guard.lr_mult, "guard_events": guard.events, "guard_level": [guard.loss_mean, guard.n_good],
            "camera_refiner": refiner.state_dict() if refiner is not None else None})

    def restore(snap: dict) -> int:
        nonlocal order, curve, train_s, log_bytes
        extra = checkpoint.restore(snap, params, optimizers, state)
        order, curve, train_s, log_bytes = extra["order"], extra["curve"], extra["train_s"], extra["log_bytes"]
        checkpoint.set_numpy_rng_state(rng, extra["numpy_rng"])
        gen.set_state(extra["gen"])
        if "guard_level" in extra:  # the loss level the guard compares with (checkpoints of older runs lack it)
            guard.loss_mean, guard.n_good = extra["guard_level"]
        if refiner is not None and extra.get("camera_refiner") is not None:
            refiner.load_state_dict(extra["camera_refiner"])
        return extra["step"]

    if ckpt is not None:
        step0 = restore(ckpt)
        guard.lr_mult, guard.events = dict(ckpt["lr_mult"]), list(ckpt["guard_events"])
        log.info("resuming %s at step %d (%.0f s of training done)", work, step0, train_s)
    with open(log_path, "a+b") as f:  # a resumed run cuts the log back to its checkpoint
        f.truncate(log_bytes)
    good = snapshot(step0)
    ckpt_path = work / checkpoint.CKPT_NAME
    last_save = train_s
    step = step0
    live = _live_view(cfg, scene)
    with open(log_path, "a") as log_file, SignalCatcher() as signals, \
            tqdm(total=cfg.iters, initial=step0, desc="splat train", unit="it") as bar, \
            contextlib.closing(live) if live else contextlib.nullcontext():
        while step < cfg.iters:
            t0 = time.perf_counter()
            frozen = step >= freeze_step
            for key, opt in optimizers.items():
                rate = means_lr(step, cfg.iters, cfg.lr, scale) if key == "means" else base_lr[key]
                if frozen and key in GEOMETRY_KEYS:
                    rate = 0.0  # Adam with lr 0 moves nothing: the geometry stays as it is
                opt.param_groups[0]["lr"] = rate * guard.lr_mult.get(key, 1.0)
            if not order:
                order = list(rng.permutation(len(train_views)))
            k = order.pop()
            view = train_views[k]
            colour_only = frozen and COLOUR_STEP_WHEN_FROZEN and step >= strategy.schedule.stop
            step_loss_cfg = loss_cfg if step < priors_step else late_loss_cfg
            source = None  # L_mv's neighbour: none for the colour step, which has no L_mv
            if neighbours and neighbours[k] and step >= loss_cfg.mv_from_iter and step_loss_cfg.lambda_mv > 0 \
                    and not colour_only:
                j = neighbours[k][int(torch.randint(len(neighbours[k]), (1,), generator=gen))]
                source = source_view(view.camera, train_views.cameras[j], train_views.image(j))
            sh_degree = min(cfg.sh_degree, step // sh_every)
            if refiner is not None:
                refiner.set_progress(step / cfg.iters, frozen=frozen)
                view = refiner.view(k, view)
            if colour_only:
                loss, terms, density = colour_step(params, optimizers, view, sh_degree, step_loss_cfg, step,
                                                   partial(render_view, cfg=cfg),
                                                   guard if cfg.guard.enabled else None)
            else:
                loss, terms, density = train_step(params, optimizers, strategy, state, view, step, sh_degree,
                                                  cfg, step_loss_cfg, gen, guard if cfg.guard.enabled else None,
                                                  source=source, refiner=refiner)
            event = density.get("guard") or guard.check_params(step, params)
            if event is None and density.get("opacity_reset"):
                guard.on_opacity_reset()
            if event is not None:
                try:
                    guard.on_rollback(event)  # raises TrainingDiverged after too many in a row
                except TrainingDiverged as exc:
                    checkpoint.save(ckpt_path, good, asdict(cfg))
                    raise TrainingDiverged(f"{exc}; the last good state (step {good['step']}) is in {ckpt_path}") from None
                log_file.flush()
                lr_mult, events = dict(guard.lr_mult), list(guard.events)
                step = restore(good)
                guard.lr_mult, guard.events = lr_mult, events
                log_file.seek(0, 2)
                log_file.write(json.dumps({"step": event["step"], "guard": event}) + "\n")
                log_file.flush()
                log_bytes = log_file.tell()
                good = snapshot(step)
                bar.n = step
                continue
            train_s += time.perf_counter() - t0
            step += 1
            bar.update(1)
            if live and (step % cfg.view_every == 0 or step == cfg.iters):
                live.update(params, step, float(loss))
            if (step - 1) % cfg.log_every == 0 or step == cfg.iters or density:
                row = {"step": step - 1, "train_s": round(train_s, 3), "loss": float(loss), **terms,
                       "n": len(state["cue_type"]), **_type_counts(state["cue_type"])}
                if density:
                    row["density"] = density
                log_file.write(json.dumps(row) + "\n")
                log_file.flush()  # readable while the run works (`splat ablate --jobs` progress, tail -f)
                bar.set_postfix(loss=f"{float(loss):.4f}", n=len(state["cue_type"]))
            if step in checkpoints:
                metrics = evaluate_views(params, test_views, sh_degree, cfg, refiner=refiner)
                curve.append({"step": step, "train_s": round(train_s, 2), "psnr": metrics["psnr"],
                              "ssim": metrics["ssim"], "n_gaussians": len(state["cue_type"])})
                if cfg.mesh and cfg.mesh_at_checkpoints:
                    rel = Path("checkpoints") / f"mesh_{step:06d}.ply"
                    write_mesh(fuse_mesh(params, train_views, sh_degree, cfg, refiner), work / rel)
                    curve[-1]["mesh"] = str(rel)
                log.info("checkpoint %d: %.1f s training, test PSNR %s", step, train_s, _db(metrics["psnr"]))
            if step % cfg.guard.snapshot_every == 0 or signals.caught or \
                    (cfg.save_every > 0 and train_s - last_save >= cfg.save_every):
                log_file.flush()
                log_bytes = log_file.tell()
                good = snapshot(step)
                guard.on_snapshot()
                if signals.caught or (cfg.save_every > 0 and train_s - last_save >= cfg.save_every):
                    checkpoint.save(ckpt_path, good, asdict(cfg))
                    last_save = train_s
                if signals.caught:
                    raise TrainingInterrupted(
                        f"stopped by {signals.caught} at step {step} of {cfg.iters}; checkpoint {ckpt_path}; "
                        "continue with the same command and --resume")
    timings["train_s"] = train_s

    t0 = time.perf_counter()
    final = evaluate_views(params, test_views, cfg.sh_degree, cfg, work / "test_renders", refiner)
    ply = write_3dgs_run(work, params, state["cue_type"], scene, asdict(cfg), cfg.iters)
    for src in (ply, cue_type_path(ply)):  # RUN/point_cloud.ply is the same model: linked, written once
        if src.is_file():
            _link_or_copy(src, work / src.name)
    if refiner is not None:  # the refined training cameras: corrections per view (bench/camera_error.py reads them)
        refiner.save(work / "camera_refinement.npz", [train_views.scene.cameras[i].name for i in train_views.indices])
    timings["eval_and_save_s"] = time.perf_counter() - t0
    if cfg.mesh:
        t0 = time.perf_counter()
        if curve and curve[-1]["step"] == cfg.iters and "mesh" in curve[-1]:
            shutil.copyfile(work / curve[-1]["mesh"], work / "mesh.ply")  # the same model, fused already
        else:
            write_mesh(fuse_mesh(params, train_views, cfg.sh_degree, cfg, refiner), work / "mesh.ply")
        timings["mesh_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    report = {"config": asdict(cfg), "scene": str(scene_dir), "cues": str(cues_ply), "device": str(device),
              "rasterizer": rasterizer,
              "scene_scale": scale, "n_train_views": len(train_views), "n_test_views": len(test_views),
              "gaussians_init": _type_counts(cue_type), "gaussians_final": _type_counts(state["cue_type"]),
              "test_metrics": {k: v for k, v in final.items() if k != "per_view"},
              "test_per_view": final.get("per_view", []), "accuracy_vs_time": curve, "timings": timings,
              "resumed_from_step": step0 if ckpt is not None else None, "guard_events": guard.events,
              "camera_refinement": refiner.summary() if refiner is not None else None}
    with atomic_path(work / "report.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2, allow_nan=False))
    if not cfg.keep_ckpt:
        shutil.rmtree(work / "ckpt", ignore_errors=True)
    publish(work, out_dir)
    log.info("done in %.1f s: test PSNR %s, %d Gaussians; outputs in %s", timings["total_s"],
             _db(final["psnr"]), len(state["cue_type"]), out_dir)
    return out_dir
