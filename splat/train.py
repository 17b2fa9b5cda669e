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
import shutil
import time
from dataclasses import asdict
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from geocues.atomic import atomic_path, locks_output
from geocues.scene import Scene
from splat import checkpoint, run_paths
from splat.camera_opt import CameraRefiner
from splat.checkpoint import SignalCatcher, TrainingInterrupted, publish
from splat.composite import describe_backend
from splat.frozen import GEOMETRY_KEYS, colour_step
from splat.guard import NumericsGuard, TrainingDiverged
from splat.losses import LossConfig, total_loss
from splat.mesh import write_mesh
from splat.multiview import SourceView, source_view
from splat.strategy import PAPER_ITERS, IndoorStrategy
from splat.init_gaussians import initial_gaussians, load_init_cloud  # noqa: F401  (re-exported)
from splat.mesh_post import ply_element_counts
from splat.train_config import LearningRates, TrainConfig  # noqa: F401  (re-exported)
from splat.train_setup import (TrainingSetup, cue_report_priors, make_optimizers,  # noqa: F401  (re-exported)
                               RunFinished, open_run, setup_training, started_budget, type_counts)
from splat.train_outputs import (empty_result, evaluate_views, final_warnings, fuse_mesh,  # noqa: F401  (re-exported)
                                 render_view)
from splat.train_outputs import write_outputs as _write_outputs
from splat.views import View

log = logging.getLogger(__name__)

COLOUR_STEP_WHEN_FROZEN = True
"""Once the geometry is frozen (TrainConfig.geometry_until), train with splat.frozen.colour_step (the
colours' gradient alone); False: the full step with the geometry's learning rates at 0, its oracle."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} asked for, but torch sees no CUDA device")
    try:
        device = torch.device(name)
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ValueError(f"--device {name!r}: give auto, cpu, cuda or cuda:N")
    return device


def means_lr(step: int, total: int, lr: LearningRates, scale: float) -> float:
    """Log-linear decay from lr.means to lr.means_final over the run (3DGS expon_lr_func)."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return scale * math.exp((1 - t) * math.log(lr.means) + t * math.log(lr.means_final))


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


def _live_view(cfg: TrainConfig, scene: Scene):
    """The `--view` server (splat/viewer.py), or None."""
    if not cfg.view:
        return None
    from splat.viewer import LiveView

    return LiveView(scene, port=cfg.view_port)


def _db(psnr: float | None) -> str:
    return "none (no test views)" if psnr is None else f"{psnr:.2f} dB"


