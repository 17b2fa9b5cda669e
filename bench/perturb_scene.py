"""A scene with imperfect cameras: every pose moved by a rigid error, the focal scaled.

    python bench/perturb_scene.py SCENE OUT [--rot-deg 0.5] [--trans-cm 1 2] [--focal 0.95] [--seed 0]

Each image's world-to-camera pose gets a rotation of ``--rot-deg`` degrees about a random axis and a
translation of a length drawn uniformly from ``--trans-cm`` (two numbers: the range, cm) in a random
direction, both in its camera frame; every camera's fx and fy are multiplied by ``--focal``. OUT is a
scene folder (images and gt linked, sparse/0 written as COLMAP text without SfM points: run
`geocues sfm OUT` to triangulate with the wrong cameras, as a user's capture would be). The drawn
errors are in OUT/perturbation.json. For measuring camera refinement (TrainConfig.pose_opt,
focal_opt; issue 12). Not part of the tests.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geocues.colmap_io import find_model_dir, read_model, write_model  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--rot-deg", type=float, default=0.5)
    p.add_argument("--trans-cm", type=float, nargs=2, default=(1.0, 2.0))
    p.add_argument("--focal", type=float, default=0.95)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.out.exists():
        raise SystemExit(f"{a.out} exists")
    images, _ = read_model(find_model_dir(a.scene))
    rng = np.random.default_rng(a.seed)
    out_images, drawn = [], []
    for im in images:
        axis = rng.standard_normal(3)
        dR = Rotation.from_rotvec(np.radians(a.rot_deg) * axis / np.linalg.norm(axis)).as_matrix()
        d = rng.standard_normal(3)
        dt = rng.uniform(*a.trans_cm) / 100.0 * d / np.linalg.norm(d)
        K = im.K.copy()
        K[0, 0] *= a.focal
        K[1, 1] *= a.focal
        out_images.append(replace(im, K=K, R=dR @ im.R, t=dR @ im.t + dt))
        drawn.append({"name": im.name, "rot_deg": a.rot_deg, "trans_m": float(np.linalg.norm(dt))})
    a.out.mkdir(parents=True)
    for sub in ("images", "gt"):
        if (a.scene / sub).exists():
            (a.out / sub).symlink_to((a.scene / sub).resolve())
    write_model(a.out / "sparse" / "0", out_images)
    (a.out / "perturbation.json").write_text(json.dumps(
        {"source": str(a.scene), "rot_deg": a.rot_deg, "trans_cm": list(a.trans_cm), "focal": a.focal,
         "seed": a.seed, "images": drawn}, indent=1))
    print(f"wrote {a.out}: {len(out_images)} cameras, rotation {a.rot_deg} deg, translation "
          f"{np.mean([d['trans_m'] for d in drawn]) * 100:.2f} cm on average, focal x {a.focal}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
