"""Diagnostic (issue 12): do wall-floor junctions, lifted from single views onto the floor plane, pin
the walls of a benchmark room where the triangulated 3D lines do not reach?

On the bare rooms the far walls are placed by the aligned prior alone (docs/training.md, "Where the
bare rooms lose"): the views that see them stand 3.4-5 m away and move along their viewing
direction, so their lines triangulate badly. A segment at a wall's foot, though, lies on the floor,
whose plane the plane cues give to a millimetre: intersecting its two end rays with that plane puts it
in 3D from one view. This measures that with the lifting and keep test of `geocues extract
--floor.lines` (geocues.floor_lines) on every raw LSD segment and a level floor: the floor height is the
median of the lowest 30 % of the horizontal PLANE cues (the rooms are z-up); every LSD segment of
every image (geocues.lines.detect.detect_gray, the extraction's own settings) whose end rays meet the
floor within 8 m and 20 cm apart is lifted; a lifted segment is kept when at least ``--min-views``
other images lift one within 2 degrees and 3 cm of its line; each kept one is scored by its larger
end distance to the nearest wall foot of the GT box (x = min/max, y = min/max of the GT mesh). For
contrast, the extraction's triangulated 3D lines (CUES/lines3d.npz) along each wall's foot are counted.
Segments at objects' feet (boxes, cabinets) and lines of a textured floor are on the floor too but
count as "not at a wall"; whether a kept segment truly lies on the floor is checked against the exact
depth of its own view (``kept_truly_on_the_floor``).

    python bench/floor_lines_diag.py --room outputs/rooms/bare_s0 --cues outputs/rooms/bare_s0_cues --name bare_s0

Writes bench/results/floor_lines_NAME.json.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import tyro

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geocues.cue_io import read_cues_ply  # noqa: E402
from geocues.floor import Floor  # noqa: E402
from geocues.floor_lines import FloorLineConfig, depth_along, kept_segments, lift_segments  # noqa: E402
from geocues.lines.config import LineConfig  # noqa: E402
from geocues.lines.detect import detect_gray  # noqa: E402
from geocues.scene import Scene  # noqa: E402
from geocues.types import CueType  # noqa: E402


@dataclass
class FloorLines:
    room: Path
    """a benchmark room (`evaluate make-room`; z-up, walls on its GT mesh's bounding box)."""
    cues: Path
    """its `geocues extract` folder."""
    name: str
    """result name: bench/results/floor_lines_NAME.json."""
    min_views: int = 4
    """a lifted segment is kept when this many other images lift one onto the same floor line."""
    min_azimuth_deg: float = 0.0
    """... and one of them sees the segment's midpoint from a horizontal direction at least this far
    (degrees) from its own view's: a horizontal line above the floor, seen by views that move along
    their viewing direction, lifts onto the same floor line from all of them (0 = no such test)."""


def floor_height(cues: Path) -> float:
    """Median height of the lowest 30 % of the horizontal PLANE cues."""
    c = read_cues_ply(cues / "cues.ply")
    z = c.xyz[(c.cue_type == CueType.PLANE) & (np.abs(c.normal[:, 2]) > 0.95), 2]
    if len(z) == 0:
        raise ValueError(f"{cues} has no horizontal PLANE cues to give the floor")
    return float(np.median(z[z <= np.percentile(z, 30)]))


def lifted_and_kept(scene: Scene, z0: float, min_views: int, min_azimuth_deg: float):
    """(the raw LSD segments of every image, geocues.floor_lines.Lifted on z = z0, the kept ones'
    indices into it): the option's lifting and keep test (`geocues extract --floor.lines`) on every
    segment LSD finds, with the floor known to be level."""
    cfg = FloorLineConfig(min_views=min_views, min_azimuth_deg=min_azimuth_deg)
    segments = [detect_gray(cv2.cvtColor((np.clip(scene.load_image(i), 0, 1) * 255).astype(np.uint8),
                                         cv2.COLOR_RGB2GRAY), LineConfig()) for i in range(len(scene.cameras))]
    floor = Floor(np.array([0.0, 0.0, 1.0]), z0, 0)
    lifted = lift_segments(scene.cameras, segments, floor, cfg)
    centres = np.array([c.center for c in scene.cameras]) @ floor.basis().T
    return segments, lifted, [a for a, _ in kept_segments(lifted, centres, cfg)]


def on_the_floor(cam, gt: np.ndarray, z0: float, seg: np.ndarray) -> bool:
    """Whether the GT depth ``gt`` of the segment's own view ``cam`` agrees, within 3 cm, with the
    ray's depth to the floor on 4 of 5 points along it (a segment that is not on the floor, lifted
    onto it, does not)."""
    z, g = depth_along(cam, seg, Floor(np.array([0.0, 0.0, 1.0]), z0, 0), gt)
    return int((np.abs(g - z) < 0.03).sum()) >= 4


def main(cfg: FloorLines) -> dict:
    import open3d as o3d

    scene = Scene.load(cfg.room)
    z0 = floor_height(cfg.cues)
    segments, lifted, keep = lifted_and_kept(scene, z0, cfg.min_views, cfg.min_azimuth_deg)
    gt = o3d.io.read_triangle_mesh(str(cfg.room / "gt" / "mesh.ply"))
    lo, hi = gt.get_min_bound(), gt.get_max_bound()
    walls = {f"x={lo[0]:.2f}": (0, lo[0]), f"x={hi[0]:.2f}": (0, hi[0]),
             f"y={lo[1]:.2f}": (1, lo[1]), f"y={hi[1]:.2f}": (1, hi[1])}
    dist, per_wall = [], {w: 0 for w in walls}
    for a in keep:
        p, q = lifted.ends[a][:, :2]
        name, (ax, val) = min(walls.items(), key=lambda kv: abs(p[kv[1][0]] - kv[1][1]) + abs(q[kv[1][0]] - kv[1][1]))
        d = max(abs(p[ax] - val), abs(q[ax] - val))
        dist.append(d)
        per_wall[name] += int(d < 0.05)
    dist = np.array(dist)
    gt_depth = {}  # view -> its exact depth, read once
    on_floor = []
    for a in keep:
        v = int(lifted.view[a])
        if v not in gt_depth:
            gt_depth[v] = np.load(cfg.room / "gt" / "depth" / f"{scene.cameras[v].stem}.npy")
        on_floor.append(on_the_floor(scene.cameras[v], gt_depth[v], z0, segments[v][lifted.seg[a]]))
    triangulated = {w: 0 for w in walls}  # the extraction's 3D lines along each wall's foot, for contrast
    lines = cfg.cues / "lines3d.npz"
    for a, b in (np.load(lines)["segments"] if lines.is_file() else []):
        for name, (ax, val) in walls.items():
            if max(abs(a[2] - z0), abs(b[2] - z0), abs(a[ax] - val), abs(b[ax] - val)) < 0.05:
                triangulated[name] += 1
    res = {"room": str(cfg.room), "cues": str(cfg.cues), "images": len(scene.cameras),
           "floor_z_from_cues": z0, "lifted": len(lifted), "min_views": cfg.min_views, "min_azimuth_deg": cfg.min_azimuth_deg, "kept": len(dist),
           "within_2cm_of_a_wall_foot": float(np.mean(dist < 0.02)) if len(dist) else None,
           "within_5cm_of_a_wall_foot": float(np.mean(dist < 0.05)) if len(dist) else None,
           "kept_truly_on_the_floor": float(np.mean(on_floor)) if on_floor else None,
           "kept_within_5cm_per_wall": per_wall, "triangulated_3d_lines_per_wall_foot": triangulated}
    print(json.dumps(res, indent=1))
    path = REPO / "bench" / "results" / f"floor_lines_{cfg.name}.json"
    path.write_text(json.dumps(res, indent=1))
    print(f"wrote {path}")
    return res


if __name__ == "__main__":
    main(tyro.cli(FloorLines))