class _Loop:
    """The loop's own state — step, view order, accuracy-against-time curve, training seconds, the
    log's byte length — with the in-memory snapshots the guard rolls back to and the checkpoint a
    stopped run resumes from (splat/checkpoint.py)."""

    def __init__(self, cfg: TrainConfig, s: TrainingSetup, work: Path, rng: np.random.Generator,
                 gen: torch.Generator, t_start: float) -> None:
        self.cfg, self.s, self.rng, self.gen = cfg, s, rng, gen
        self.step, self.order, self.curve, self.train_s, self.log_bytes = 0, [], [], 0.0, 0
        # seconds of held-out metrics and meshes at checkpoints, and of wall time in earlier sessions (a resumed run)
        self.checkpoint_s, self.wall_before, self.t_start = 0.0, 0.0, t_start
        self.checkpoints = sorted({max(1, min(cfg.iters, round(f * cfg.iters))) for f in cfg.checkpoints})
        self.sh_every = max(1, round(1000 * cfg.iters / PAPER_ITERS))
        self.freeze_step = round(cfg.geometry_until * cfg.iters)
        self.base_lr = {k: opt.param_groups[0]["lr"] for k, opt in s.optimizers.items()}
        self.work, self.log_path, self.ckpt_path = work, work / "train_log.jsonl", work / checkpoint.CKPT_NAME

    def snapshot(self) -> dict:
        s = self.s
        return checkpoint.capture(s.params, s.optimizers, s.state, {
            "step": self.step, "order": [int(i) for i in self.order],
            "numpy_rng": checkpoint.numpy_rng_state(self.rng), "gen": self.gen.get_state(), "curve": self.curve,
            "train_s": self.train_s, "log_bytes": self.log_bytes, "lr_mult": s.guard.lr_mult,
            "guard_events": s.guard.events, "guard_level": [s.guard.loss_mean, s.guard.n_good],
            "camera_refiner": s.refiner.state_dict() if s.refiner is not None else None,
            "checkpoint_s": self.checkpoint_s, "wall_s": self.wall_s(), "gaussian_budget": s.strategy.cfg.max_gaussians})

    def wall_s(self) -> float:
        """Wall seconds of the run so far, earlier sessions included."""
        return self.wall_before + time.perf_counter() - self.t_start

    def restore(self, snap: dict) -> None:
        s = self.s
        extra = checkpoint.restore(snap, s.params, s.optimizers, s.state)
        self.order, self.curve, self.train_s, self.log_bytes = (extra["order"], extra["curve"], extra["train_s"],
                                                                extra["log_bytes"])
        checkpoint.set_numpy_rng_state(self.rng, extra["numpy_rng"])
        self.gen.set_state(extra["gen"])
        if "guard_level" in extra:  # the loss level the guard compares with (checkpoints of older runs lack it)
            s.guard.loss_mean, s.guard.n_good = extra["guard_level"]
        if s.refiner is not None and extra.get("camera_refiner") is not None:
            s.refiner.load_state_dict(extra["camera_refiner"])
        self.step = extra["step"]

    def resume(self, ckpt: dict) -> None:
        self.restore(ckpt)
        # seconds are not rolled back with the guard's snapshots: taken from the checkpoint here only
        self.checkpoint_s, self.wall_before = ckpt.get("checkpoint_s", 0.0), ckpt.get("wall_s", self.train_s)
        self.s.guard.lr_mult, self.s.guard.events = dict(ckpt["lr_mult"]), list(ckpt["guard_events"])
        log.info("resuming %s at step %d (%.0f s of training done)", self.work, self.step, self.train_s)

    def _iteration(self) -> tuple[Tensor, dict, dict, int]:
        """One step on the next view of the order: (loss, its terms, what density control did, the SH degree)."""
        cfg, s, step = self.cfg, self.s, self.step
        frozen = step >= self.freeze_step
        for key, opt in s.optimizers.items():
            rate = means_lr(step, cfg.iters, cfg.lr, s.scale) if key == "means" else self.base_lr[key]
            if frozen and key in GEOMETRY_KEYS:
                rate = 0.0  # Adam with lr 0 moves nothing: the geometry stays as it is
            opt.param_groups[0]["lr"] = rate * s.guard.lr_mult.get(key, 1.0)
        if not self.order:
            self.order = list(self.rng.permutation(len(s.train_views)))
        k = self.order.pop()
        view = s.train_views[k]
        colour_only = frozen and COLOUR_STEP_WHEN_FROZEN and step >= s.strategy.schedule.stop
        loss_cfg = s.loss_cfg if step < s.priors_step else s.late_loss_cfg
        source = None  # L_mv's neighbour: none for the colour step, which has no L_mv
        if s.neighbours and s.neighbours[k] and step >= s.loss_cfg.mv_from_iter and loss_cfg.lambda_mv > 0 \
                and not colour_only:
            j = s.neighbours[k][int(torch.randint(len(s.neighbours[k]), (1,), generator=self.gen))]
            source = source_view(view.camera, s.train_views.cameras[j], s.train_views.image(j))
        sh_degree = min(cfg.sh_degree, step // self.sh_every)
        if s.refiner is not None:
            s.refiner.set_progress(step / cfg.iters, frozen=frozen)
            view = s.refiner.view(k, view)
        guard = s.guard if cfg.guard.enabled else None
        if colour_only:
            loss, terms, density = colour_step(s.params, s.optimizers, view, sh_degree, loss_cfg, step,
                                               partial(render_view, cfg=cfg), guard)
        else:
            loss, terms, density = train_step(s.params, s.optimizers, s.strategy, s.state, view, step, sh_degree,
                                              cfg, loss_cfg, self.gen, guard, source=source, refiner=s.refiner)
        return loss, terms, density, sh_degree

    def _roll_back(self, event: dict, good: dict, log_file) -> dict:
        """Back to the last good snapshot ``good`` after the guard's ``event``, its lowered learning
        rates and its events kept; the event logged. Returns the new good snapshot."""
        guard = self.s.guard
        try:
            guard.on_rollback(event)  # raises TrainingDiverged after too many in a row
        except TrainingDiverged as exc:
            checkpoint.save(self.ckpt_path, good, asdict(self.cfg))
            raise TrainingDiverged(f"{exc}; the last good state (step {good['step']}) is in {self.ckpt_path}") from None
        log_file.flush()
        lr_mult, events = dict(guard.lr_mult), list(guard.events)
        self.restore(good)
        guard.lr_mult, guard.events = lr_mult, events
        log_file.seek(0, 2)
        log_file.write(json.dumps({"step": event["step"], "guard": event}) + "\n")
        log_file.flush()
        self.log_bytes = log_file.tell()
        return self.snapshot()

    def _at_checkpoint(self, sh_degree: int) -> None:
        """Held-out PSNR/SSIM (and a mesh, with mesh_at_checkpoints) onto the accuracy-against-time curve."""
        cfg, s, t0 = self.cfg, self.s, time.perf_counter()
        metrics = evaluate_views(s.params, s.test_views, sh_degree, cfg, refiner=s.refiner)
        self.curve.append({"step": self.step, "train_s": round(self.train_s, 2), "psnr": metrics["psnr"],
                           "ssim": metrics["ssim"], "n_gaussians": len(s.state["cue_type"])})
        if cfg.mesh and cfg.mesh_at_checkpoints:
            rel = Path("checkpoints") / f"mesh_{self.step:06d}.ply"
            write_mesh(fuse_mesh(s.params, s.train_views, sh_degree, cfg, s.refiner), self.work / rel)
            self.curve[-1]["mesh"] = str(rel)
        self.checkpoint_s += time.perf_counter() - t0
        log.info("checkpoint %d: %.1f s training, test PSNR %s", self.step, self.train_s, _db(metrics["psnr"]))

    def run(self) -> None:
        """Iterate to cfg.iters; on SIGINT / SIGTERM write the checkpoint and raise TrainingInterrupted."""
        cfg, s = self.cfg, self.s
        with open(self.log_path, "a+b") as f:  # a resumed run cuts the log back to its checkpoint
            f.truncate(self.log_bytes)
        good = self.snapshot()
        last_save = self.train_s
        live = _live_view(cfg, s.scene)
        with open(self.log_path, "a") as log_file, SignalCatcher() as signals, \
                tqdm(total=cfg.iters, initial=self.step, desc="splat train", unit="it") as bar, \
                contextlib.closing(live) if live else contextlib.nullcontext():
            while self.step < cfg.iters:
                t0 = time.perf_counter()
                loss, terms, density, sh_degree = self._iteration()
                event = density.get("guard") or s.guard.check_params(self.step, s.params)
                if event is None and density.get("opacity_reset"):
                    s.guard.on_opacity_reset()
                if event is not None:
                    good = self._roll_back(event, good, log_file)
                    bar.n = self.step
                    continue
                self.train_s += time.perf_counter() - t0
                self.step += 1
                step = self.step
                bar.update(1)
                if live and (step % cfg.view_every == 0 or step == cfg.iters):
                    live.update(s.params, step, float(loss))
                if (step - 1) % cfg.log_every == 0 or step == cfg.iters or density:
                    row = {"step": step - 1, "train_s": round(self.train_s, 3), "loss": float(loss), **terms,
                           "n": len(s.state["cue_type"]), **type_counts(s.state["cue_type"])}
                    if density:
                        row["density"] = density
                    log_file.write(json.dumps(row) + "\n")
                    log_file.flush()  # readable while the run works (`splat ablate --jobs` progress, tail -f)
                    bar.set_postfix(loss=f"{float(loss):.4f}", n=len(s.state["cue_type"]))
                if step in self.checkpoints:
                    self._at_checkpoint(sh_degree)
                save_due = cfg.save_every > 0 and self.train_s - last_save >= cfg.save_every
                if step % cfg.guard.snapshot_every == 0 or signals.caught or save_due:
                    log_file.flush()
                    self.log_bytes = log_file.tell()
                    good = self.snapshot()
                    s.guard.on_snapshot()
                    if signals.caught or save_due:
                        checkpoint.save(self.ckpt_path, good, asdict(cfg))
                        last_save = self.train_s
                    if signals.caught:
                        raise TrainingInterrupted(
                            f"stopped by {signals.caught} at step {step} of {cfg.iters}; checkpoint "
                            f"{self.ckpt_path}; continue with the same command and --resume", signals.caught)
            log_file.flush()
            self.log_bytes = log_file.tell()  # every row: the state after the loop is whole (see run())


@locks_output("splat train")  # a second run into OUT removed or published this one's work
def run(cfg: TrainConfig | None, scene_dir: str | Path, cues: str | Path, out_dir: str | Path, *,
        overwrite: bool = False, resume: bool = False) -> Path:
    """Train on the scene in ``scene_dir`` from the cue cloud ``cues`` (a cues.ply or the folder
    holding it); write the outputs (module docstring) to ``out_dir``; return ``out_dir``.

    The run works in ``OUT.partial`` and renames it to OUT when everything is written, so OUT is
    never a mix of two runs. ``OUT.partial/ckpt/last.pt`` is written every ``save_every`` seconds
    of training and on SIGINT / SIGTERM (then :class:`TrainingInterrupted` is raised);
    ``resume=True`` continues from it. A finished OUT is only replaced with ``overwrite=True``.
    """
    if cfg is None:  # as geocues.extract.run: the defaults
        cfg = TrainConfig()
    elif not isinstance(cfg, TrainConfig):
        raise TypeError(f"cfg must be a TrainConfig (or None for the defaults; splat.presets.preset_config "
                        f"for a preset), got {type(cfg).__name__}")
    out_dir = Path(out_dir)
    try:
        work, cues_ply, ckpt, cfg = open_run(cfg, out_dir, Path(cues), overwrite, resume, Path(scene_dir))
    except RunFinished:  # killed while publishing its finished run, which open_run published
        log.info("done: the run had finished before the kill; outputs in %s", out_dir)
        return out_dir
    device = resolve_device(cfg.device)
    rasterizer = describe_backend(cfg.backend, device)  # builds the kernels now, with a message, not in the first step
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)  # CPU: the loss patches are drawn on the CPU
    t_start = time.perf_counter()
    s = setup_training(started_budget(cfg, ckpt), Path(scene_dir), cues_ply, device)
    timings = {"load_and_init_s": time.perf_counter() - t_start}
    log.info("training %d iterations on %d views (%d test), %d Gaussians %s, scene scale %.2f m, rasterizer %s",
             cfg.iters, len(s.train_views), len(s.test_views), len(s.state["cue_type"]), s.init_counts, s.scale,
             rasterizer)

    work.mkdir(parents=True, exist_ok=True)
    if ckpt is None:
        from splat.presets import write_config_file

        write_config_file(work / "config.yaml", cfg, {f"{name}{k}": v for name, path in (("scene", scene_dir),
                                                                                         ("cues", cues_ply))
                                                      for k, v in run_paths.record(path, work).items()})
    loop = _Loop(cfg, s, work, rng, gen, t_start)
    if ckpt is not None:
        loop.resume(ckpt)
    step0 = loop.step
    loop.run()
    timings["train_s"], timings["checkpoints_s"] = loop.train_s, loop.checkpoint_s

    try:
        final = _write_outputs(cfg, s, loop, timings)
    except KeyboardInterrupt as exc:  # Ctrl-C / SIGTERM while meshing: keep the trained model, resumable
        checkpoint.save(loop.ckpt_path, loop.snapshot(), asdict(cfg))
        raise TrainingInterrupted(
            f"stopped after training (step {loop.step} of {cfg.iters}) while writing its outputs; checkpoint "
            f"{loop.ckpt_path}; continue with the same command and --resume (the outputs are written, "
            "nothing trained again)", exc.args[0] if exc.args else "SIGINT") from None
    timings["total_s"] = loop.wall_s()  # earlier sessions of a resumed run included
    mesh = None
    if cfg.mesh and (work / "mesh.ply").is_file():
        counts = ply_element_counts(work / "mesh.ply")
        mesh = {"vertices": counts.get("vertex", 0), "triangles": counts.get("face", 0)}
    paths = {f"{name}{k}": v for name, path in (("scene", scene_dir), ("cues", cues_ply))
             for k, v in run_paths.record(path, out_dir).items()}  # readable from any folder (splat/run_paths.py)
    report = {"config": asdict(cfg), **paths, "device": str(device),
              "rasterizer": rasterizer,
              "scene_scale": s.scale, "n_train_views": len(s.train_views), "n_test_views": len(s.test_views),
              "gaussians_init": s.init_counts, "gaussians_final": type_counts(s.state["cue_type"]),
              "gaussian_budget": s.strategy.cfg.max_gaussians,
              "test_metrics": {k: v for k, v in final.items() if k != "per_view"},
              "test_per_view": final.get("per_view", []), "accuracy_vs_time": loop.curve, "timings": timings,
              "resumed_from_step": step0 if ckpt is not None else None, "guard_events": s.guard.events,
              "camera_refinement": s.refiner.summary() if s.refiner is not None else None, "mesh": mesh,
              "empty_result": empty_result(cfg, s, final)}
    if cfg.keep_ckpt:  # the final state (a save every --save-every seconds left an older one, or none)
        checkpoint.save(loop.ckpt_path, loop.snapshot(), asdict(cfg))
    with atomic_path(work / "report.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2, allow_nan=False))
    if not cfg.keep_ckpt:
        shutil.rmtree(work / "ckpt", ignore_errors=True)
    publish(work, out_dir)
    log.info("done in %.1f s: test PSNR %s, %d Gaussians; outputs in %s", timings["total_s"],
             _db(final["psnr"]), len(s.state["cue_type"]), out_dir)
    for warning in final_warnings(cfg, s, mesh, _db(final["psnr"]), out_dir,
                                  report["empty_result"]):  # what a run's result may not be: said last
        log.warning("%s", warning)
    return out_dir
