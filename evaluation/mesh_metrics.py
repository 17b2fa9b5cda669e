"""Mesh metrics by the MonoSDF / GO-Surf protocol: accuracy, completeness, Chamfer-L1, F-score, NC.

Protocol (MonoSDF ``replica_eval/eval_recon.py``, GO-Surf ``tools/mesh_metrics.py``):

1. optionally keep only the surface the GT cameras saw (view frusta, optionally an occlusion
   test; ``evaluation.culling``) -- for the predicted mesh and, by default, for the GT mesh;
2. crop the predicted surface to the GT mesh's bounding box (plus a margin);
3. sample points uniformly on both surfaces (MonoSDF: 200k each), with the normal of the triangle
   each point lies on;
4. measure each sample's distance to the other surface and average (equations below).

Steps 1-2 are applied to the samples, by rejection: points are drawn uniformly on the whole mesh
and those outside the kept region are discarded until ``n_samples`` remain, so the kept samples are
uniform on the kept part of the surface whatever the tessellation.

Distances: ``mode="point"`` (the protocol; what published numbers use) takes the nearest *sample*
of the other surface (an exact KD-tree search). This overestimates the true distance by a sampling bias of a
few millimetres at 200k samples per room. ``mode="surface"`` takes the exact distance to the other
mesh's triangles (Open3D ``RaycastingScene.compute_closest_points``); the target is then the whole
other mesh (culling and cropping choose which points are *measured*, not what they are measured
against). The output's ``protocol`` object records which was used.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

from evaluation.culling import CameraSet, bounds_mask, raycasting_scene, visible_mask
from evaluation.surfaces import (TriMesh, load_mesh, nearest_sample_distances, sample_kept_surface,  # noqa: F401
                                 sample_surface, surface_distances, surface_near_box)
from geocues.atomic import atomic_path

log = logging.getLogger(__name__)

METRIC_KEYS = ("accuracy", "completeness", "chamfer_l1", "precision", "recall", "f_score",
               "normal_consistency")


@dataclass
class MeshMetricsConfig:
    """Mesh metrics by the MonoSDF / GO-Surf protocol."""

    n_samples: int = 200_000
    """points sampled on each surface after culling and cropping (MonoSDF: 200k)."""
    threshold: float = 0.05
    """distance threshold (metres) of precision, recall and F-score (a distance counts if < it)."""
    mode: Literal["point", "surface"] = "point"
    """point: to the nearest sample of the other surface (the protocol); surface: exact distance to the other mesh's triangles."""
    cull_to_frusta: bool = True
    """when cameras are given (SCENE): keep only surface inside at least one camera's view frustum."""
    occlusion: Literal["none", "gt", "self"] = "none"
    """occlusion test with cameras: none; gt: a point must not lie behind the GT mesh as seen from the camera; self: not behind its own mesh (GO-Surf)."""
    occlusion_tolerance: float = 0.02
    """how far (metres, along the viewing ray) a point may lie behind the occluding surface and still count as seen."""
    cull_gt: bool = True
    """with cameras: cull the GT surface too, so completeness only asks for what the cameras saw."""
    max_cameras: int = 0
    """use at most this many cameras for culling, evenly spread (0 = all)."""
    crop_to_gt_bounds: bool = True
    """drop predicted surface outside the GT mesh's axis-aligned bounding box (plus the margin)."""
    crop_margin: float = 0.05
    """margin (metres) added to the GT bounding box on every side before cropping."""
    seed: int = 0
    """seed of the surface sampling."""

    def validate(self) -> None:
        """Raise ValueError on an impossible setting."""
        if self.n_samples <= 0:
            raise ValueError(f"n_samples must be positive, got {self.n_samples}")
        if not 0 < self.threshold < math.inf:  # nan: every F-score 0; inf: every one 1
            raise ValueError(f"threshold must be a positive number of metres, got {self.threshold}")
        if self.mode not in ("point", "surface"):
            raise ValueError(f"mode must be 'point' or 'surface', got {self.mode!r}")
        if self.occlusion not in ("none", "gt", "self"):
            raise ValueError(f"occlusion must be 'none', 'gt' or 'self', got {self.occlusion!r}")
        for name in ("occlusion_tolerance", "crop_margin", "max_cameras"):
            if not 0 <= getattr(self, name) < math.inf:  # a nan margin cropped everything away
                raise ValueError(f"{name} must be >= 0 and finite, got {getattr(self, name)}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")


def accuracy(dist_pred_to_gt: np.ndarray) -> float:
    """Accuracy = mean over predicted samples p of d(p, GT)   (MonoSDF / GO-Surf)."""
    return float(np.mean(dist_pred_to_gt))


