"""The fused prior (an extension, ``splat train --loss.fused-anchor``): L_a's anchor from every
training view's aligned prior at once, not from the view's own.

A monocular depth prior aligned to the cues by one scale and shift per image keeps its
low-frequency warp: on the benchmark rooms the aligned simulated prior is 8.7 cm (textured) and
15.8 cm (bare) off in the median, and L_a holds the surface within its tolerance of that. The warp
differs from image to image, so the views disagree, and a TSDF of all their aligned priors with a
wide truncation averages the disagreement away along each ray: rendered back into the views it is
2.8 / 4.5 cm off in the median on 97 / 92 % of the pixels (docs/training_losses.md). Here the aligned
priors of the training views are fused (:class:`splat.mesh.TSDFFuser`, ``voxel`` and ``trunc``),
the mesh is cleaned like every TSDF mesh of the project, and each view's anchor is the z-depth of
the first surface on its pixel-centre rays (Open3D ray casting); pixels the mesh does not cover keep
the view's own aligned prior. The TSDF leans towards the farther priors (a view that sees the wall
behind where another puts it marks the other's surface free space): on the bare rooms 17-28 % of
the fused pixels lie more than 5 cm behind GT and 8-11 % in front. ``method="median"`` instead takes,
in each pixel, the median of the view's own prior and its nearest views' priors warped into it
(:func:`median_anchors`), which leans neither way.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import replace

import numpy as np

from evaluation.culling import raycasting_scene
from geocues.plane_anchors import anchor_depth
from splat.mesh import backproject

log = logging.getLogger(__name__)


def fuse_depths(views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], voxel: float, trunc: float,
                weight_threshold: float = 3.0):
    """The cleaned TSDF mesh (Open3D legacy) of ``(depth [H, W] m, K [3, 3], world_to_cam [4, 4])``
    views, without colour; None when it has no triangle (too few views agree anywhere)."""
    from splat.mesh import TSDFConfig, clean_mesh, fuse_views

    if not (voxel > 0 and trunc > 0):
        raise ValueError(f"voxel and trunc must be > 0, got {voxel}, {trunc}")
    cfg = replace(TSDFConfig(), voxel_size=voxel, sdf_trunc=trunc, weight_threshold=weight_threshold)
    mesh = clean_mesh(fuse_views(((d, None, K, w2c) for d, K, w2c in views), cfg, progress=False), cfg)
    return mesh if len(mesh.triangles) else None


def raycast_depth(scene, K: np.ndarray, R: np.ndarray, t: np.ndarray, height: int, width: int) -> np.ndarray:
    """[H, W] float32 z-depth of the first surface of the Open3D ``RaycastingScene`` ``scene``
    (:func:`evaluation.culling.raycasting_scene`) on the pixel-centre rays of the camera
    ``x_cam = R X + t`` (COLMAP pixel convention); 0 where a ray hits nothing."""
    import open3d as o3d

    K, R = np.asarray(K, np.float64), np.asarray(R, np.float64)
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays_cam = np.stack([(j - K[0, 2]) / K[0, 0], (i - K[1, 2]) / K[1, 1], np.ones_like(j)], -1).reshape(-1, 3)
    dirs = rays_cam @ R  # world directions whose camera z is 1: the hit distance is the z-depth
    origin = np.broadcast_to(-R.T @ np.asarray(t, np.float64), dirs.shape)
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, dirs], 1).astype(np.float32)))["t_hit"].numpy()
    return np.where(np.isfinite(hit), hit, 0.0).astype(np.float32).reshape(height, width)


def median_anchors(scene, aligned: dict[int, np.ndarray], neighbours: int = 32, min_votes: int = 3
                   ) -> dict[str, np.ndarray]:
    """{name: [H, W]}: in each pixel of each view, the median of its own aligned prior and those of its
    ``neighbours`` nearest views (camera distance, minus the cosine of the viewing directions, in
    metres) warped into it (nearest point per pixel); the view's own prior where fewer than
    ``min_votes`` depths fall. Unlike the TSDF, whose free-space updates let a farther prior carve a
    nearer one, the median leans neither way (bare room, seed 0: 22 % of the pixels more than 5 cm
    behind GT and 24 % in front, against 28 % and 11 % for the TSDF)."""
    idx = list(aligned)
    cams = [scene.cameras[i] for i in idx]
    centres = np.array([c.center for c in cams])
    axes = np.array([np.asarray(c.R)[2] for c in cams])
    points = [backproject(aligned[i], c.K, c.world_to_camera) for i, c in zip(idx, cams)]
    out = {}
    for k, cam in enumerate(cams):
        score = np.linalg.norm(centres - centres[k], axis=1) - axes @ axes[k]
        order = [j for j in np.argsort(score, kind="stable") if j != k][:neighbours]
        stack = np.stack([aligned[idx[k]]] + [anchor_depth(points[j], None, cam.K, cam.R, cam.t, cam.height, cam.width)
                                               for j in order])  # nearest point per pixel
        votes = (stack > 0).sum(0)
        with warnings.catch_warnings():  # pixels without any depth: an all-NaN slice, replaced below
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(np.where(stack > 0, stack, np.nan), axis=0)
        out[cam.name] = np.where(votes >= min_votes, med, aligned[idx[k]]).astype(np.float32)
    return out


def fused_anchors(scene, indices: list[int], alignments: dict, voxel: float = 0.04, trunc: float = 0.3,
                  method: str = "tsdf", neighbours: int = 32) -> dict[str, np.ndarray]:
    """{image name: [H, W] anchor} for the views of ``scene`` with ``indices`` whose prior
    ``alignments`` aligned: the fused prior where its mesh covers the pixel, the view's own aligned
    prior elsewhere (0 where neither has a finite positive depth). Empty when fewer than two views
    are aligned or the fusion is empty."""
    aligned = {}
    for i in indices:
        cam = scene.cameras[i]
        al = alignments.get(cam.name)
        d = scene.depth_prior(i) if al is not None else None
        if d is not None:
            a = al.apply(d).astype(np.float32)
            aligned[i] = np.where(np.isfinite(a) & (a > 0), a, 0.0).astype(np.float32)  # 0: no depth
    if len(aligned) < 2:
        return {}
    if method == "median":
        out = median_anchors(scene, aligned, neighbours)
        log.info("fused prior: the median of %d aligned views' priors (up to %d neighbours each)", len(aligned), neighbours)
        return out
    if method != "tsdf":
        raise ValueError(f"method must be 'tsdf' or 'median', got {method!r}")
    mesh = fuse_depths([(d, scene.cameras[i].K, scene.cameras[i].world_to_camera) for i, d in aligned.items()],
                       voxel, trunc)
    if mesh is None:
        log.warning("fused prior: the TSDF of %d aligned priors is empty; L_a keeps each view's own", len(aligned))
        return {}
    rays = raycasting_scene(np.asarray(mesh.vertices), np.asarray(mesh.triangles))  # built once
    out, covered = {}, []
    for i, own in aligned.items():
        cam = scene.cameras[i]
        z = raycast_depth(rays, cam.K, cam.R, cam.t, cam.height, cam.width)
        covered.append(float(np.mean(z > 0)))
        out[cam.name] = np.where(z > 0, z, own)
    log.info("fused prior: %d aligned views, mesh of %d triangles covers %.0f %% of their pixels",
             len(aligned), len(mesh.triangles), 100 * float(np.mean(covered)))
    return out
