"""The camera-refinement measurement on ICL with wrong cameras (docs/training.md): runs with and
without --pose-opt --focal-opt per perturbation seed, their mesh scores and camera errors.

    python bench/camera_opt_table.py GT_SCENE RUN_NOPOSE_S0 RUN_POSE_S0 [RUN_NOPOSE_S1 RUN_POSE_S1 ...]

Each RUN holds report.json and eval.json (`evaluate RUN/mesh.ply GT_SCENE --gt ... -o RUN/eval.json`);
a refining run also camera_refinement.npz. Writes bench/results/icl_camera_opt.json and prints the
markdown table. Not part of the tests.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from camera_error import camera_errors  # noqa: E402

from splat.train_config import TrainConfig  # noqa: E402

DEFAULT_POSE_LR = TrainConfig().pose_lr


def row(run: Path, gt_scene: Path) -> dict:
    rep = json.loads((run / "report.json").read_text())
    ev = json.loads((run / "eval.json").read_text())
    c = rep["config"]
    refine = " + ".join(n for n, on in (("pose", c.get("pose_opt")), ("focal", c.get("focal_opt"))) if on) or "none"
    if c.get("pose_opt") and c.get("pose_lr", DEFAULT_POSE_LR) != DEFAULT_POSE_LR:
        refine += f" (pose lr {c['pose_lr']:g})"
    out = {"run": str(run), "scene": rep["scene"], "refine": refine,
           "train_s": rep["timings"]["train_s"], "test_psnr": rep["test_metrics"]["psnr"],
           **{k: ev[k] for k in ("accuracy", "completeness", "chamfer_l1", "f_score", "normal_consistency")}}
    if (run / "camera_refinement.npz").is_file():
        out["cameras"] = camera_errors(run, gt_scene)
        z = np.load(run / "camera_refinement.npz")
        if "from_checkpoint_step" in z:
            out["cameras"]["note"] = (f"corrections of the run's last checkpoint (step {int(z['from_checkpoint_step'])}): "
                                      "the run predates camera_refinement.npz")
    return out


def main(argv: list[str]) -> int:
    gt, runs = Path(argv[0]), [Path(a) for a in argv[1:]]
    rows = [row(r, gt) for r in runs]
    Path(REPO / "bench/results/icl_camera_opt.json").write_text(json.dumps({"gt_scene": str(gt), "rows": rows}, indent=1))
    print("| cameras | refinement | C-L1 cm | F@5cm | NC | rotation error ° (start → refined) | centre error cm | focal factor (true) | training s |")
    print("|---|---|---:|---:|---:|---|---|---|---:|")
    for r in rows:
        c = r.get("cameras")
        cam = ("–", "–", "–") if c is None else (
            f"{c['start']['rotation_deg']['median']:.2f} → {c['refined']['rotation_deg']['median']:.2f}",
            f"{c['start']['centre_cm']['median']:.2f} → {c['refined']['centre_cm']['median']:.2f}",
            f"{c['focal_factor']:.3f} ({c['true_focal_factor']:.3f})")
        print(f"| {Path(r['scene']).name} | {r['refine']} | {100 * r['chamfer_l1']:.2f} | "
              f"{r['f_score']:.3f} | {r['normal_consistency']:.3f} | {cam[0]} | {cam[1]} | {cam[2]} | {r['train_s']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
