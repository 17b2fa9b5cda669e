"""Merging the plane-like points of all images (paper §4.1, "voxel-downsample").

:func:`voxel_downsample` merges points per voxel and counts the images that support each voxel
(the PLANE cues' confidence). Before that, the planes of different images check each other:
:func:`multiview_support` (enough images put the same plane -- position and orientation -- near a
point) and :func:`multiview_conflict` (no more images put the surface elsewhere there);
:func:`consolidate_planes` optionally fuses the planes of one surface. :func:`merge_plane_points`
chains them for ``geocues extract``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from geocues.cue_io import CueCloud
from geocues.types import CueType

if TYPE_CHECKING:
    from geocues.planes import PlaneConfig


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


def _merge_per_view(xyz: np.ndarray, view: np.ndarray, voxel: float, normal: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Points merged per (voxel, image): (centres [M, 3], image [M], row of each point [N], unit
    normal of the first point of each [M, 3] or None)."""
    keys = np.floor(xyz / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    nv = int(view.max()) + 1
    flat = ((keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]) * nv + view
    uk, inv = np.unique(flat, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv).astype(np.float64)
    cen = np.stack([np.bincount(inv, weights=xyz[:, j]) for j in range(3)], axis=1) / cnt[:, None]
    cn = None
    if normal is not None:
        first = np.zeros(len(uk), np.int64)
        first[inv[::-1]] = np.arange(len(inv))[::-1]
        cn = np.asarray(normal, np.float64)[first]
        cn /= np.maximum(np.linalg.norm(cn, axis=1, keepdims=True), 1e-12)
    return cen, uk % nv, inv, cn


def _distinct(views: np.ndarray) -> np.ndarray:
    """Number of distinct values >= 0 in each row of views [M, k]."""
    views = np.sort(views, axis=1)
    return (views[:, :1] >= 0).astype(np.int64).ravel() + np.sum(
        (views[:, 1:] != views[:, :-1]) & (views[:, 1:] >= 0), axis=1)


def multiview_support(xyz: np.ndarray, view: np.ndarray, radius: float, voxel: float, k: int = 32,
                      normal: np.ndarray | None = None, max_angle_deg: float = 180.0) -> np.ndarray:
    """Number of images that put a plane point within ``radius`` of each point (its own included),
    with a plane normal within ``max_angle_deg`` of the point's own (when ``normal`` [N, 3] is given).

    Planes found independently in several images agree where they are right; a wrong plane (a bad
    anchor, a region straddling two surfaces) is rarely repeated by other images. Position alone is
    a weak test: the planes of different images that cut a curved surface, or that are tilted
    through a wall and an object in front of it, cross each other near the surface, and every
    crossing band would count as support. Two planes of one surface agree in orientation too.
    Points are first merged per (voxel, image), with the normal of the first point there; the count
    looks at the ``k`` nearest merged points, so it saturates near k / (points one image puts within
    ``radius``). xyz: [N, 3], view: [N]. Returns [N] int."""
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, np.float64)
    if len(xyz) == 0:
        return np.zeros(0, np.int64)
    if normal is not None and np.shape(normal) != xyz.shape:
        raise ValueError(f"normal must be {xyz.shape}, got {np.shape(normal)}")
    cen, cview, inv, cn = _merge_per_view(xyz, np.asarray(view, np.int64), voxel, normal)
    kk = min(k, len(cen))
    dist, nn = cKDTree(cen).query(cen, k=kk, distance_upper_bound=radius)
    nn = np.minimum(nn.reshape(len(cen), kk), len(cen) - 1)
    valid = np.isfinite(dist.reshape(len(cen), kk))
    if cn is not None and max_angle_deg < 180.0:
        valid &= np.abs(np.einsum("mj,mkj->mk", cn, cn[nn])) >= np.cos(np.radians(max_angle_deg))
    return _distinct(np.where(valid, cview[nn], -1))[inv]


