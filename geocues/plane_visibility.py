"""The visibility check of plane-like points against every view's aligned depth prior
(`geocues extract --plane.visibility-check`, an extension).

A plane point is a claim that a surface lies there. A view whose aligned prior sees a surface
clearly in front of the point (the point lies behind it by more than ``rel`` of the prior's depth)
says the point is hidden there; a view whose prior lies within ``rel`` of it agrees. A point hidden
in at least ``min_views`` views and in more views than agree with it is dropped: a surface the
region's own view put behind what the others see — a weak region of a sofa or a chair cut with the
floor's plane where the prior has a hole, so its points lie on the floor under the furniture. Views
where the prior has no depth at the point, or where the point falls outside the image or behind the
camera, do not vote. Free space in front of a surface is not tested (a prior with holes cannot tell
free space from a surface it missed).
"""

from __future__ import annotations

import numpy as np

from geocues.scene import Camera


def behind_and_agree(xyz: np.ndarray, cameras: list[Camera], priors: dict[int, np.ndarray],
                     stride: int, rel: float) -> tuple[np.ndarray, np.ndarray]:
    """Votes of the views' priors on points ``xyz`` [N, 3]: (views whose prior lies in front of the
    point by more than ``rel`` of its depth [N], views whose prior lies within ``rel`` [N]).
    ``priors``: image index -> aligned prior depth sampled every ``stride``-th pixel
    (``depth[::stride, ::stride]``; 0 or non-finite where the prior has none)."""
    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be [N, 3], got {xyz.shape}")
    if stride < 1 or not rel > 0:
        raise ValueError(f"stride must be >= 1 and rel > 0, got {stride}, {rel}")
    behind = np.zeros(len(xyz), np.int32)
    agree = np.zeros(len(xyz), np.int32)
    for i, depth in priors.items():
        uv, z = cameras[i].project(xyz)
        h, w = depth.shape
        with np.errstate(invalid="ignore"):
            col = np.rint((uv[:, 0] - 0.5) / stride)  # pixel centres at (0.5, 0.5) + (stride * col, ...)
            row = np.rint((uv[:, 1] - 0.5) / stride)
            idx = np.flatnonzero((z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h))
        d = depth[row[idx].astype(np.int64), col[idx].astype(np.int64)]
        has = np.isfinite(d) & (d > 0)
        idx, d, zi = idx[has], d[has], z[idx[has]]
        behind[idx[zi > d * (1 + rel)]] += 1
        agree[idx[np.abs(zi - d) <= rel * d]] += 1
    return behind, agree


def visible_mask(behind: np.ndarray, agree: np.ndarray, min_views: int) -> np.ndarray:
    """[N] True for the points to keep: hidden in fewer than ``min_views`` views, or in no more views
    than agree with them."""
    return ~((behind >= min_views) & (behind > agree))
