"""`evaluate report RUN`: one `splat train` folder at a glance.

Writes into RUN: ``report.md`` linking ``report_losses.png`` (loss terms against iterations),
``report_gaussians.png`` (Gaussians per type against iterations), ``report_accuracy.png`` (test
PSNR / SSIM and, when a GT mesh is at hand, mesh metrics of the checkpoint meshes against training
seconds), ``report_views.png`` (held-out views: GT | render | rendered depth | rendered normals |
depth error against exact GT depth where it exists) and ``report_data.json``, the data every figure
was drawn from. The checkpoint meshes of a run on a scene mapped from images alone are scored only with
``align_to`` (`evaluate report RUN --align-to GT_SCENE`, the alignment of `evaluate --align-to`).
Rendering goes through splat's public API (``splat.render_run.load_run``, ``render``).
"""

from __future__ import annotations

import json
import logging
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evaluation import figures as plt  # pyplot's calls on detached figures: the user's backend is left alone
from evaluation.ablation_report import PANELS
from geocues.atomic import atomic_path, check_output_file

log = logging.getLogger(__name__)

LOSS_TERMS = ("loss", "rgb", "depth", "anchor", "normal", "flat", "nc", "mv")
TYPES = ("SFM", "LINE", "PLANE", "n")


def _read_log(run_dir: Path) -> list[dict]:
    path = run_dir / "train_log.jsonl"
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir} is not a `splat train` folder: no train_log.jsonl")
    rows = []
    for k, line in enumerate(path.read_text().splitlines()):
        try:
            rows.append(json.loads(line))
        except ValueError:
            log.warning("%s line %d is not JSON (a killed run?): skipped", path, k + 1)
    return rows


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    return path


def _gaussians(final) -> str:
    """report.json's ``gaussians_final`` ({type: count}, or a count) as text."""
    if isinstance(final, dict):
        return f"{sum(final.values())} Gaussians (" + ", ".join(f"{k} {v}" for k, v in final.items()) + ")"
    return f"{final} Gaussians" if final is not None else "Gaussians unknown"


@dataclass
class MeshCurve:
    """Mesh metrics of a run's checkpoint meshes (:func:`mesh_curve`)."""

    points: list[dict]  # per checkpoint mesh: step, train_s, chamfer_l1, f_score, normal_consistency
    alignment: dict | None = None  # with --align-to: Alignment.to_dict() of the run's scene to GT_SCENE
    skipped: str | None = None  # why no mesh was scored though a GT mesh is at hand


def mesh_curve(run_dir: Path, report: dict, gt: Path | None, scene: Path | None,
               align_to: Path | None = None) -> MeshCurve:
    """Mesh metrics of each checkpoint mesh the run kept (paths relative to RUN; needs a GT mesh).

    ``align_to``: the GT scene of a run whose scene is in its own frame; the meshes are moved into its
    frame as `evaluate PRED_MESH SCENE --align-to GT_SCENE` does (one alignment for all) and scored
    against its GT mesh (or ``gt``). Without it, the meshes of a scene mapped from images alone are not
    scored: a warning, and ``skipped`` says why (the report carries it)."""
    from evaluation.align import align_scenes, evaluate_aligned, own_frame_warning
    from evaluation.mesh_metrics import evaluate_with_scene
    from geocues.scene import gt_mesh_file

    points = [p for p in report.get("accuracy_vs_time", []) if p.get("mesh") and (run_dir / p["mesh"]).is_file()]
    alignment = None
    if not points:  # no checkpoint mesh: nothing to align or score
        if align_to is not None or gt is not None:  # asked for, and it would pass without a word
            why = (f"{run_dir} kept no checkpoint meshes (`splat train --mesh-at-checkpoints` keeps one per "
                   f"checkpoint): no mesh metrics; `evaluate RUN/mesh.ply SCENE` (with the same --gt / --align-to) "
                   "scores the final mesh")
            log.warning("%s", why)
            return MeshCurve([], skipped=why)
        return MeshCurve([])
    if align_to is not None:
        alignment = align_scenes(scene, align_to)  # first: too few shared images is named before any scoring
    elif gt is None and (scene is None or gt_mesh_file(scene) is None):
        return MeshCurve([])
    elif (warning := own_frame_warning(scene, "checkpoint meshes")) is not None:
        log.warning("%s; the report leaves the mesh metrics out", warning)
        return MeshCurve([], skipped=warning)

    def score(mesh: Path):
        if alignment is None:
            return evaluate_with_scene(mesh, gt, scene)
        return evaluate_aligned(mesh, scene, align_to, gt, alignment=alignment)

    out = []
    for p in points:
        m = score(run_dir / p["mesh"]).to_dict()
        out.append({"step": p["step"], "train_s": p["train_s"],
                    **{k: m[k] for k in ("chamfer_l1", "f_score", "normal_consistency")}})
    return MeshCurve(out, alignment.to_dict() if alignment is not None else None)


