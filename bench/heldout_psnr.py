"""Held-out PSNR of finished `splat train` runs with the test views' focal as given and with the run's
refined shared focal (RUN/camera_refinement.npz; what `splat train --focal-opt` now scores with).

    python bench/heldout_psnr.py RUN [RUN ...] [--json bench/results/NAME.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation.image_metrics import psnr  # noqa: E402
from splat.camera import Camera  # noqa: E402
from splat.camera_opt import load_refinement  # noqa: E402
from splat.render_run import load_run  # noqa: E402
from splat.train import TrainConfig, render_view  # noqa: E402
from splat.views import ViewSet  # noqa: E402


def heldout_psnr(run: Path) -> dict:
    scene, params, cfg = load_run(run)
    views = ViewSet(scene, scene.test_indices, "cpu", load_priors=False, desc="test views")
    npz = run / "camera_refinement.npz"
    focal = load_refinement(npz)[1] if npz.is_file() else 1.0
    tc = TrainConfig(sh_degree=cfg.get("sh_degree", 3), background=tuple(cfg.get("background", (0.0, 0.0, 0.0))))
    row = {"run": str(run), "focal_factor": focal}
    for key, f in (("psnr_given_focal", 1.0), ("psnr_refined_focal", focal)):
        vals = []
        for k in range(len(views)):
            v = views[k]
            K = v.camera.K.clone()
            K[0, 0] *= f
            K[1, 1] *= f
            cam = Camera(K=K, viewmat=v.camera.viewmat, width=v.camera.width, height=v.camera.height)
            with torch.no_grad():
                rgb = render_view(params, dataclasses.replace(v, camera=cam), tc.sh_degree, tc)["rgb"].clamp(0, 1)
            vals.append(psnr(rgb, v.rgb))
        row[key] = float(np.mean(vals))
    return row


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = [heldout_psnr(r) for r in args.runs]
    for r in rows:
        print(f"{r['run']}: focal x{r['focal_factor']:.4f}  given {r['psnr_given_focal']:.2f} dB  "
              f"refined {r['psnr_refined_focal']:.2f} dB")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
