"""Planar completion of MVS depth on textureless surfaces (an extension of `geocues mvs`, after the
planar prior of ACMP: Xu & Tao, "Planar Prior Assisted PatchMatch Multi-View Stereo", AAAI 2020).

The plane sweep gives no depth where a patch has no texture (NCC is undefined there): on the walls
of a room that is a third to a half of every view. ACMP triangulates the reliable depths of a view
and takes each triangle's plane as the prior of the pixels inside it. Here, weight-free and in one
pass:

1. one consistent depth per ``fill_stride`` × ``fill_stride`` cell is back-projected and the pixels
   are triangulated (Delaunay, in the image);
2. a triangle gives a plane unless its longest 3D edge exceeds ``fill_max_edge`` × its mean depth
   (a long sliver; at the default 2 it rejects few depth jumps — the check below is the guard) or
   the plane is seen at a grazing angle (|n · ray| < ``fill_min_cos`` at its centre);
3. a pixel with no depth whose patch is textureless (the sweep's own ``min_texture`` test) takes the
   depth where its ray meets its triangle's plane, if that lies within the view's sweep bounds.

The filled depths are not trusted on their own: `geocues.mvs.run` then applies the same
forward-backward consistency check as to the swept depths, so a fill survives only where
neighbouring views' own fills (their own triangulations) put the surface in the same place. A
triangle that bridges an occluding edge is seen from elsewhere with another parallax and fails it:
tests/test_mvs_fill.py's occluder (a textured box 0.7-1.3 m in front of a plain wall) gets 442 fill
pixels more than 5 % off the surface with the check skipped, none with it.
"""

from __future__ import annotations

import numpy as np


def cell_samples(depth: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the first pixel (row-major) with a depth in each ``stride`` × ``stride``
    cell of ``depth`` [H, W] (0 = none)."""
    rows, cols = np.nonzero(depth > 0)
    cell = (rows // stride) * (depth.shape[1] // stride + 1) + cols // stride
    _, first = np.unique(cell, return_index=True)
    return rows[first], cols[first]


def triangle_planes(X: np.ndarray, simplices: np.ndarray, max_edge: float,
                    min_cos: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Planes of the triangles ``simplices`` [T, 3] over camera-frame points ``X`` [P, 3]: unit
    normals [T, 3], offsets [T] (n · x = offset) and which triangles may give a prior [T] (longest
    edge under ``max_edge`` × mean depth, |n · ray| at the centre at least ``min_cos``)."""
    A, B, C = (X[simplices[:, k]] for k in range(3))
    n = np.cross(B - A, C - A)
    norm = np.linalg.norm(n, axis=1)
    n = n / np.maximum(norm, 1e-300)[:, None]
    edge = np.max([np.linalg.norm(B - A, axis=1), np.linalg.norm(C - B, axis=1),
                   np.linalg.norm(A - C, axis=1)], axis=0)
    centre = (A + B + C) / 3.0
    cos_view = np.abs((n * centre).sum(1)) / np.maximum(np.linalg.norm(centre, axis=1), 1e-300)
    ok = (norm > 1e-12 * np.maximum(edge, 1e-300) ** 2) & (edge < max_edge * centre[:, 2]) & (cos_view >= min_cos)
    return n, (n * A).sum(1), ok


def planar_fill(depth: np.ndarray, textureless: np.ndarray, rays: np.ndarray, bounds: tuple[float, float], *,
                stride: int = 8, max_edge: float = 2.0, min_cos: float = 0.25) -> np.ndarray:
    """Depth [H, W] (0 = none) for the textureless pixels of ``textureless`` [H, W] bool that
    ``depth`` [H, W] (consistent MVS depth, 0 = none) leaves empty, from the planes of a Delaunay
    triangulation of ``depth`` (module docstring); ``rays`` [H, W, 3] are the pixels' camera-frame
    rays (z = 1), ``bounds`` the (near, far) depths a fill may take. Zero everywhere else and where
    fewer than three non-collinear depths exist."""
    from scipy.spatial import Delaunay, QhullError

    if depth.ndim != 2:
        raise ValueError(f"planar_fill: depth must be [H, W], got {depth.shape}")
    H, W = depth.shape
    if rays.shape != (H, W, 3) or textureless.shape != (H, W):
        raise ValueError(f"planar_fill: depth {depth.shape}, textureless {textureless.shape} and rays "
                         f"{rays.shape} must share [H, W] (rays [H, W, 3])")
    if textureless.dtype != bool or stride < 1 or not bounds[0] < bounds[1]:
        raise ValueError(f"planar_fill: need a bool textureless mask, stride >= 1 and near < far "
                         f"(got {textureless.dtype}, {stride}, {bounds})")
    out = np.zeros((H, W), np.float32)
    rows, cols = cell_samples(depth, stride)
    if len(rows) < 3:
        return out
    try:
        tri = Delaunay(np.stack([cols, rows], 1).astype(np.float64))
    except QhullError:  # all samples on a line
        return out
    X = rays[rows, cols].astype(np.float64) * depth[rows, cols, None].astype(np.float64)
    n, offset, ok = triangle_planes(X, tri.simplices, max_edge, min_cos)
    target = textureless & ~(depth > 0)
    t_rows, t_cols = np.nonzero(target)
    simplex = tri.find_simplex(np.stack([t_cols, t_rows], 1).astype(np.float64))
    inside = simplex >= 0
    inside[inside] = ok[simplex[inside]]
    t_rows, t_cols, simplex = t_rows[inside], t_cols[inside], simplex[inside]
    r = rays[t_rows, t_cols].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = offset[simplex] / (n[simplex] * r).sum(1)
    good = np.isfinite(z) & (z >= bounds[0]) & (z <= bounds[1])
    out[t_rows[good], t_cols[good]] = z[good]
    return out
