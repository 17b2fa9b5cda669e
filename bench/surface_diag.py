"""Which surfaces of a benchmark room a mesh misses: recall and precision at 5 cm per surface.

The F-score of `evaluate` (the MonoSDF protocol: meshes culled to the training frusta, the
prediction cropped to the GT box plus 5 cm) is one number; this splits it. The GT room's triangles
are labelled by their material (`gt/triangle_material.npy`, names in scene.json) and the walls by
which side of the room they face (x min / x max / y min / y max, z up); a predicted sample is
labelled by its nearest GT sample. The samples and distances are `evaluate`'s own
(``evaluation.mesh_metrics.evaluate_with_scene``), so the rows add up to its figures. Per label: its share of the GT surface, recall (GT samples
within 5 cm of the mesh), mean completeness distance, its share of the prediction and precision.
Several meshes (a run's `checkpoints/mesh_*.ply`, the floor row's mesh) print side by side.

    python bench/surface_diag.py --scene outputs/rooms/bare_s2 --meshes OUT/rows/full_s0/train/mesh.ply \
        OUT/floor/mesh.ply [--json FILE]
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation.mesh_metrics import MeshMetricsConfig, evaluate_with_scene, load_mesh  # noqa: E402


@dataclass
class SurfaceDiag:
    scene: Path  # a benchmark room (evaluate make-room): gt/mesh.ply, gt/triangle_material.npy
    meshes: list[Path]  # predicted meshes, compared one by one
    json: Path | None = None  # write the table here too


def surface_labels(scene: Path, faces: np.ndarray, vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """[F] label per GT triangle: its material's name, walls split into wall_xmin / _xmax / _ymin / _ymax."""
    if not (scene / "gt" / "triangle_material.npy").is_file() or not (scene / "scene.json").is_file():
        raise FileNotFoundError(f"{scene} is not a benchmark room (`evaluate make-room`): it has no "
                                "scene.json with materials and gt/triangle_material.npy")
    names = [m["name"] for m in json.loads((scene / "scene.json").read_text())["room"]["materials"]]
    material = np.load(scene / "gt" / "triangle_material.npy")
    if material.shape != (len(faces),):
        raise SystemExit(f"{scene}/gt/triangle_material.npy has {material.shape} labels for {len(faces)} triangles")
    label = np.array(names, object)[material]
    centre = vertices[faces].mean(axis=1)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    for k, axis in enumerate("xy"):
        for side, bound in (("min", lo[k]), ("max", hi[k])):
            wall = (label == "walls") & (np.abs(normals[:, k]) > 0.9) & (np.abs(centre[:, k] - bound) < 0.05)
            label[wall] = f"wall_{axis}{side}"
    return label


def diagnose(scene: Path, mesh_path: Path, cfg: MeshMetricsConfig | None = None) -> dict:
    """Per label: gt_share, recall, completeness_cm, pred_share, precision (the protocol's samples,
    from ``evaluate``'s own evaluation of the mesh against the scene)."""
    cfg = cfg or MeshMetricsConfig()
    m = evaluate_with_scene(mesh_path, scene_dir=scene, cfg=cfg)
    gt = load_mesh(m.protocol["gt_mesh"])
    label = surface_labels(scene, gt.faces, gt.vertices, gt.face_normals)
    label_g, label_p = label[m.gt_face], label[m.gt_face_at_pred]
    d_pg, d_gp = m.dist_pred_to_gt, m.dist_gt_to_pred
    out = {}
    for name in sorted(set(label_g)):
        mg, mp = label_g == name, label_p == name
        out[name] = {"gt_share": round(float(mg.mean()), 4), "recall": round(float((d_gp[mg] < cfg.threshold).mean()), 4),
                     "completeness_cm": round(float(100 * d_gp[mg].mean()), 2),
                     "pred_share": round(float(mp.mean()), 4),
                     "precision": round(float((d_pg[mp] < cfg.threshold).mean()), 4) if mp.any() else None}
    out["all"] = {"gt_share": 1.0, "recall": round(float((d_gp < cfg.threshold).mean()), 4),
                  "completeness_cm": round(float(100 * d_gp.mean()), 2), "pred_share": 1.0,
                  "precision": round(float((d_pg < cfg.threshold).mean()), 4)}
    return out


def main(args: SurfaceDiag) -> None:
    try:
        results = {str(m): diagnose(args.scene, m) for m in args.meshes}
    except (FileNotFoundError, ValueError, KeyError) as e:  # a bad path or a scene that is no benchmark room
        raise SystemExit(f"surface_diag: error: {e}") from None
    for mesh, rows in results.items():
        print(f"\n{mesh}\n{'surface':12s} {'GT share':>8s} {'recall':>7s} {'comp cm':>8s} {'pred share':>10s} {'precision':>9s}")
        for name, r in rows.items():
            prec = "–" if r["precision"] is None else f"{r['precision']:.3f}"
            print(f"{name:12s} {r['gt_share']:8.3f} {r['recall']:7.3f} {r['completeness_cm']:8.1f} "
                  f"{r['pred_share']:10.3f} {prec:>9s}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scene": str(args.scene), "threshold_m": 0.05, "meshes": results}, indent=1))


if __name__ == "__main__":
    main(tyro.cli(SurfaceDiag))