def contact_sheet(run_dir: Path, scene_dir: Path, n_views: int, gt_depth: Path | None) -> dict:
    """Render ``n_views`` held-out views; returns the panel images and per-view depth errors."""
    import torch

    from splat.camera import Camera
    from splat.rasterize import render
    from splat.render_run import load_run

    scene, params, cfg = load_run(run_dir, scene_dir)
    indices = scene.test_indices or scene.train_indices
    pick = [indices[k] for k in np.linspace(0, len(indices) - 1, min(n_views, len(indices))).round().astype(int)]
    depth_dir = gt_depth if gt_depth is not None else (scene.root / "gt" / "depth")
    rows, errors = [], []
    bg = torch.tensor(cfg.get("background", (0.0, 0.0, 0.0)), dtype=torch.float32)
    for i in dict.fromkeys(pick):
        cam = scene.cameras[i]
        with torch.no_grad():
            out = render(params, Camera.from_Rt(cam.K, cam.R, cam.t, cam.width, cam.height), background=bg)
        depth = out["median_depth"].numpy()
        err = None
        if depth_dir.is_dir():
            from splat.floor import load_gt_depth

            try:
                gt = load_gt_depth(depth_dir, cam.stem, depth.shape, 1000.0)
                both = (gt > 0) & (depth > 0)
                err = np.where(both, np.abs(depth - gt), np.nan)
                errors.append({"view": cam.name,  # None: nothing rendered where GT has depth (JSON has no NaN)
                               "median_abs_depth_error_m": float(np.median(err[both])) if both.any() else None})
            except FileNotFoundError:
                err = None
        rows.append({"name": cam.name, "gt": scene.load_image(i), "render": out["rgb"].clamp(0, 1).numpy(),
                     "depth": depth, "normal": out["normal"].numpy(), "error": err})
    return {"rows": rows, "depth_errors": errors}


def _draw_sheet(sheet: dict, path: Path) -> Path:
    rows = sheet["rows"]
    has_err = any(r["error"] is not None for r in rows)
    cols = ["GT", "render", "depth (m)", "normals"] + (["|depth - GT| (m)"] if has_err else [])
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(3.2 * len(cols), 2.5 * len(rows)), squeeze=False,
                             constrained_layout=True)
    errors = {e["view"]: e["median_abs_depth_error_m"] for e in sheet["depth_errors"]}
    depth_cmap = plt.get_cmap("turbo").with_extremes(bad="black")  # black: no depth, as `splat render`
    for ri, (r, row) in enumerate(zip(axes, rows)):
        valid = row["depth"][row["depth"] > 0]
        vmin, vmax = (float(np.percentile(valid, 1)), float(np.percentile(valid, 99))) if valid.size else (0.0, 1.0)
        panels = [row["gt"], row["render"], None, (1 - row["normal"]) / 2]
        for k, ax in enumerate(r):
            ax.set_xticks([]), ax.set_yticks([])
            if k == 2:
                im = ax.imshow(np.where(row["depth"] > 0, row["depth"], np.nan), cmap=depth_cmap, vmin=vmin,
                               vmax=vmax)
                fig.colorbar(im, ax=ax, fraction=0.04, extend="both")
            elif k == 4:
                if row["error"] is not None:
                    im = ax.imshow(row["error"], cmap="magma", vmin=0, vmax=0.1)
                    fig.colorbar(im, ax=ax, fraction=0.04, extend="max")  # the arrow: 0.1 m and more
            else:
                ax.imshow(np.clip(panels[k], 0, 1))
            if ri == 0:
                ax.set_title(cols[k], fontsize=9)
        err = errors.get(row["name"])  # None: no rendered depth where GT has some
        r[0].set_ylabel(row["name"] + (f"\nmedian |depth - GT| {100 * err:.1f} cm" if err is not None else ""),
                        fontsize=8)
    return _save(fig, path)


