"""Accuracy and coverage of geometric cues (``geocues extract`` output) against a GT surface.

Distances are exact point-to-triangle distances (Open3D ``RaycastingScene``). Coverage is the share
of GT surface samples — uniform by area, restricted to what the scene's cameras see (frustum and
occlusion by the GT itself) — that have a cue point within ``coverage_dist``.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geocues.cue_io import CueCloud, read_cues_ply
from geocues.types import CueType

log = logging.getLogger(__name__)


@dataclass
class CueMetricsConfig:
    """Options of the cue evaluation."""

    n_gt_samples: int = 100_000
    """GT surface samples for coverage (on the part of the surface the cameras see)."""
    coverage_dist: float = 0.05
    """A GT sample is covered when a cue point lies within this distance (metres)."""
    occlusion_tolerance: float = 0.02
    """A GT sample counts as seen if it lies at most this far behind the GT surface along a ray."""
    seed: int = 0
    """Seed of the GT sampling."""

    def validate(self) -> None:
        """Raise ValueError naming an impossible option (--coverage-dist -1 printed 'within -100 cm')."""
        if not (math.isfinite(self.coverage_dist) and self.coverage_dist > 0):
            raise ValueError(f"--coverage-dist must be a finite distance > 0 (metres), got {self.coverage_dist}")
        if not (math.isfinite(self.occlusion_tolerance) and self.occlusion_tolerance >= 0):
            raise ValueError(f"--occlusion-tolerance must be a finite distance >= 0 (metres), got "
                             f"{self.occlusion_tolerance}")
        if self.n_gt_samples < 1 or self.seed < 0:
            raise ValueError(f"--n-gt-samples must be >= 1 and --seed >= 0, got {self.n_gt_samples}, {self.seed}")


def share_within(d: np.ndarray, t: float) -> float | None:
    """Share of distances <= t (None for no distances)."""
    return float(np.mean(d <= t)) if len(d) else None


def median_or_none(d: np.ndarray) -> float | None:
    """Median of the distances (None for no distances)."""
    return float(np.median(d)) if len(d) else None


class GroundTruth:
    """A GT mesh prepared for cue evaluation: exact-distance queries and seen-surface samples."""

    def __init__(self, gt_path: str | Path, cameras: list, cfg: CueMetricsConfig):
        from evaluation.culling import CameraSet, raycasting_scene, visible_mask
        from evaluation.surfaces import load_mesh, sample_kept_surface

        self.path = Path(gt_path)
        mesh = load_mesh(self.path)
        self.scene = raycasting_scene(mesh.vertices, mesh.faces)
        cams = CameraSet.from_cameras(cameras)
        self.samples, _, self.seen_fraction = sample_kept_surface(
            mesh, cfg.n_gt_samples, np.random.default_rng(cfg.seed),
            keep=lambda p: visible_mask(p, cams, occluder=self.scene, tolerance=cfg.occlusion_tolerance))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Exact distance of each point [N, 3] to the GT surface, [N]."""
        from evaluation.surfaces import surface_distances

        return surface_distances(np.asarray(points, np.float64), self.scene)[0] if len(points) else np.zeros(0)


def coverage(points: np.ndarray, gt_samples: np.ndarray, dist: float) -> float:
    """Share of GT samples with a point within ``dist`` (0 when there are no points)."""
    from evaluation.surfaces import nearest_sample_distances

    if len(points) == 0:
        return 0.0
    return float(np.mean(nearest_sample_distances(gt_samples, np.asarray(points, np.float64))[0] <= dist))


def cue_accuracy(cues: CueCloud, gt: GroundTruth, cfg: CueMetricsConfig) -> dict:
    """Per cue type: count, median distance to GT, shares within 1/2/3/5 cm, and coverage."""
    dist = gt.distances(cues.xyz)
    out: dict = {"counts": cues.counts(), "per_type": {}, "coverage": {}}
    for t in CueType:
        mask = cues.cue_type == t
        d = dist[mask]
        out["per_type"][t.name] = {"n": int(mask.sum()), "median_m": median_or_none(d),
                                   **{f"within_{c}cm": share_within(d, c / 100) for c in (1, 2, 3, 5)}}
        out["coverage"][t.name] = coverage(cues.xyz[mask], gt.samples, cfg.coverage_dist)
    out["coverage"]["ALL"] = coverage(cues.xyz, gt.samples, cfg.coverage_dist)
    out["coverage_dist_m"] = cfg.coverage_dist
    out["gt_seen_fraction"] = gt.seen_fraction
    return out