def completeness(dist_gt_to_pred: np.ndarray) -> float:
    """Completeness = mean over GT samples g of d(g, Pred)   (MonoSDF / GO-Surf)."""
    return float(np.mean(dist_gt_to_pred))


def chamfer_l1(acc: float, comp: float) -> float:
    """Chamfer-L1 = (Accuracy + Completeness) / 2. (Open3D's ChamferDistance is their sum.)"""
    return 0.5 * (acc + comp)


def precision_recall_fscore(dist_pred_to_gt: np.ndarray, dist_gt_to_pred: np.ndarray,
                            threshold: float) -> tuple[float, float, float]:
    """Precision = mean[d(p, GT) < tau], Recall = mean[d(g, Pred) < tau], F = 2PR / (P + R).

    Fractions in [0, 1]; F = 0 when P + R = 0 (strict '<' as MonoSDF and Open3D).
    """
    p = float(np.mean(dist_pred_to_gt < threshold))
    r = float(np.mean(dist_gt_to_pred < threshold))
    f = 2.0 * p * r / (p + r) if p + r > 0 else 0.0
    return p, r, f


def normal_consistency(n_pred: np.ndarray, n_gt_at_pred: np.ndarray, n_gt: np.ndarray,
                       n_pred_at_gt: np.ndarray) -> float:
    """NC = ( mean_p |n_p . n_GT(nn(p))| + mean_g |n_g . n_Pred(nn(g))| ) / 2   (orientation-free)."""
    nc_acc = np.abs(np.sum(n_pred * n_gt_at_pred, axis=1)).mean()
    nc_comp = np.abs(np.sum(n_gt * n_pred_at_gt, axis=1)).mean()
    return float(0.5 * (nc_acc + nc_comp))


@dataclass
class MeshMetrics:
    """Result of a mesh evaluation: metres for distances, fractions in [0, 1] for the rest."""

    accuracy: float
    completeness: float
    chamfer_l1: float
    precision: float
    recall: float
    f_score: float
    normal_consistency: float
    protocol: dict[str, Any] = field(default_factory=dict)
    dist_pred_to_gt: np.ndarray | None = field(default=None, repr=False)  # [N] per predicted sample
    dist_gt_to_pred: np.ndarray | None = field(default=None, repr=False)  # [M] per GT sample
    gt_face: np.ndarray | None = field(default=None, repr=False)  # [M] GT triangle of each GT sample
    gt_face_at_pred: np.ndarray | None = field(default=None, repr=False)  # [N] GT triangle nearest each predicted one

    def to_dict(self) -> dict[str, Any]:
        """The JSON form: the seven metric keys plus the ``protocol`` object."""
        out: dict[str, Any] = {k: float(getattr(self, k)) for k in METRIC_KEYS}
        out["protocol"] = dict(self.protocol)
        return out


FRAME_INSIDE_MIN = 0.5
"""frame check: least share of the predicted surface inside the GT mesh's bounds (plus the crop margin)."""
FRAME_SIZE_MAX = 3.0
"""frame check: most the predicted surface may span (robust diagonal) over the GT's."""
FRAME_SIZE_MIN = 1 / 30
"""frame check: least the predicted surface may span over the GT's (a GT in millimetres: 0.001)."""
SEEN_MIN = 0.3
"""least share of the predicted surface the scene's cameras see (inside the GT's box) before a warning:
the demo's trained mesh with its own scene's: 99.5 %; with ICL's cameras: 8 %."""
GT_SPAN_M = (0.3, 300.0)
"""unit check: the GT surface's robust diagonal, in metres, of a scene the metrics are made for
(the F-score's threshold is in metres: a GT in millimetres spans thousands)."""


UNITS = {1000.0: "millimetres", 100.0: "centimetres", 39.37: "inches", 3.281: "feet"}
"""Units a mesh may be written in against a GT in metres, by their size ratio."""


def _unit_hint(ratio: float) -> str:
    """" (about 1000x: millimetres?)" when the size ratio is within 15 % of a unit's, else ""."""
    unit = next((name for f, name in UNITS.items() if abs(ratio / f - 1) < 0.15), None)
    return f" (about {ratio:.0f}x: {unit}?)" if unit and ratio >= 10 else f" (about {ratio:.2g}x: {unit}?)" if unit else ""


