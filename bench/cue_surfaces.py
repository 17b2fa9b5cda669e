"""Which surfaces of a benchmark room the cues reach: coverage per surface and cue type.

`evaluate cues` gives one coverage per cue type; this splits it by the GT surface (the labels of
bench/surface_diag.py: materials, walls by the side of the room they face). Per surface: its share
of the seen GT surface and, per cue type, the share of its seen GT samples within 5 cm of a cue
point; then, per surface, the PLANE cue points nearest it and the share of them farther than 3 cm.
The GT samples are `evaluate cues`' own (seen from the scene's cameras).

    python bench/cue_surfaces.py --scene outputs/rooms/bare_s5 --cues CUES [CUES ...] [--json FILE]
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from evaluation.cue_metrics import CueMetricsConfig, GroundTruth  # noqa: E402
from evaluation.mesh_metrics import load_mesh  # noqa: E402
from surface_diag import surface_labels  # noqa: E402


@dataclass
class CueSurfaces:
    scene: Path  # a benchmark room (evaluate make-room)
    cues: list[Path]  # cue folders of `geocues extract` (cues.ply)
    json: Path | None = None  # write the table here too


def surface_of(gt: GroundTruth, label: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[N] label of the GT triangle nearest each point."""
    import open3d as o3d

    if not len(points):
        return np.zeros(0, object)
    hit = gt.scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
    return label[hit["primitive_ids"].numpy()]


def diagnose(scene: Path, cues: Path, gt: GroundTruth, label: np.ndarray) -> dict:
    from scipy.spatial import cKDTree

    from geocues.cue_io import read_cues_ply
    from geocues.types import CueType

    cloud = read_cues_ply(cues / "cues.ply")
    at = surface_of(gt, label, gt.samples)
    plane = cloud.xyz[cloud.cue_type == int(CueType.PLANE)]
    off = gt.distances(plane) > 0.03
    near = surface_of(gt, label, plane)
    out = {}
    for name in sorted(set(at)):
        m = at == name
        row = {"gt_share": round(float(m.mean()), 4)}
        for t in CueType:
            pts = cloud.xyz[cloud.cue_type == int(t)]
            d = cKDTree(pts).query(gt.samples[m])[0] if len(pts) else np.full(int(m.sum()), np.inf)
            row[f"coverage_{t.name}"] = round(float(np.mean(d <= 0.05)), 4)
        k = near == name
        row["plane_points"] = int(k.sum())
        row["plane_beyond_3cm"] = round(float(off[k].mean()), 4) if k.any() else None
        out[name] = row
    return out


def main(args: CueSurfaces) -> None:
    from geocues.scene import Scene

    try:
        sc = Scene.load(args.scene, check_priors=False)
        gt = GroundTruth(args.scene / "gt" / "mesh.ply", sc.cameras, CueMetricsConfig())
        mesh = load_mesh(args.scene / "gt" / "mesh.ply")
        label = surface_labels(args.scene, mesh.faces, mesh.vertices, mesh.face_normals)
        results = {str(c): diagnose(args.scene, c, gt, label) for c in args.cues}
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise SystemExit(f"cue_surfaces: error: {e}") from None
    for cues, rows in results.items():
        print(f"\n{cues}\n{'surface':12s} {'GT share':>8s} {'SFM':>6s} {'LINE':>6s} {'PLANE':>6s} "
              f"{'PLANE pts':>9s} {'>3 cm':>6s}")
        for name, r in rows.items():
            far = "–" if r["plane_beyond_3cm"] is None else f"{r['plane_beyond_3cm']:.3f}"
            print(f"{name:12s} {r['gt_share']:8.3f} {r['coverage_SFM']:6.2f} {r['coverage_LINE']:6.2f} "
                  f"{r['coverage_PLANE']:6.2f} {r['plane_points']:9d} {far:>6s}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scene": str(args.scene), "coverage_dist_m": 0.05, "cues": results},
                                        indent=1))


if __name__ == "__main__":
    main(tyro.cli(CueSurfaces))