def evaluate_cues_dir(cues_dir: str | Path, scene_dir: str | Path, gt_path: str | Path | None = None,
                      cfg: CueMetricsConfig | None = None, align_to: str | Path | None = None) -> dict:
    """Evaluate ``CUES/cues.ply`` against the GT mesh (default ``SCENE/gt/mesh.ply``), with the
    SfM points of the scene before statistical outlier removal as a reference.

    ``align_to``: the GT scene of a SCENE in its own frame (`geocues sfm --mode map`): the cues and SfM
    points are moved into its frame by `evaluate --align-to`'s similarity of the shared camera centres
    (:func:`evaluation.align.align_scenes`) and scored against its GT mesh (or ``gt_path``), the seen
    surface being what its cameras of the shared images see."""
    from geocues.scene import Scene

    cfg = cfg or CueMetricsConfig()
    cfg.validate()
    cues_path = Path(cues_dir) / "cues.ply"
    if not cues_path.is_file():
        raise FileNotFoundError(f"no cues.ply in {cues_dir} (run `geocues extract SCENE -o {cues_dir}`)")
    scene = Scene.load(scene_dir, check_priors=False)
    gt_scene, alignment = scene, None
    if align_to is not None:
        from evaluation.align import align_scenes

        alignment = align_scenes(scene_dir, align_to)
        gt_scene = Scene.load(align_to, check_priors=False)
    gt_path = Path(gt_path) if gt_path is not None else gt_scene.gt_mesh_path
    if gt_path is None:
        raise FileNotFoundError(f"no GT mesh: pass --gt or put one at {gt_scene.root / 'gt' / 'mesh.ply'}")
    from splat.init_gaussians import foreign_cues

    report = Path(cues_dir) / "report.json"
    try:
        extracted_from = Path(json.loads(report.read_text())["scene"])
    except (OSError, ValueError, KeyError, TypeError):
        extracted_from = None
    if extracted_from is not None and extracted_from.exists() and extracted_from.resolve() != scene.root.resolve():
        log.warning("the cues %s were extracted from %s (its report.json), not %s: is SCENE the cues' scene?",
                    cues_path, extracted_from, scene.root)  # scored anyway: the figures then measure the mix-up
    elif foreign := foreign_cues(cues_path, scene):
        log.warning("the cues %s were extracted from another scene than %s: %s", cues_path, scene.root, foreign)
    cues, sfm_xyz, cameras = read_cues_ply(cues_path), scene.points.xyz, scene.cameras
    if alignment is not None:  # into the GT's frame and unit; the shared images' cameras there
        cues.xyz, sfm_xyz = alignment.transform.apply(cues.xyz), alignment.transform.apply(sfm_xyz)
        shared = set(alignment.shared)
        cameras = [c for c in gt_scene.cameras if c.name in shared]
    gt = GroundTruth(gt_path, cameras, cfg)
    result = cue_accuracy(cues, gt, cfg)
    sfm_all = gt.distances(sfm_xyz)
    result["sfm_before_sor"] = {"n": int(len(sfm_all)), "within_5cm": share_within(sfm_all, 0.05)}
    result.update(cues=str(cues_path), scene=str(scene_dir), gt=str(gt_path))
    if alignment is not None:
        result.update(gt_scene=str(align_to), alignment=alignment.to_dict())
    if report.is_file():
        result["seconds"] = json.loads(report.read_text()).get("seconds", {})
    return result


def format_cue_table(result: dict) -> str:
    """A plain-text table of :func:`evaluate_cues_dir`'s result."""
    def pct(v):
        return "   -  " if v is None else f"{100 * v:5.1f}%"

    lines = [f"{'type':<6} {'points':>8} {'median':>9} {'<=1cm':>7} {'<=2cm':>7} {'<=3cm':>7} {'<=5cm':>7} "
             f"{'coverage':>9}"]
    for name, m in result["per_type"].items():
        med = "      -  " if m["median_m"] is None else f"{1000 * m['median_m']:6.1f} mm"
        lines.append(f"{name:<6} {m['n']:>8} {med:>9} {pct(m['within_1cm']):>7} {pct(m['within_2cm']):>7} "
                     f"{pct(m['within_3cm']):>7} {pct(m['within_5cm']):>7} {pct(result['coverage'][name]):>9}")
    lines.append(f"{'ALL':<6} {sum(result['counts'].values()):>8} {'':>9} {'':>7} {'':>7} {'':>7} {'':>7} "
                 f"{pct(result['coverage']['ALL']):>9}")
    sfm = result.get("sfm_before_sor")
    if sfm and sfm["n"]:
        lines.append(f"SfM points before SOR: {sfm['n']}, {pct(sfm['within_5cm']).strip()} within 5 cm")
    lines.append(f"coverage = share of the seen GT surface ({pct(result['gt_seen_fraction']).strip()} of its area) "
                 f"within {100 * result['coverage_dist_m']:.0f} cm of a cue point")
    return "\n".join(lines)