def frame_mismatch(pred: TriMesh, gt: TriMesh, margin: float = 0.05, n: int = 20_000) -> str | None:
    """A warning when ``pred`` may not be in ``gt``'s frame and unit, else None.

    Culling and cropping would otherwise score such a mesh without a word (an images-only
    reconstruction, 6 units per metre and its own origin, scored 34 cm / F 0.13 against ICL's GT).
    Two whole-surface figures on ``n`` samples of each mesh (an own generator: the metrics' samples
    are not touched): the share of the predicted surface inside the GT's bounds plus ``margin``
    (< ``FRAME_INSIDE_MIN``: another origin or axes) and the ratio of the two surfaces' robust
    diagonals (2nd-98th percentile box; > ``FRAME_SIZE_MAX`` or < ``FRAME_SIZE_MIN``: another unit),
    and the GT's own diagonal (outside ``GT_SPAN_M``: not in metres). A mesh of a part of the
    GT (one room of a house) passes both; one in a smaller unit inside the GT's box, or in the right unit
    but another frame that overlaps the GT's box (an images-only ICL model at the exact scale: 54 %
    inside), cannot be told: the scene's mark (`geocues sfm --mode map`) is the other check. A mesh
    spraying far outside the room would also be named (a bare room's `no-cues` meshes, C-L1 45 cm:
    62-77 % inside), hence the sentence states what was measured.
    """
    rng = np.random.default_rng(0)
    p, _ = sample_surface(pred, n, rng)
    g, _ = sample_surface(gt, n, rng)
    lower, upper = gt.bounds
    inside = float(bounds_mask(p, lower, upper, margin).mean())

    def diagonal(x: np.ndarray) -> float:
        return float(np.linalg.norm(np.percentile(x, 98, axis=0) - np.percentile(x, 2, axis=0)))

    gt_span = diagonal(g)
    ratio = diagonal(p) / max(gt_span, 1e-12)
    said = []
    if not GT_SPAN_M[0] <= gt_span <= GT_SPAN_M[1]:
        said.append(f"the GT mesh {gt.name} spans {gt_span:.3g} units across: the metrics take metres (a GT in "
                    f"millimetres or centimetres must be scaled to metres first, or every distance and the "
                    f"F-score's threshold are in its unit)")
    if ratio < FRAME_SIZE_MIN:
        said.append(f"{pred.name} spans {ratio:.2g} times the GT's size: are both in metres?")
    if inside < FRAME_INSIDE_MIN or ratio > FRAME_SIZE_MAX:
        said.append(f"{100 * (1 - inside):.0f} % of {pred.name} lies outside the bounds of the GT mesh {gt.name} "
                    f"(cropped away: the figures score the rest) and it spans {ratio:.2g} times the GT's size"
                    f"{_unit_hint(ratio)}: a far background or floaters, or a mesh in its own frame or unit? One "
                    "in its own frame (geocues sfm from images alone) is scored with `evaluate PRED_MESH SCENE "
                    "--align-to GT_SCENE`; one in another unit is scaled to metres first")
    return "; ".join(said) or None


def _culling_name(cams: CameraSet | None, cfg: MeshMetricsConfig) -> str:
    if cams is None:
        return "none"
    return "frusta" if cfg.occlusion == "none" else f"frusta+occlusion({cfg.occlusion})"


