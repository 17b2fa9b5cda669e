"""Rendered depth of a trained model against a benchmark room's exact GT depth, per view.

Where does the mesh error come from? The TSDF fuses the median depth (alpha > 0.5) of the
training views, so this measures that depth directly: the share of GT pixels that are holes
(alpha <= 0.5), the share within 2 / 5 cm, and whether the wrong pixels sit in front of the GT
surface (floaters) or behind it, over all pixels and split into textureless pixels (grey 7×7
standard deviation < 0.01, where NCC and MVS see nothing) and textured ones. Needs exact depth:
the scene's `gt/depth/` (evaluate make-room) or ``--gt-depth DIR`` (.npy in metres, or .png divided
by ``--gt-depth-png-scale``: 1000 for ICL-NUIM).

    python bench/depth_diag.py --scene outputs/demo/room --model outputs/exp/base1k [--json OUT]
    python bench/depth_diag.py --scene outputs/icl_sfm --model RUN --gt-depth ../shared/data/icl_livingroom1/depth \
        --depth expected --every 6
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geocues.scene import Scene  # noqa: E402
from splat.camera import Camera  # noqa: E402
from splat.gaussians import load_ply  # noqa: E402
from splat.rasterize import render  # noqa: E402


@dataclass
class DepthDiag:
    scene: Path
    model: Path  # a `splat train` output folder (point_cloud.ply) or the PLY itself
    downscale: float = 2.0  # render size; GT depth is sampled at the rendered pixel centres
    split: str = "train"  # train | test | all
    json: Path | None = None
    gt_depth: Path | None = None  # folder of exact depth (default: SCENE/gt/depth)
    gt_depth_png_scale: float = 1000.0  # .png depth values per metre
    depth: str = "median"  # rendered depth compared: "median" or "expected"
    every: int = 1  # every n-th view of the split


def gt_depth_at(folder: Path, index_name: str, width: int, height: int, png_scale: float = 1000.0) -> np.ndarray:
    """GT z-depth of the full-size image sampled (nearest) at the centres of a width×height grid."""
    stem = Path(index_name).stem
    if (folder / f"{stem}.npy").is_file():
        gt = np.load(folder / f"{stem}.npy")
    else:
        import cv2

        gt = cv2.imread(str(folder / f"{stem}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / png_scale
    rows = np.minimum(((np.arange(height) + 0.5) * gt.shape[0] / height).astype(int), gt.shape[0] - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * gt.shape[1] / width).astype(int), gt.shape[1] - 1)
    return gt[np.ix_(rows, cols)]


def main(cfg: DepthDiag) -> dict:
    ply = cfg.model / "point_cloud.ply" if cfg.model.is_dir() else cfg.model
    params, _ = load_ply(ply)
    scene = Scene.load(cfg.scene, downscale=cfg.downscale)
    idx = {"train": scene.train_indices, "test": scene.test_indices}.get(cfg.split, range(len(scene.cameras)))
    from geocues.mvs import _gray, patch_stats

    folder = cfg.gt_depth or Path(cfg.scene) / "gt" / "depth"
    idx = list(idx)[:: max(cfg.every, 1)]
    acc = {k: 0.0 for k in ("pixels", "hole", "w2", "w5", "front5", "behind5")}
    split = {f"{part}_{k}": 0.0 for part in ("flat", "textured") for k in ("pixels", "w2", "w5", "front5", "behind5")}
    errs = []
    per_view = []
    with torch.no_grad():
        for i in idx:
            c = scene.cameras[i]
            out = render(params, Camera.from_Rt(c.K, c.R, c.t, c.width, c.height))
            d = out["median_depth" if cfg.depth == "median" else "depth"].numpy()
            a = out["alpha"].numpy()
            gt = gt_depth_at(folder, c.name, c.width, c.height, cfg.gt_depth_png_scale)
            ok = gt > 0
            hole = ok & (a <= 0.5)
            cov = ok & ~hole
            e = d[cov] - gt[cov]
            errs.append(np.abs(e))
            v = {"pixels": ok.sum(), "hole": hole.sum(), "w2": (np.abs(e) < 0.02).sum(), "w5": (np.abs(e) < 0.05).sum(),
                 "front5": (e < -0.05).sum(), "behind5": (e > 0.05).sum()}
            for k in acc:
                acc[k] += float(v[k])
            flat = (patch_stats(_gray(scene.load_image(i)), 7)[1].sqrt()[0, 0].numpy() < 0.01)[cov]
            for part, m in (("flat", flat), ("textured", ~flat)):
                split[f"{part}_pixels"] += float(m.sum())
                for k, sel in (("w2", np.abs(e) < 0.02), ("w5", np.abs(e) < 0.05), ("front5", e < -0.05), ("behind5", e > 0.05)):
                    split[f"{part}_{k}"] += float((sel & m).sum())
            per_view.append({"image": c.name, "hole": float(v["hole"] / max(v["pixels"], 1)),
                             "within_5cm": float(v["w5"] / max(v["pixels"], 1))})
    n = max(acc["pixels"], 1.0)
    e = np.concatenate(errs) if errs else np.zeros(0)
    res = {"model": str(ply), "split": cfg.split, "views": len(per_view),
           "hole": acc["hole"] / n, "within_2cm": acc["w2"] / n, "within_5cm": acc["w5"] / n,
           "in_front_5cm": acc["front5"] / n, "behind_5cm": acc["behind5"] / n,
           "abs_err_median_m": float(np.median(e)) if e.size else None,
           "abs_err_p90_m": float(np.percentile(e, 90)) if e.size else None,
           "by_texture": {part: {"share_of_covered": split[f"{part}_pixels"] / max(n - acc["hole"], 1.0)}
                          | {k: split[f"{part}_{k}"] / max(split[f"{part}_pixels"], 1.0) for k in ("w2", "w5", "front5", "behind5")}
                          for part in ("flat", "textured")},
           "depth": cfg.depth,
           "worst_views": sorted(per_view, key=lambda r: r["within_5cm"])[:5]}
    print(json.dumps(res, indent=1))
    if cfg.json:
        cfg.json.write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main(tyro.cli(DepthDiag))
