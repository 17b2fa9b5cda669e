"""Put a reconstruction into the ground truth's frame before scoring it (`evaluate --align-to`).

An images-only reconstruction (`geocues sfm --mode map`) has its own frame and scale. Benchmarks
that take poses from SfM score it after a similarity transform estimated from the camera centres of
the images both reconstructions share (Umeyama 1991), optionally refined by ICP of the mesh against
the GT mesh (Tanks and Temples, ETH3D). This module does exactly that and reports the transform and
the camera-centre residuals, so a bad alignment is visible rather than hidden in the metrics.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def scene_metadata(scene: str | Path | None) -> dict:
    """SCENE/scene.json without loading the scene; {} when there is none (or a damaged one: the scene
    loader names that)."""
    import json

    meta = Path(scene) / "scene.json" if scene is not None else None
    try:
        data = json.loads(meta.read_text()) if meta is not None and meta.is_file() else {}
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


def own_frame_warning(scene: str | Path | None, what: str = "mesh") -> str | None:
    """The warning for a SCENE mapped from images alone (`geocues sfm --mode map` marks scene.json,
    `rescale`, `undistort` and `mvs` keep the mark): its frame is its own, so scoring its ``what``
    (mesh, cues, ...) against a GT needs --align-to. None for any other scene."""
    from geocues.scene import OWN_FRAME

    if scene_metadata(scene).get("frame") != OWN_FRAME:
        return None
    return (f"{scene} was mapped from images alone, so its frame (origin, axes, unit) is its own, not the ground "
            "truth's: pass --align-to GT_SCENE (a scene in the GT's frame with the same image names) to score its "
            f"{what}")


def alignment_line(gt_scene: str | Path, a: dict) -> str:
    """One line of an :meth:`Alignment.to_dict` (``a``): what `evaluate ... --align-to` prints."""
    res, icp = a["centre_residual_m"], a["icp"]
    return (f"aligned to {gt_scene}: scale {a['scale']:.4f} from {a['shared_images']} shared images, camera "
            f"centre residual RMS {res['rms']:.4f} m, median {res['median']:.4f} m, max {res['max']:.4f} m"
            + (f"; ICP {icp['rotation_deg']:.3f} deg, {icp['translation_m']:.4f} m, scale {icp['scale']:.4f}, "
               f"fitness {icp['fitness']:.3f}, inlier RMSE {icp['inlier_rmse_m']:.4f} m" if icp else ""))


@dataclass
class Similarity:
    """x_gt = s R x + t."""

    s: float
    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.s * np.asarray(x, np.float64) @ self.R.T + self.t

    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous form."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.s * self.R, self.t
        return T


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity dst ≈ s R src + t (Umeyama 1991, eq. 40–42).

    src, dst: [N, 3] corresponding points, N >= 3 and not all collinear. float64 throughout."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"need two [N, 3] point sets of one shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"a similarity needs at least 3 corresponding points, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs ** 2).sum() / len(src)
    cov = xd.T @ xs / len(src)  # [3, 3]
    U, D, Vt = np.linalg.svd(cov)
    if var_s < 1e-18 or D[1] < 1e-12 * max(D[0], 1e-300):
        raise ValueError("the corresponding points are (nearly) collinear or coincide: the rotation "
                         "about their line is undetermined")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    return Similarity(s, R, mu_d - s * R @ mu_s)


@dataclass
class Alignment:
    """The result of :func:`align_scenes`: the transform and how well the camera centres agree."""

    transform: Similarity
    shared: list[str]
    residuals_m: np.ndarray  # [len(shared)] distance of each aligned centre to its GT centre
    icp: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        r = self.residuals_m
        return {"scale": self.transform.s, "matrix": self.transform.matrix().tolist(),
                "shared_images": len(self.shared),
                "centre_residual_m": {"rms": float(np.sqrt(np.mean(r ** 2))), "median": float(np.median(r)),
                                      "max": float(r.max())},
                "icp": self.icp}


def align_scenes(pred_scene: str | Path, gt_scene: str | Path) -> Alignment:
    """Similarity from the frame of ``pred_scene`` to that of ``gt_scene`` through the centres of the
    images (matched by file name) that both register."""
    from geocues.scene import Scene

    pred, gt = Scene.load(pred_scene, check_priors=False), Scene.load(gt_scene, check_priors=False)
    gt_by_name = {c.name: c for c in gt.cameras}
    shared = [c.name for c in pred.cameras if c.name in gt_by_name]
    if len(shared) < 3:
        raise ValueError(f"--align-to needs at least 3 images registered in both {pred_scene} and "
                         f"{gt_scene} (matched by file name); found {len(shared)}")
    pred_by_name = {c.name: c for c in pred.cameras}
    src = np.stack([pred_by_name[n].center for n in shared])
    dst = np.stack([gt_by_name[n].center for n in shared])
    T = umeyama(src, dst)
    res = np.linalg.norm(T.apply(src) - dst, axis=1)
    log.info("aligned %s to %s with %d shared images: scale %.4f, centre residual median %.4f m, max %.4f m",
             pred_scene, gt_scene, len(shared), T.s, float(np.median(res)), float(res.max()))
    return Alignment(T, shared, res)


def icp_refine(points: np.ndarray, gt_points: np.ndarray, max_dist: float, iters: int = 100) -> tuple[np.ndarray, dict]:
    """Similarity ICP (Open3D point-to-point with scaling) of surface samples ``points`` of the
    roughly aligned mesh onto GT surface samples: camera centres of a compact capture leave errors in
    scale as well as in rotation. Returns the [4, 4] correction and its fitness / inlier RMSE."""
    import open3d as o3d

    reg_ = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(gt_points, np.float64)))
    reg = reg_.registration_icp(src, dst, max_dist, np.eye(4),
                                reg_.TransformationEstimationPointToPoint(with_scaling=True),
                                reg_.ICPConvergenceCriteria(max_iteration=iters))
    T = np.asarray(reg.transformation)
    return T, {"fitness": float(reg.fitness), "inlier_rmse_m": float(reg.inlier_rmse), **correction_size(T, points)}


def correction_size(T: np.ndarray, points: np.ndarray) -> dict:
    """Scale, rotation (degrees), translation (metres, about the origin) of a [4, 4] similarity ``T``, and
    the mean distance it moves ``points`` [N, 3] (the surface's shift: the translation includes the
    rotation's lever arm about the origin)."""
    scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
    cos = np.clip((np.trace(T[:3, :3] / scale) - 1) / 2, -1, 1)
    moved = np.linalg.norm(np.asarray(points, np.float64) @ (T[:3, :3] - np.eye(3)).T + T[:3, 3], axis=1)
    return {"scale": scale, "rotation_deg": float(np.degrees(np.arccos(cos))),
            "translation_m": float(np.linalg.norm(T[:3, 3])), "mean_shift_m": float(moved.mean())}


ICP_MAX_ROTATION_DEG = 3.0
"""ICP check: most rotation an ICP refinement may add before a warning. Measured after camera alignments:
0.6-1.5 deg on ICL (images-only and known-pose meshes, bench/results/icl_images_only*.json), 1.7 deg on the
test's room with 1 cm of camera noise; 3 deg moves a wall 2.5 m from a room's centre by 13 cm, more than
the 10 cm (2 x the F-score threshold) within which ICP pairs points."""
ICP_MAX_SCALE_CHANGE = 0.05
"""ICP check: most relative scale change |scale - 1|; measured 0.1-1.9 %; 5 % moves that wall by 12 cm."""
ICP_MAX_SHIFT_THRESHOLDS = 2.0
"""ICP check: most mean shift of the surface, in F-score thresholds: the correspondence distance ICP is
given (2 x 5 cm); a fit that moved the surface further than it could pair points at the start walked
there. Measured: 5.6 cm on the test's room with 1 cm of camera noise (ICL's refinements: 0.7-3.3 cm of
translation about the origin)."""


def icp_warning(icp: dict, residual_median_m: float, threshold: float) -> str | None:
    """A warning when the ICP correction ``icp`` (:func:`icp_refine`'s dict) is large for a refinement:
    rotation > ``ICP_MAX_ROTATION_DEG``, scale change > ``ICP_MAX_SCALE_CHANGE`` or mean surface shift >
    ``ICP_MAX_SHIFT_THRESHOLDS`` x ``threshold``, else None. ICP with scaling can slide a mesh onto another
    part of the GT and shrink it there (a 7.6 cm camera alignment followed by 24.7 deg, scale 0.72, 1.2 m
    of translation about the origin, 0.35 m of mean surface shift: precision 0.15 -> 0.91), which flatters
    accuracy and precision."""
    rot, scale, shift = icp["rotation_deg"], icp["scale"], icp["mean_shift_m"]
    max_shift = ICP_MAX_SHIFT_THRESHOLDS * threshold
    if rot <= ICP_MAX_ROTATION_DEG and abs(scale - 1) <= ICP_MAX_SCALE_CHANGE and shift <= max_shift:
        return None
    return (f"ICP turned the mesh {rot:.1f} deg, scaled it {scale:.3f}x and moved its surface {shift:.3f} m on "
            f"average after a camera alignment good to {residual_median_m:.3f} m (median centre residual): more than "
            f"a refinement (over {ICP_MAX_ROTATION_DEG:g} deg, {100 * ICP_MAX_SCALE_CHANGE:.0f} % scale or "
            f"{max_shift:g} m), so it may have slid the mesh onto another part of the GT: compare with the figures "
            "without --icp")


def evaluate_aligned(pred_path: str | Path, pred_scene: str | Path, gt_scene: str | Path,
                     gt_path: str | Path | None = None, cfg=None, icp: bool = False,
                     alignment: Alignment | None = None):
    """Score the mesh ``pred_path`` (in the frame of ``pred_scene``) against the GT of ``gt_scene``
    after :func:`align_scenes` (or the given ``alignment`` of the two scenes, for several meshes) and,
    with ``icp``, a similarity ICP refinement (correspondences within twice the F-score threshold).
    The returned metrics' protocol holds the alignment."""
    from evaluation.mesh_metrics import MeshMetricsConfig, evaluate_meshes, scene_cameras_and_gt
    from evaluation.surfaces import TriMesh, load_mesh, sample_surface

    cfg = cfg or MeshMetricsConfig()
    cameras, scene_gt = scene_cameras_and_gt(gt_scene)
    gt_path = gt_path if gt_path is not None else scene_gt
    if gt_path is None:
        raise ValueError(f"no GT mesh: pass --gt GT_MESH (the scene {gt_scene} has no gt/mesh.ply)")
    if alignment is None:
        alignment = align_scenes(pred_scene, gt_scene)
    elif icp:  # the ICP record is the alignment's: one per mesh
        alignment = Alignment(alignment.transform, alignment.shared, alignment.residuals_m)
    pred, gt = load_mesh(pred_path), load_mesh(gt_path)
    vertices = alignment.transform.apply(pred.vertices)
    if icp:
        rng = np.random.default_rng(0)
        src, _ = sample_surface(TriMesh(vertices, pred.faces), 50_000, rng)
        pts, _ = sample_surface(gt, 100_000, rng)
        T, alignment.icp = icp_refine(src, pts, max_dist=2 * cfg.threshold)
        vertices = vertices @ T[:3, :3].T + T[:3, 3]
        warning = icp_warning(alignment.icp, float(np.median(alignment.residuals_m)), cfg.threshold)
        if warning is not None:
            log.warning("%s", warning)
        alignment.icp["warning"] = warning
    result = evaluate_meshes(TriMesh(vertices, pred.faces, name=f"{pred.name} (aligned)"), gt, cfg, cameras)
    result.protocol.update({"pred_mesh": str(pred_path), "gt_mesh": str(gt_path), "scene": str(gt_scene),
                            "pred_scene": str(pred_scene), "alignment": alignment.to_dict()})
    return result
