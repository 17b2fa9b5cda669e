"""Merging the plane-like points of all images (paper §4.1, "voxel-downsample").

:func:`voxel_downsample` merges points per voxel and counts the images that support each voxel
(the PLANE cues' confidence).
"""

from __future__ import annotations

import numpy as np


def voxel_downsample(xyz: np.ndarray, rgb: np.ndarray, normal: np.ndarray, view: np.ndarray,
                     voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Merge points per voxel of edge ``voxel``: mean position and colour, mean normal
    (re-normalised, sign-aligned to the voxel's first normal) and the number of distinct images
    (``view`` [N]) that put a point in the voxel. Returns (xyz, rgb, normal, n_views) per voxel."""
    xyz = np.asarray(xyz, np.float64)
    if len(xyz) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), \
            np.zeros(0, np.int64)
    if voxel <= 0:
        raise ValueError(f"voxel size must be > 0, got {voxel}")
    keys = np.floor(xyz / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if np.prod(span.astype(np.float64)) < 2.0 ** 62:  # one int64 per voxel: a fast 1D unique
        flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, inv, cnt = np.unique(flat, return_inverse=True, return_counts=True)
    else:
        _, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    m = len(cnt)

    def mean(a: np.ndarray) -> np.ndarray:  # per-voxel mean of each column
        return np.stack([np.bincount(inv, weights=a[:, j], minlength=m) for j in range(a.shape[1])],
                        axis=1) / cnt[:, None]

    first = np.full(m, -1, np.int64)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    ref = normal[first]
    sign = np.where(np.sum(normal * ref[inv], axis=1) < 0, -1.0, 1.0)
    nrm = mean(normal * sign[:, None])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    view = np.asarray(view, np.int64)
    nv = int(view.max()) + 1
    pairs = np.sort(inv.astype(np.int64) * nv + view)  # (voxel, view) pairs, sorted
    first_of_pair = np.r_[True, pairs[1:] != pairs[:-1]]
    n_views = np.bincount(pairs[first_of_pair] // nv, minlength=m)
    return mean(xyz), mean(rgb).astype(np.float32), nrm.astype(np.float32), n_views


def consolidate_planes(xyz: np.ndarray, plane_of: np.ndarray, planes: np.ndarray, plane_view: np.ndarray,
                       centers: np.ndarray, max_angle_deg: float, max_dist: float, min_ray_cos: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse the per-image planes that describe the same surface (our addition: each image's plane
    carries that image's prior and anchor errors; the errors of different images partly cancel).

    Planes j and i (n·X + d = 0, world) are one surface when their normals differ by less than
    ``max_angle_deg`` and each passes within ``max_dist`` of the other's point centroid. Greedily,
    largest first, every cluster gets the plane n* = mean of its normals, d* = median over its
    members of −n*·centroid_j, and its points move along their camera rays onto it:

        X' = c + t (X − c),   t = −(n*·c + d*) / (n*·(X − c))

    (kept where the ray is grazing, |cos| < ``min_ray_cos``). xyz: [N, 3] points, plane_of: [N]
    their plane row in ``planes`` [K, 4]; plane_view: [K] camera index of each plane; centers:
    [C, 3] camera centres. Returns (new xyz [N, 3], new normals [N, 3] facing each point's camera,
    number of distinct images in each point's cluster [N])."""
    xyz = np.asarray(xyz, np.float64)
    K = len(planes)
    if K == 0:
        return xyz, np.zeros((len(xyz), 3)), np.zeros(len(xyz), np.int64)
    cnt = np.bincount(plane_of, minlength=K).astype(np.float64)
    cen = np.stack([np.bincount(plane_of, weights=xyz[:, j], minlength=K) for j in range(3)], 1)
    cen /= np.maximum(cnt, 1.0)[:, None]
    n, d = planes[:, :3], planes[:, 3]
    cos_max = np.cos(np.radians(max_angle_deg))
    cluster = np.full(K, -1, np.int64)
    fused: list[np.ndarray] = []
    for i in np.argsort(-cnt, kind="stable"):
        if cluster[i] >= 0 or cnt[i] == 0:
            continue
        free = np.flatnonzero(cluster < 0)
        dots = n[free] @ n[i]
        same = (np.abs(dots) >= cos_max) & (np.abs(cen[free] @ n[i] + d[i]) <= max_dist) \
            & (np.abs(np.sum(n[free] * cen[i], axis=1) + d[free]) <= max_dist)
        members = free[same]
        cluster[members] = len(fused)
        sign = np.where(n[members] @ n[i] < 0, -1.0, 1.0)
        n_star = (n[members] * sign[:, None]).mean(axis=0)
        n_star /= np.linalg.norm(n_star)
        fused.append(np.r_[n_star, float(np.median(-(cen[members] @ n_star)))])
    fused_arr = np.array(fused)  # [M, 4]
    views_of = np.array([len(np.unique(plane_view[cluster == c])) for c in range(len(fused_arr))])
    pc = cluster[plane_of]  # [N] cluster of each point
    c = centers[plane_view[plane_of]]  # [N, 3] camera centre of each point
    nf, df = fused_arr[pc, :3], fused_arr[pc, 3]
    ray = xyz - c
    denom = np.sum(nf * ray, axis=1)
    ok = np.abs(denom) >= min_ray_cos * np.linalg.norm(ray, axis=1)
    t = np.where(ok, -(np.sum(nf * c, axis=1) + df) / np.where(ok, denom, 1.0), 1.0)
    ok &= t > 0
    out = np.where(ok[:, None], c + t[:, None] * ray, xyz)
    face = np.where(np.sum(nf * ray, axis=1)[:, None] < 0, nf, -nf)
    return out, face, views_of[pc]


def multiview_support(xyz: np.ndarray, view: np.ndarray, radius: float, voxel: float, k: int = 32
                      ) -> np.ndarray:
    """Number of images that put a plane point within ``radius`` of each point (its own included).

    Planes found independently in several images agree where they are right; a wrong plane (a bad
    anchor, a region straddling two surfaces) is rarely repeated by other images. Points are first
    merged per (voxel, image); the count looks at the ``k`` nearest merged points, so it saturates
    near k / (points one image puts within ``radius``). xyz: [N, 3], view: [N]. Returns [N] int."""
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, np.float64)
    if len(xyz) == 0:
        return np.zeros(0, np.int64)
    view = np.asarray(view, np.int64)
    keys = np.floor(xyz / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    nv = int(view.max()) + 1
    flat = ((keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]) * nv + view
    uk, inv = np.unique(flat, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv).astype(np.float64)
    cen = np.stack([np.bincount(inv, weights=xyz[:, j]) for j in range(3)], axis=1) / cnt[:, None]
    cview = uk % nv  # [M] image of each merged point
    kk = min(k, len(cen))
    dist, nn = cKDTree(cen).query(cen, k=kk, distance_upper_bound=radius)
    nn = nn.reshape(len(cen), kk)
    valid = np.isfinite(dist.reshape(len(cen), kk))
    views = np.where(valid, cview[np.minimum(nn, len(cen) - 1)], -1)  # [M, kk]
    views.sort(axis=1)
    distinct = (views[:, :1] >= 0).astype(np.int64).ravel() + np.sum(
        (views[:, 1:] != views[:, :-1]) & (views[:, 1:] >= 0), axis=1)
    return distinct[inv]