def multiview_conflict(xyz: np.ndarray, view: np.ndarray, normal: np.ndarray, radius: float,
                       offset: float, max_angle_deg: float, voxel: float, k: int = 64
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Images whose planes agree / disagree with each point (a majority vote of the images).

    Within ``radius`` of a point X with normal n, another image's plane point Y agrees when it lies
    on the same plane -- angle(n, n_Y) <= ``max_angle_deg`` and |n·(Y − X)| <= ``offset`` -- and
    disagrees otherwise. Agreement alone can be had by a wrong plane that several images repeat
    (they share an anchor off the surface); images whose planes put the surface elsewhere there
    are evidence against it. Points are merged per (voxel, image) first; the vote is over the
    images among the ``k`` nearest merged points (a sample of the images when more are near).
    xyz, normal: [N, 3]; view: [N]. Returns (agreeing images [N], disagreeing images [N]); the
    point's own image agrees."""
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, np.float64)
    if len(xyz) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if np.shape(normal) != xyz.shape:
        raise ValueError(f"normal must be {xyz.shape}, got {np.shape(normal)}")
    cen, cview, inv, cn = _merge_per_view(xyz, np.asarray(view, np.int64), voxel, normal)
    kk = min(k, len(cen))
    dist, nn = cKDTree(cen).query(cen, k=kk, distance_upper_bound=radius)
    nn = np.minimum(nn.reshape(len(cen), kk), len(cen) - 1)
    valid = np.isfinite(dist.reshape(len(cen), kk))
    same = (np.abs(np.einsum("mj,mkj->mk", cn, cn[nn])) >= np.cos(np.radians(max_angle_deg))) \
        & (np.abs(np.einsum("mj,mkj->mk", cn, cen[nn] - cen[:, None])) <= offset)
    agree = _distinct(np.where(valid & same, cview[nn], -1))
    disagree = _distinct(np.where(valid & ~same, cview[nn], -1))
    return agree[inv], disagree[inv]


def merge_plane_points(centers: np.ndarray, cfg: PlaneConfig, xyz: list, rgb: list, nrm: list, pid: list,
                       planes: list, plane_view: list
                       ) -> tuple[CueCloud, dict[str, int], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """All images' plane points -> fused planes (optional) -> multi-view support and vote -> voxel
    grid -> PLANE cloud. centers: [V, 3] camera centres; the lists hold one array per image
    (points, colours, normals, plane ids, planes, the view of each plane). Returns (the cloud,
    rejections, (the kept points before the voxel grid [M, 3], their plane normals [M, 3], the view
    that made each [M]): the plane anchors of geocues.plane_anchors)."""
    rej: dict[str, int] = {}
    if not xyz:
        return CueCloud.empty(), rej, (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
    X, C, N = np.concatenate(xyz), np.concatenate(rgb), np.concatenate(nrm)
    P, PL, PV = np.concatenate(pid), np.concatenate(planes), np.concatenate(plane_view)
    if cfg.fuse_planes and len(PL):
        X, N, cluster_views = consolidate_planes(X, P, PL, PV, centers, cfg.fuse_angle_deg,
                                                 cfg.fuse_dist, cfg.min_ray_cos)
        lone = cluster_views < cfg.min_plane_views
        if lone.any():
            rej["points_on_planes_seen_in_too_few_images"] = int(lone.sum())
            X, C, N, P = X[~lone], C[~lone], N[~lone], P[~lone]
    view = PV[P]
    drop = np.zeros(len(X), bool)  # multi-view consistency of the planes of different images:
    if cfg.min_views > 1:  # enough images put the same plane there ...
        few = multiview_support(X, view, cfg.support_radius, cfg.voxel_size, normal=N,
                                max_angle_deg=cfg.support_angle_deg) < cfg.min_views
        rej["points_seen_by_fewer_images"] = int(few.sum())
        drop |= few
    if cfg.conflict_radius > 0:  # ... and no more images put the surface elsewhere (votes of all images)
        agree, disagree = multiview_conflict(X, view, N, cfg.conflict_radius, cfg.support_radius,
                                             cfg.support_angle_deg, cfg.voxel_size)
        rej["points_outvoted_by_other_images"] = int((~drop & (agree < disagree)).sum())
        drop |= agree < disagree
    X, C, N, view = X[~drop], C[~drop], N[~drop], view[~drop]
    vx, vc, vn, nv = voxel_downsample(X, C, N, view, cfg.voxel_size)
    cloud = CueCloud.make(vx, vc, CueType.PLANE, normal=vn, confidence=np.minimum(1.0, nv / 3.0))
    return cloud, rej, (X, N, view)
