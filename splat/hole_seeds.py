"""Hole seeds (an extension, ``splat train --init.fill-holes``): Gaussians where the cue Gaussians
leave a training view empty.

The cues cover a third of a room's surface or less (a bare room: its edges and a few objects), so
the initial Gaussians leave most of each training image black, and gradient densification grows
into an empty wall only from its border: on the bare benchmark room the held-out views stayed at
~5 dB PSNR for the first quarter of a 3000-iteration run (docs/training.md). Here, once before
training, each training view renders the initial Gaussians; on a grid of its pixels where they leave
the view open (alpha below ``hole_alpha``) and the view has an L_a anchor (the depth prior aligned
to the cues, or a plane cue's depth), a point is placed at that depth with the image's colour and
the view's normal prior; the points of all views are averaged per voxel and seed SFM-typed
Gaussians (3DGS density control, scaled from their neighbours like every cue). Views without an
anchor add nothing, so prior-free scenes and the ``no-cues`` baseline are unchanged.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from geocues.cue_io import CueCloud
from geocues.types import CueType
from splat.mesh import backproject

log = logging.getLogger(__name__)


def view_hole_points(alpha: np.ndarray, anchor: np.ndarray, rgb: np.ndarray, normal: np.ndarray | None,
                     K: np.ndarray, R: np.ndarray, t: np.ndarray, stride: int, max_alpha: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points [m, 3], colours [m, 3] in [0, 1] and world normals [m, 3] (zeros: none) of one
    view's open pixels: on the grid of every ``stride``-th pixel (from stride // 2), those with
    ``alpha`` [H, W] < ``max_alpha`` and a finite ``anchor`` [H, W] > 0 (z-depth, m), back-projected
    through the pixel centre of the camera ``x_cam = R X + t`` with intrinsics ``K``."""
    h, w = alpha.shape
    if anchor.shape != (h, w) or rgb.shape[:2] != (h, w):
        raise ValueError(f"alpha {alpha.shape}, anchor {anchor.shape} and rgb {rgb.shape[:2]} must agree")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    grid = np.zeros((h, w), bool)
    grid[stride // 2::stride, stride // 2::stride] = True
    z = np.where(grid & (alpha < max_alpha) & np.isfinite(anchor) & (anchor > 0), anchor, 0.0).astype(np.float64)
    R = np.asarray(R, np.float64)
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, np.asarray(t, np.float64)
    xyz = backproject(z, np.asarray(K, np.float64), w2c)
    rows, cols = np.nonzero(z > 0)  # backproject's order
    col = rgb[rows, cols].astype(np.float64)
    if normal is None:
        nrm = np.zeros_like(xyz)
    else:
        n = np.nan_to_num(normal[rows, cols].astype(np.float64))
        nrm = n @ R  # camera -> world
        nrm[np.linalg.norm(n, axis=1) < 0.5] = 0.0
    return xyz, col, nrm


def voxel_average(xyz: np.ndarray, rgb: np.ndarray, normal: np.ndarray, voxel: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One point per occupied voxel of edge ``voxel`` (m): the mean position and colour, and the mean
    normal renormalised (zeros where the voxel's normals cancel or none was known)."""
    if len(xyz) == 0:
        return xyz.reshape(0, 3), rgb.reshape(0, 3), normal.reshape(0, 3)
    if not voxel > 0:
        raise ValueError(f"voxel must be > 0, got {voxel}")
    _, inv, cnt = np.unique(np.floor(xyz / voxel).astype(np.int64), axis=0, return_inverse=True,
                            return_counts=True)
    inv = inv.reshape(-1)

    def mean(a: np.ndarray) -> np.ndarray:
        out = np.zeros((len(cnt), a.shape[1]))
        np.add.at(out, inv, a)
        return out / cnt[:, None]

    n = mean(normal)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0.5, n / np.maximum(length, 1e-12), 0.0)
    return mean(xyz), mean(rgb), n


@torch.no_grad()
def hole_seeds(params: dict, views, stride: int = 4, max_alpha: float = 0.5, voxel: float = 0.1
               ) -> CueCloud:
    """SFM-typed seed points where ``params`` (the initial Gaussians) leave the training ``views``
    (a :class:`splat.views.ViewSet`) open; see the module docstring. Empty when no view has an anchor."""
    from splat.rasterize import render

    pts, cols, nrms = [], [], []
    for k in range(len(views)):
        v = views[k]
        if v.depth_anchor is None:
            continue
        cam = views.scene.cameras[v.index]
        alpha = render(params, v.camera, sh_degree=0)["alpha"].detach().cpu().numpy()
        normal = None if v.normal_prior is None else v.normal_prior.cpu().numpy()
        p, c, n = view_hole_points(alpha, v.depth_anchor.cpu().numpy(), v.rgb.cpu().numpy(), normal,
                                   cam.K, cam.R, cam.t, stride, max_alpha)
        pts.append(p), cols.append(c), nrms.append(n)
    if not pts:
        return CueCloud.make(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), CueType.SFM)
    xyz, rgb, nrm = voxel_average(np.concatenate(pts), np.concatenate(cols), np.concatenate(nrms), voxel)
    log.info("hole seeds: %d points (voxel %.3f m) from %d views' open pixels", len(xyz), voxel, len(pts))
    return CueCloud.make(xyz, np.clip(rgb, 0.0, 1.0), CueType.SFM, normal=nrm)
