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
    scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
    cos = np.clip((np.trace(T[:3, :3] / scale) - 1) / 2, -1, 1)
    return T, {"fitness": float(reg.fitness), "inlier_rmse_m": float(reg.inlier_rmse), "scale": scale,
               "rotation_deg": float(np.degrees(np.arccos(cos))), "translation_m": float(np.linalg.norm(T[:3, 3]))}


def evaluate_aligned(pred_path: str | Path, pred_scene: str | Path, gt_scene: str | Path,
                     gt_path: str | Path | None = None, cfg=None, icp: bool = False):
    """Score the mesh ``pred_path`` (in the frame of ``pred_scene``) against the GT of ``gt_scene``
    after :func:`align_scenes` and, with ``icp``, a similarity ICP refinement (correspondences
    within twice the F-score threshold). The returned metrics' protocol holds the alignment."""
    from evaluation.mesh_metrics import MeshMetricsConfig, evaluate_meshes, scene_cameras_and_gt
    from evaluation.surfaces import TriMesh, load_mesh, sample_surface

    cfg = cfg or MeshMetricsConfig()
    cameras, scene_gt = scene_cameras_and_gt(gt_scene)
    gt_path = gt_path if gt_path is not None else scene_gt
    if gt_path is None:
        raise ValueError(f"no GT mesh: pass --gt GT_MESH (the scene {gt_scene} has no gt/mesh.ply)")
    alignment = align_scenes(pred_scene, gt_scene)
    pred, gt = load_mesh(pred_path), load_mesh(gt_path)
    vertices = alignment.transform.apply(pred.vertices)
    if icp:
        rng = np.random.default_rng(0)
        src, _ = sample_surface(TriMesh(vertices, pred.faces), 50_000, rng)
        pts, _ = sample_surface(gt, 100_000, rng)
        T, alignment.icp = icp_refine(src, pts, max_dist=2 * cfg.threshold)
        vertices = vertices @ T[:3, :3].T + T[:3, 3]
    result = evaluate_meshes(TriMesh(vertices, pred.faces, name=f"{pred.name} (aligned)"), gt, cfg, cameras)
    result.protocol.update({"pred_mesh": str(pred_path), "gt_mesh": str(gt_path), "scene": str(gt_scene),
                            "pred_scene": str(pred_scene), "alignment": alignment.to_dict()})
    return result
