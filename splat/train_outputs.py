"""What `splat train` renders and writes from its Gaussians: a view's render with the run's
background, the held-out metrics (and PNGs), the TSDF mesh of the training views, and the outputs a
finished run leaves in its folder (the 3DGS-format model, refined cameras, mesh)."""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from splat.camera_opt import CameraRefiner
from splat.export import write_3dgs_run
from splat.gaussians import cue_type_path
from splat.mesh import write_mesh
from splat.mesh_run import fuse_cameras
from splat.rasterize import render
from splat.train_config import TrainConfig
from splat.train_setup import TrainingSetup
from splat.views import View, ViewSet

_BACKGROUNDS: dict[tuple, Tensor] = {}

FEW_VIEWS = 8  # training views under which an empty mesh is named as their lack
FEW_TRIANGLES = 1000  # a mesh under this is named as (nearly) empty: a room at 2 cm voxels has tens of thousands
TSDF_SAYS = ("voxel_size", "sdf_trunc", "depth_max", "weight_threshold", "consistent_views", "max_depth_spread")
"""TSDF options that can leave a mesh empty when set far from their defaults."""


def render_view(params, view: View, sh_degree: int, cfg: TrainConfig, maps: bool = True) -> dict[str, Tensor]:
    key = (tuple(cfg.background), view.rgb.device)  # made once: a copy to a GPU waits for it each time
    if key not in _BACKGROUNDS:
        _BACKGROUNDS[key] = torch.tensor(cfg.background, dtype=torch.float32, device=view.rgb.device)
    return render(params, view.camera, sh_degree=sh_degree, backend=cfg.backend, background=_BACKGROUNDS[key],
                  maps=maps)


@torch.no_grad()
def evaluate_views(params, views: ViewSet, sh_degree: int, cfg: TrainConfig, out_dir: Path | None = None,
                   refiner: CameraRefiner | None = None) -> dict:
    """Mean PSNR / SSIM of the renders of held-out ``views`` (with the refined shared focal when a
    ``refiner`` is given); PNGs to ``out_dir`` when given."""
    from evaluation.image_metrics import PSNR_MAX, psnr, ssim

    rows = []
    for k in range(len(views)):
        view = refiner.test_view(views[k]) if refiner is not None else views[k]
        out = render_view(params, view, sh_degree, cfg, maps=False)
        rgb = out["rgb"].clamp(0, 1)  # colour alone: the same image
        rows.append({"name": view.name, "psnr": min(psnr(rgb.cpu(), view.rgb.cpu()), PSNR_MAX),  # as `evaluate`
                     "ssim": ssim(rgb.cpu(), view.rgb.cpu()), "alpha": float(out["alpha"].mean())})
        if out_dir is not None:
            import cv2
            out_dir.mkdir(parents=True, exist_ok=True)
            img = (rgb.cpu().numpy()[:, :, ::-1] * 255.0 + 0.5).astype(np.uint8)
            cv2.imwrite(str(out_dir / (Path(view.name).stem + ".png")), img)
    if not rows:
        return {"psnr": None, "ssim": None, "n_views": 0}
    return {"psnr": float(np.mean([r["psnr"] for r in rows])), "ssim": float(np.mean([r["ssim"] for r in rows])),
            "alpha": float(np.mean([r["alpha"] for r in rows])), "n_views": len(rows), "per_view": rows}


NOTHING_RENDERED = 0.01  # mean alpha of the held-out views under which a model is said to render nothing
PRUNING_SAYS = ("strategy.prune_opa", "strategy.prune_scale3d", "strategy.grow_scale3d", "init.min_scale",
                "init.opacity", "lr.opacities", "lr.scales")
"""Options that can prune every Gaussian (or leave none visible) when set far from their defaults."""


def empty_result(cfg: TrainConfig, s: TrainingSetup, final: dict) -> str | None:
    """Why the trained model is no model (a sentence), or None: no Gaussian left, or none that the
    held-out views see (mean alpha under 1 %: a scene in millimetres lies within the 0.01 m near plane)."""
    n = len(s.state["cue_type"])
    default = type(cfg)()
    changed = []
    for dotted in PRUNING_SAYS:
        group, name = dotted.split(".")
        if hasattr(getattr(cfg, group), name) and getattr(getattr(cfg, group), name) != getattr(getattr(default, group), name):
            changed.append(f"--{group}.{name.replace('_', '-')} {getattr(getattr(cfg, group), name)}")
    settings = f"the settings in use ({', '.join(changed)})" if changed else "the --strategy.* and --init.* settings"
    if n == 0:
        return f"the run ended with 0 Gaussians: every one was pruned; check {settings}"
    alpha = final.get("alpha")
    if alpha is not None and alpha < NOTHING_RENDERED:
        from geocues.rescale import metric_warning

        why = metric_warning(s.scene)
        return (f"the held-out views render nothing (mean alpha {alpha:.2g}, {n} Gaussians): "
                + (why if why else f"the Gaussians are out of the cameras' view; check {settings} and the cameras "
                   "(geocues info)"))
    return None


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