def evaluate_meshes(pred: TriMesh, gt: TriMesh, cfg: MeshMetricsConfig | None = None,
                    cameras: Sequence[Any] | CameraSet | None = None) -> MeshMetrics:
    """Compare a predicted mesh with the ground truth (see the module docstring for the protocol).

    cameras: objects with ``K, R, t, width, height`` (``geocues.scene.Camera``) or a ``CameraSet``;
    used for culling when ``cfg.cull_to_frusta``. Without cameras nothing is culled.
    """
    cfg = cfg or MeshMetricsConfig()
    cfg.validate()
    pred, gt = TriMesh.of(pred, "pred"), TriMesh.of(gt, "gt")
    cams = None
    if cameras is not None and cfg.cull_to_frusta:
        cams = cameras if isinstance(cameras, CameraSet) else CameraSet.from_cameras(cameras, cfg.max_cameras)
    elif cfg.occlusion != "none":
        raise ValueError(f"occlusion={cfg.occlusion!r} needs cameras (pass SCENE) and cull_to_frusta")
    log.info("mesh metrics: %s vs %s, mode=%s, n_samples=%d, culling=%s",
             pred.name, gt.name, cfg.mode, cfg.n_samples, _culling_name(cams, cfg))
    frame_warning = frame_mismatch(pred, gt, cfg.crop_margin)  # logged once the crop left something to score

    need_gt_scene = cfg.mode == "surface" or (cams is not None and cfg.occlusion != "none")
    gt_scene = raycasting_scene(gt.vertices, gt.faces) if need_gt_scene else None
    need_pred_scene = cfg.mode == "surface" or (cams is not None and cfg.occlusion == "self")
    pred_scene = raycasting_scene(pred.vertices, pred.faces) if need_pred_scene else None

    def visibility(own_scene):
        if cams is None:
            return None
        occluder = {"none": None, "gt": gt_scene, "self": own_scene}[cfg.occlusion]
        return lambda p: visible_mask(p, cams, occluder, cfg.occlusion_tolerance)

    lower, upper = gt.bounds
    pred_vis = visibility(pred_scene)

    def pred_keep(p: np.ndarray) -> np.ndarray:
        mask = bounds_mask(p, lower, upper, cfg.crop_margin) if cfg.crop_to_gt_bounds else np.ones(len(p), bool)
        if pred_vis is not None:
            mask[mask] = pred_vis(p[mask])
        return mask

    use_pred_keep = cfg.crop_to_gt_bounds or pred_vis is not None
    gt_keep = visibility(gt_scene) if cfg.cull_gt else None

    rng_pred, rng_gt = (np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(2))
    near = surface_near_box(pred, lower, upper, cfg.crop_margin) if cfg.crop_to_gt_bounds else None
    try:
        if near is None:
            p_pts, p_face, p_frac = sample_kept_surface(pred, cfg.n_samples, rng_pred,
                                                        pred_keep if use_pred_keep else None)
        else:  # far surfaces (a background shell, a floater km away, a ground plane's far part) not drawn
            part, index = near
            p_pts, p_face, p_frac = sample_kept_surface(part, cfg.n_samples, rng_pred, pred_keep)
            p_face, p_frac = index[p_face], p_frac * float(part.areas.sum() / pred.areas.sum())
    except ValueError as exc:
        raise ValueError(f"{exc}; {frame_warning}" if frame_warning else str(exc)) from None
    if frame_warning is not None:
        log.warning("%s", frame_warning)
    g_pts, g_face, g_frac = sample_kept_surface(gt, cfg.n_samples, rng_gt, gt_keep)
    n_pred, n_gt = pred.face_normals[p_face], gt.face_normals[g_face]  # [N, 3], [M, 3]

    if cfg.mode == "point":
        d_pg, idx_pg = nearest_sample_distances(p_pts, g_pts)
        d_gp, idx_gp = nearest_sample_distances(g_pts, p_pts)
        n_gt_at_pred, n_pred_at_gt = n_gt[idx_pg], n_pred[idx_gp]
        gt_face_at_pred = g_face[idx_pg]
    else:
        d_pg, face_pg = surface_distances(p_pts, gt_scene)
        d_gp, face_gp = surface_distances(g_pts, pred_scene)
        n_gt_at_pred, n_pred_at_gt = gt.face_normals[face_pg], pred.face_normals[face_gp]
        gt_face_at_pred = face_pg

    acc, comp = accuracy(d_pg), completeness(d_gp)
    prec, rec, fs = precision_recall_fscore(d_pg, d_gp, cfg.threshold)
    seen_warning = None
    if cams is not None and p_frac < SEEN_MIN and frame_warning is None:
        seen_warning = (f"only {100 * p_frac:.0f} % of {pred.name} is seen by the {len(cams)} cameras (culling "
                        f"{_culling_name(cams, cfg)}, inside the GT's box): the figures score that part alone; is "
                        "SCENE the scene the mesh was made from?")
        log.warning("%s", seen_warning)
    protocol = {
        "name": "MonoSDF/GO-Surf",
        "distance": "point-to-point (nearest sample)" if cfg.mode == "point" else "point-to-surface (exact)",
        "mode": cfg.mode,
        "n_samples": cfg.n_samples,
        "n_pred_samples": int(len(p_pts)),
        "n_gt_samples": int(len(g_pts)),
        "threshold": cfg.threshold,
        "culling": _culling_name(cams, cfg),
        "n_cameras": 0 if cams is None else len(cams),
        "cull_gt": bool(cams is not None and cfg.cull_gt),
        "occlusion_tolerance": cfg.occlusion_tolerance if cams is not None and cfg.occlusion != "none" else None,
        "crop_to_gt_bounds": cfg.crop_to_gt_bounds,
        "crop_margin": cfg.crop_margin if cfg.crop_to_gt_bounds else None,
        "pred_kept_area_fraction": float(f"{p_frac:.6g}"),  # 6 digits: a far plane leaves ~1e-7
        "gt_kept_area_fraction": float(f"{g_frac:.6g}"),
        "seed": cfg.seed,
        "frame_warning": frame_warning,
        "seen_warning": seen_warning,
        "units": "metres; precision, recall, f_score, normal_consistency are fractions in [0, 1]",
    }
    return MeshMetrics(
        accuracy=acc, completeness=comp, chamfer_l1=chamfer_l1(acc, comp), precision=prec,
        recall=rec, f_score=fs,
        normal_consistency=normal_consistency(n_pred, n_gt_at_pred, n_gt, n_pred_at_gt),
        protocol=protocol, dist_pred_to_gt=d_pg, dist_gt_to_pred=d_gp, gt_face=g_face,
        gt_face_at_pred=gt_face_at_pred,
    )


