"""Accuracy of `geocues mvs` depth priors against exact GT depth (issue 12's weight-free depth).

    .venv/bin/python bench/mvs_accuracy.py MVS_SCENE GT_DEPTH_DIR [--png-scale 1000] [--json OUT]

MVS_SCENE is the folder `geocues mvs` wrote; GT_DEPTH_DIR holds <stem>.npy (metres) or <stem>.png
(``--png-scale`` units per metre, ICL: 1000). Prints and writes: the share of pixels with an MVS
depth, the relative error |d - gt| / gt (median, 90th and 99th percentiles, share within 1 %, 2 %,
5 %), over all views, with the run's seconds from mvs_report.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from geocues.scene import Scene
from splat.floor import load_gt_depth


def measure(mvs_scene: Path, gt_dir: Path, png_scale: float) -> dict:
    scene = Scene.load(mvs_scene, check_priors=False)
    errs, valid, gt_valid = [], [], []
    for i, cam in enumerate(scene.cameras):
        d = scene.depth_prior(i)
        gt = load_gt_depth(gt_dir, cam.stem, d.shape, png_scale)
        both = (d > 0) & (gt > 0)
        valid.append(float((d > 0).mean()))
        gt_valid.append(float(both.sum() / max((gt > 0).sum(), 1)))
        errs.append(np.abs(d[both] - gt[both]) / gt[both])
    e = np.concatenate(errs)
    report = json.loads((mvs_scene / "mvs_report.json").read_text())
    return {"scene": str(mvs_scene), "views": len(scene), "seconds": report["seconds"],
            "working_size": report["working_size"], "config": report["config"],
            "valid_fraction": float(np.mean(valid)), "gt_pixels_covered": float(np.mean(gt_valid)),
            "valid_before_consistency": report["valid_fraction"]["mean_before_consistency"],
            "rel_error": {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
                          "p99": float(np.percentile(e, 99)),
                          "within_1pct": float((e < 0.01).mean()), "within_2pct": float((e < 0.02).mean()),
                          "within_5pct": float((e < 0.05).mean())}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mvs_scene", type=Path)
    ap.add_argument("gt_depth", type=Path)
    ap.add_argument("--png-scale", type=float, default=1000.0)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    result = measure(a.mvs_scene, a.gt_depth, a.png_scale)
    print(json.dumps(result, indent=1))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