def write_outputs(cfg: TrainConfig, s: TrainingSetup, loop, timings: dict[str, float]) -> dict:
    """Held-out renders and metrics, the 3DGS-format model, the refined cameras and the mesh into the
    staging folder of ``loop`` (the finished splat.train._Loop: its folder and accuracy curve); returns
    the final held-out metrics."""
    work = loop.work
    t0 = time.perf_counter()
    final = evaluate_views(s.params, s.test_views, cfg.sh_degree, cfg, work / "test_renders", s.refiner)
    refinement = None
    if s.refiner is not None:  # the refined training cameras: corrections per view (bench/camera_error.py reads them)
        refinement = work / "camera_refinement.npz"
        s.refiner.save(refinement, [s.scene.cameras[i].name for i in s.train_views.indices])
    ply = write_3dgs_run(work, s.params, s.state["cue_type"], s.scene, asdict(cfg), cfg.iters, refinement)
    for src in (ply, cue_type_path(ply)):  # RUN/point_cloud.ply is the same model: a copy, not a hard link
        if src.is_file():  # (a file edited in place would change what SIBR and render.py load as well)
            shutil.copyfile(src, work / src.name)
    timings["eval_and_save_s"] = time.perf_counter() - t0
    if cfg.mesh:
        t0 = time.perf_counter()
        if loop.curve and loop.curve[-1]["step"] == cfg.iters and "mesh" in loop.curve[-1]:
            shutil.copyfile(work / loop.curve[-1]["mesh"], work / "mesh.ply")  # the same model, fused already
        else:
            write_mesh(fuse_mesh(s.params, s.train_views, cfg.sh_degree, cfg, s.refiner), work / "mesh.ply")
        timings["mesh_s"] = time.perf_counter() - t0
    return final


def final_warnings(cfg: TrainConfig, s: TrainingSetup, mesh: dict | None, psnr: str, out_dir: Path,
                   empty: str | None = None) -> list[str]:
    """The sentences a finished run ends with when its result may not be what it looks like: an empty
    (or nearly empty) mesh and its likely cause, steps the divergence guard rolled back, a camera refinement
    gone far; ``empty`` (:func:`empty_result`) is said last, in place of the mesh's cause."""
    out = []
    events = len(s.guard.events)
    if empty is not None:
        pass  # the model itself is empty: the mesh's emptiness has no other cause to name
    elif mesh is not None and mesh["triangles"] < FEW_TRIANGLES:
        changed = [f"--tsdf.{k.replace('_', '-')} {getattr(cfg.tsdf, k)}" for k in TSDF_SAYS
                   if getattr(cfg.tsdf, k) != getattr(type(cfg.tsdf)(), k)]  # from the command line or a preset
        from geocues.rescale import metric_warning

        unit = metric_warning(s.scene) if getattr(s, "scene", None) is not None else None
        cause = (f"{len(s.train_views)} training views are too few to fit a room (it wants dozens)"
                 if len(s.train_views) < FEW_VIEWS else
                 unit if unit else  # a scene in mm: every depth beyond --tsdf.depth-max, voxels of 2 mm
                 f"check the TSDF settings in use ({', '.join(changed)})" if changed else
                 "check the cameras (geocues info) and the learning rates (--lr.*)")
        what = ("is EMPTY (no rendered depth was fused" if mesh["triangles"] == 0 else
                f"has only {mesh['triangles']} triangle{'s' * (mesh['triangles'] != 1)} (a room meshes to tens of thousands")
        out.append(f"the mesh of {out_dir} {what}: test PSNR {psnr}"
                   f"{f', {events} steps rolled back' if events else ''}); {cause}")
    elif events:
        out.append(f"the divergence guard rolled back {events} steps of this run (report.json guard_events): its "
                   f"result may be poor; lower the learning rates (--lr.*) or the loss weights that spiked")
    if empty is None and (idle := idle_terms(Path(out_dir) / "train_log.jsonl")):  # (an empty model: no term acts)
        out.append(f"the loss term{'s' * (len(idle) > 1)} {', '.join(idle)} {'were' if len(idle) > 1 else 'was'} 0 at "
                   f"every logged step: never acted (patches of --loss.patch-size {cfg.loss.patch_size} px with too few "
                   "valid pixels in small images, or priors that cover nothing rendered); the run is the row without it")
    if s.refiner is not None:
        r = s.refiner.summary()
        if not 0.67 < r["focal_factor"] < 1.5 or r["rotation_deg"]["max"] > 10:
            out.append(f"the camera refinement went far (focal x{r['focal_factor']:.3g}, up to "
                       f"{r['rotation_deg']['max']:.3g} deg): it no longer refines the scene's cameras; lower "
                       "--pose-lr / --focal-lr, or check the scene's poses")
    if empty is not None:
        out.append(f"the model of {out_dir} is EMPTY: {empty}")
    return out


PRIOR_TERMS = ("depth", "anchor", "normal", "nc", "mv")  # loss terms that can be 0 for want of valid pixels


def idle_terms(log_path: Path) -> list[str]:
    """The prior loss terms a run's train_log.jsonl logs at every line and that are exactly 0 at
    every one (a tiny run's L_d found no patch with enough valid pixels: `no-ld` scored as `full`)."""
    import json

    try:
        rows = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError):
        return []
    return [t for t in PRIOR_TERMS if rows and all(t in r for r in rows) and all(r[t] == 0 for r in rows)]