def evaluate_mesh_files(pred_path: str | Path, gt_path: str | Path, cfg: MeshMetricsConfig | None = None,
                        cameras: Sequence[Any] | CameraSet | None = None) -> MeshMetrics:
    """Load both meshes (errors name the bad path) and run ``evaluate_meshes``."""
    pred, gt = load_mesh(pred_path), load_mesh(gt_path)
    result = evaluate_meshes(pred, gt, cfg, cameras)
    result.protocol["pred_mesh"] = str(pred_path)
    result.protocol["gt_mesh"] = str(gt_path)
    return result


def scene_cameras_and_gt(scene_dir: str | Path) -> tuple[list[Any], Path | None]:
    """All cameras (train and test) of a scene folder and its ``gt/mesh.ply`` if present."""
    from geocues.scene import Scene  # lazy: geocues is only needed with a scene

    scene = Scene.load(scene_dir, check_priors=False)
    return list(scene.cameras), scene.gt_mesh_path


def evaluate_with_scene(pred_path: str | Path, gt_path: str | Path | None = None,
                        scene_dir: str | Path | None = None,
                        cfg: MeshMetricsConfig | None = None) -> MeshMetrics:
    """The ``evaluate`` command's work: GT from ``gt_path`` or the scene's ``gt/mesh.ply``; with a
    scene, its cameras cull both surfaces (``cfg.cull_to_frusta``)."""
    if not Path(pred_path).is_file():  # the input named first is checked first
        raise FileNotFoundError(f"no mesh at {pred_path}" + (" (a folder)" if Path(pred_path).is_dir() else ""))
    cameras, scene_gt = scene_cameras_and_gt(scene_dir) if scene_dir is not None else (None, None)
    gt_path = gt_path if gt_path is not None else scene_gt
    if gt_path is None:
        raise ValueError("no GT mesh: pass --gt GT_MESH"
                         + (f" (the scene {scene_dir} has no gt/mesh.ply)" if scene_dir else ""))
    result = evaluate_mesh_files(pred_path, gt_path, cfg, cameras)
    if scene_dir is not None:
        result.protocol["scene"] = str(scene_dir)
    return result


def save_json(metrics: MeshMetrics, path: str | Path, extra: dict | None = None) -> Path:
    """Write ``metrics.to_dict()`` (and the keys of ``extra``) as JSON atomically (temp file, then rename)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(metrics.to_dict() | (extra or {}), indent=2) + "\n")
    return Path(path)


def format_table(metrics: MeshMetrics) -> str:
    """A plain-text table of the metrics and the protocol used (for the CLI)."""
    rows = [
        ("accuracy", f"{metrics.accuracy:.4f} m"),
        ("completeness", f"{metrics.completeness:.4f} m"),
        ("chamfer_l1", f"{metrics.chamfer_l1:.4f} m"),
        ("precision", f"{metrics.precision:.4f}"),
        ("recall", f"{metrics.recall:.4f}"),
        ("f_score", f"{metrics.f_score:.4f}"),
        ("normal_consistency", f"{metrics.normal_consistency:.4f}"),
    ]
    p = metrics.protocol
    note = (f"distance: {p.get('distance')}; threshold {p.get('threshold')} m; "
            f"{p.get('n_pred_samples')} pred / {p.get('n_gt_samples')} GT samples; "
            f"culling: {p.get('culling')} ({p.get('n_cameras')} cameras); "
            f"crop to GT bounds: {p.get('crop_to_gt_bounds')}")
    width = max(len(k) for k, _ in rows)
    lines = [f"{'metric':<{width}}  value", f"{'-' * width}  {'-' * 10}"]
    lines += [f"{k:<{width}}  {v}" for k, v in rows]
    return "\n".join(lines) + "\n" + note


__all__ = ["MeshMetricsConfig", "MeshMetrics", "TriMesh", "load_mesh", "evaluate_meshes",
           "evaluate_mesh_files", "evaluate_with_scene", "save_json", "format_table", "METRIC_KEYS"]
