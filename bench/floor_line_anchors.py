"""Prototype measurement (issue 12): floor-contact lines as plane-stage anchors.

`bench/floor_lines_diag.py` showed that LSD segments lifted onto the floor plane from single views
find every wall foot of the benchmark rooms, where triangulated 3D lines find almost none. This
script measures what they do as anchors of the plane stage (the anchors that pin each image's
prior planes and the prior's alignment), without building them into `geocues extract` yet: it
takes the floor height from an earlier extraction's PLANE cues (``--cues``), keeps the lifted
segments that 4 other images lift onto the same floor line with one of them seeing it from 15
degrees away in azimuth (`floor_lines_diag.kept_segments`), samples them every 2 cm, and runs the
extraction again with those samples added to the line anchors (each with the views that lifted it).
The samples are anchors only: they are not written as cue points. It patches ``Anchors.build`` for
the length of that one run -- a measurement device; the real stage needs the floor before the plane
stage (a first plane pass or gravity from the cameras), see docs/training.md.

    python bench/floor_line_anchors.py --room outputs/rooms/bare_s0 --cues outputs/rooms/bare_s0_cues \
        --out outputs/rooms/bare_s0_cues_floorlines
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import geocues.extract as extract  # noqa: E402
from floor_lines_diag import floor_height, kept_segments, lift_segments  # noqa: E402
from geocues.anchors import Anchors  # noqa: E402
from geocues.scene import Scene  # noqa: E402


@dataclass
class FloorLineAnchors:
    room: Path
    """the scene folder."""
    cues: Path
    """an earlier `geocues extract` folder of it (its PLANE cues give the floor height)."""
    out: Path
    """the new cue folder."""
    step: float = 0.02
    """sample spacing along a kept segment (metres)."""


def anchor_samples(segs: list, keep: list[tuple[int, list[int]]], z0: float, step: float
                   ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """([P, 3] points every ``step`` along each kept segment at height z0, [P] its index, per
    segment the views that lifted it)."""
    pts, lid, views = [], [], []
    for a, others in keep:
        _, p, q, _ = segs[a]
        n = max(int(np.linalg.norm(q - p) / step), 2)
        f = np.linspace(0.0, 1.0, n)
        pts.append(np.c_[p[None] + f[:, None] * (q - p)[None], np.full(n, z0)])
        lid.append(np.full(n, len(views), np.int64))
        views.append(np.array(sorted(set(others) | {segs[a][0]}), np.int64))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64), []
    return np.concatenate(pts), np.concatenate(lid), views


def main(cfg: FloorLineAnchors) -> Path:
    scene = Scene.load(cfg.room)
    z0 = floor_height(cfg.cues)
    segs = lift_segments(scene, z0)
    keep = kept_segments(scene, segs, min_views=4, min_azimuth_deg=15.0)
    P, L, V = anchor_samples(segs, keep, z0, cfg.step)
    print(f"floor at z = {z0:.4f} m; {len(keep)} of {len(segs)} lifted segments kept; {len(P)} anchor samples")
    real = Anchors.build

    def build(sfm_xyz=None, sfm_views=None, line_points=None, line_of_point=None, line_views=None):
        lp = np.zeros((0, 3)) if line_points is None else np.asarray(line_points, np.float64).reshape(-1, 3)
        lo = np.zeros(0, np.int64) if line_of_point is None else np.asarray(line_of_point, np.int64)
        lv = [] if line_views is None else list(line_views)
        return real(sfm_xyz, sfm_views, np.concatenate([lp, P]), np.concatenate([lo, L + len(lv)]), lv + V)

    extract.Anchors.build = staticmethod(build)
    try:
        extract.run(extract.ExtractConfig(), cfg.room, cfg.out)
    finally:
        extract.Anchors.build = staticmethod(real)
    return cfg.out


if __name__ == "__main__":
    main(tyro.cli(FloorLineAnchors))