def write_run_report(run_dir: str | Path, scene: str | Path | None = None, gt: str | Path | None = None,
                     gt_depth: str | Path | None = None, n_views: int = 4, *, overwrite: bool = False,
                     align_to: str | Path | None = None) -> Path:
    """The report of one `splat train` folder (module docstring); returns RUN/report.md. An earlier
    report (RUN/report.md, written last) is replaced only with ``overwrite``. ``align_to``: the GT scene
    of a run on a scene in its own frame (:func:`mesh_curve`)."""
    run_dir = Path(run_dir)
    report_path = run_dir / "report.json"
    if not report_path.is_file():
        raise FileNotFoundError(f"{run_dir} holds no report.json (not a finished `splat train` folder)")
    check_output_file(run_dir / "report.md", overwrite)  # the report is written into RUN
    report = json.loads(report_path.read_text())
    from splat.run_paths import recorded_path

    scene_dir = Path(scene) if scene is not None else recorded_path(run_dir, report, "scene")
    if scene_dir is None or not scene_dir.is_dir():
        where = "given" if scene is not None else f"recorded in {report_path}"
        raise FileNotFoundError(f"the run's scene folder {scene_dir} ({where}) does not exist; give the scene after "
                                f"RUN: `evaluate report {shlex.quote(str(run_dir))} SCENE`")
    log_rows = _read_log(run_dir)
    curve = mesh_curve(run_dir, report, Path(gt) if gt else None, scene_dir, Path(align_to) if align_to else None)
    meshes = curve.points

    losses = {t: [(r["step"], r[t]) for r in log_rows if r.get(t) is not None] for t in LOSS_TERMS}
    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    for t, pts in losses.items():
        if pts:
            ax.plot(*zip(*pts), label=t, lw=2 if t == "loss" else 1)
    ax.set_yscale("log"), ax.set_xlabel("iteration"), ax.set_ylabel("value (log scale)")
    ax.set_title("loss terms (unweighted; loss = weighted total)")
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5)), ax.grid(alpha=0.3)  # beside: no curve hidden
    _save(fig, run_dir / "report_losses.png")

    counts = {t: [(r["step"], r[t]) for r in log_rows if t in r] for t in TYPES}
    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    for t, pts in counts.items():
        if pts:
            ax.plot(*zip(*pts), label="all" if t == "n" else t, lw=2 if t == "n" else 1.3)
    ax.set_xlabel("iteration"), ax.set_ylabel("Gaussians"), ax.set_title("Gaussians per type")
    ax.legend(fontsize=8), ax.grid(alpha=0.3)
    _save(fig, run_dir / "report_gaussians.png")

    images = [{k: p.get(k) for k in ("step", "train_s", "psnr", "ssim", "n_gaussians")}
              for p in report.get("accuracy_vs_time", [])]
    panels = [("psnr", "test PSNR (dB)", 1.0, images), ("ssim", "test SSIM", 1.0, images)]
    panels += [(k, title, scale, meshes) for k, title, scale in PANELS[:3]] if meshes else []  # C-L1 in cm
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.4), squeeze=False, constrained_layout=True)
    for ax, (key, title, scale, data) in zip(axes[0], panels):
        pts = [(d["train_s"], d[key] * scale) for d in data if d.get(key) is not None]
        if pts:
            ax.plot(*zip(*pts), marker="o")
        ax.set_xlabel("training seconds"), ax.set_title(title), ax.grid(alpha=0.3)
    _save(fig, run_dir / "report_accuracy.png")

    sheet = contact_sheet(run_dir, scene_dir, n_views, Path(gt_depth) if gt_depth else None)
    _draw_sheet(sheet, run_dir / "report_views.png")

    data = {"run": str(run_dir), "scene": str(scene_dir), "losses": losses, "gaussians": counts,
            "images_vs_time": images, "mesh_vs_time": meshes, "mesh_alignment": curve.alignment,
            "mesh_skipped": curve.skipped,
            "views": [r["name"] for r in sheet["rows"]], "depth_errors": sheet["depth_errors"]}
    with atomic_path(run_dir / "report_data.json") as tmp:
        tmp.write_text(json.dumps(data, indent=1, allow_nan=False))
    final = report.get("test_metrics", {})
    name = run_dir.resolve().name
    if name == "train":  # `splat ablate`'s OUT/rows/<row>_s<seed>/train: the row names the run
        name = f"{run_dir.resolve().parent.name}/train"
    held_out = bool(final.get("n_views"))  # --test-every 0: no held-out view (it said 'test PSNR nan dB')
    scores = (f"test PSNR {final.get('psnr'):.2f} dB, SSIM {final.get('ssim'):.3f} ({final.get('n_views')} views)"
              if held_out else "no held-out views (--test-every 0): no test PSNR")
    lines = [f"# `splat train` run: {name}", "",
             f"Scene `{scene_dir.resolve()}`; {report['config']['iters']} iterations; {scores}; "
             f"{_gaussians(report.get('gaussians_final'))}; training {report['timings']['train_s']:.0f} s.", ""]
    if meshes:
        m, a = meshes[-1], curve.alignment
        lines += [f"Final mesh: Chamfer-L1 {m['chamfer_l1'] * 100:.2f} cm, F@5cm {m['f_score']:.3f}, "
                  f"NC {m['normal_consistency']:.3f}"
                  + (f", after aligning the scene to `{align_to}` by the camera centres of {a['shared_images']} "
                     f"shared images (residual median {100 * a['centre_residual_m']['median']:.1f} cm)" if a else "")
                  + ".", ""]
    elif curve.skipped:
        lines += [f"Mesh metrics left out: {curve.skipped}.", ""]
    lines += ["![accuracy against time](report_accuracy.png)", "", "![loss terms](report_losses.png)", "",
              "![Gaussians per type](report_gaussians.png)", "",
              ("Held-out views" if held_out else "Training views (the run held none out)")
              + ": GT | render | rendered median depth | rendered normals"
              + (" | depth error against exact GT depth" if sheet["depth_errors"] else "") + ":", "",
              "![held-out views](report_views.png)", ""]
    with atomic_path(run_dir / "report.md") as tmp:
        tmp.write_text("\n".join(lines))
    return run_dir / "report.md"
