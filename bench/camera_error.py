"""How far a run's training cameras are from the true ones, before and after camera refinement.

    python bench/camera_error.py RUN GT_SCENE [--json OUT]

RUN: a `splat train --pose-opt/--focal-opt` folder (its camera_refinement.npz and report.json, whose
scene holds the cameras the run started from); GT_SCENE: the same images with the true cameras
(e.g. outputs/icl_sfm for bench/perturb_scene.py's scenes). Prints and returns the median and 90th
percentile of the rotation error (degrees) and camera-centre error (cm) of the starting and the
refined cameras, and the focal factor against the true one. Not part of the tests.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geocues.scene import Scene  # noqa: E402


def camera_errors(run: Path, gt_scene: Path) -> dict:
    z = np.load(run / "camera_refinement.npz")
    start = {c.name: c for c in Scene.load(json.loads((run / "report.json").read_text())["scene"],
                                          check_priors=False).cameras}
    gt = {c.name: c for c in Scene.load(gt_scene, check_priors=False).cameras}

    def err(R, t, g):
        return (Rotation.from_matrix(R @ g.R.T).magnitude() * 180 / np.pi, 100 * np.linalg.norm(-R.T @ t - g.center))

    before, after = [], []
    for name, w, v in zip(z["names"], z["rot"], z["trans"]):
        c, g = start[str(name)], gt[str(name)]
        dR = Rotation.from_rotvec(w).as_matrix()
        before.append(err(c.R, c.t, g))
        after.append(err(dR @ c.R, dR @ c.t + v, g))
    c0 = next(iter(start.values()))
    g0 = gt[c0.name]
    true_factor = g0.K[0, 0] / c0.K[0, 0]

    def stats(e):
        e = np.asarray(e)
        return {"rotation_deg": {"median": float(np.median(e[:, 0])), "p90": float(np.percentile(e[:, 0], 90))},
                "centre_cm": {"median": float(np.median(e[:, 1])), "p90": float(np.percentile(e[:, 1], 90))}}

    return {"run": str(run), "views": len(before), "start": stats(before), "refined": stats(after),
            "focal_factor": float(z["focal_factor"]), "true_focal_factor": float(true_factor)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("gt_scene", type=Path)
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    out = camera_errors(a.run, a.gt_scene)
    print(json.dumps(out, indent=1))
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
