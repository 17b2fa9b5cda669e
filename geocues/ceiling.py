"""The ceiling as a horizontal plane (an extension; `geocues extract --floor.ceiling`).

A bare ceiling has no texture, no SfM point and, where its junction with the walls shows no edge, no
3D line: no cue reaches it, and the plane stage, which keeps only the prior planes that anchors
confirm, leaves it empty (5.5-8.8 % of the benchmark bare rooms' seen surface, recall 0.13 at 5 cm).
Rooms have level ceilings, so one number places it: :func:`ceiling_height` takes, in each view, the
median height of the aligned prior's horizontal surface above the cameras, and the median of those
over the views (a monocular prior keeps a low-frequency warp after its per-view alignment, which
the views do not share; a few centimetres remain). :func:`ceiling_anchors` then lays a grid of
assumed anchors at that height over the room's footprint (the convex hull of the raised walls'
feet), like the raised walls' rows (geocues.walls): each view's prior plane of a ceiling region is
snapped to them, the regions are cut along the hull's edges at that height (:func:`ceiling_edges`),
and the raised walls stop at the ceiling. With `--floor.level-snap`, :func:`level_plane_points` cuts
a weak region whose prior lies on the ceiling's (or the floor grid's) level plane onto it directly:
a warped prior's plane of a ceiling strip at the top of a few views fails the anchors' check.
"""

from __future__ import annotations

import numpy as np

from geocues.floor import Floor
from geocues.plane_fit import ray_plane_depth

HORIZONTAL_COS = np.cos(np.radians(20.0))  # a surface within 20 degrees of level is horizontal
MIN_PIXELS = 100  # prior pixels (on the every-4th-pixel grid) a view needs on such a surface


def _world_points(cam, depth: np.ndarray) -> np.ndarray:
    """[h, w, 3] world points of a z-depth map of ``cam`` at any resolution (every s-th pixel of
    the image from pixel 0, s = width / w: `geocues extract` keeps every 4th)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w] * (cam.width / w)
    Xc = cam.rays_at(v, u) * depth[..., None]  # camera frame
    return (Xc - np.asarray(cam.t)) @ np.asarray(cam.R)  # R^T (Xc - t), row form


def view_ceiling_height(cam, depth: np.ndarray, up: np.ndarray, floor_height: float, above: float,
                        baseline: int = 2) -> float | None:
    """Median height above the floor of the pixels of the aligned prior ``depth`` [h, w] of ``cam``
    that lie more than ``above`` metres over the floor and on a horizontal surface (normal from the
    depth map's differences ``baseline`` pixels apart, within 20 degrees of ``up``); None with fewer
    than :data:`MIN_PIXELS` such pixels."""
    if min(depth.shape) <= 2 * baseline:
        return None
    X = _world_points(cam, np.where(np.isfinite(depth) & (depth > 0), depth, np.nan))
    b = baseline
    du = X[b:-b, 2 * b:] - X[b:-b, :-2 * b]
    dv = X[2 * b:, b:-b] - X[:-2 * b, b:-b]
    n = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(n @ up) / np.linalg.norm(n, axis=-1)
    height = X[b:-b, b:-b] @ up - floor_height
    sel = np.isfinite(height) & np.isfinite(cos) & (cos >= HORIZONTAL_COS) & (height > above)
    if sel.sum() < MIN_PIXELS:
        return None
    return float(np.median(height[sel]))


def ceiling_height(cameras, priors: dict[int, np.ndarray], up: np.ndarray, floor_height: float,
                   margin: float, min_views: int) -> tuple[float | None, dict]:
    """The ceiling's height above the floor: the median over the views of :func:`view_ceiling_height`
    (horizontal prior surfaces more than ``margin`` above the highest camera), None when fewer than
    ``min_views`` views see one. Returns (height, statistics for the report)."""
    up = np.asarray(up, np.float64)
    cam_top = max(float(np.asarray(c.center) @ up) for c in cameras) - floor_height
    per_view = {}
    for i, depth in priors.items():
        h = view_ceiling_height(cameras[i], np.asarray(depth, np.float64), up, floor_height, cam_top + margin)
        if h is not None:
            per_view[int(i)] = h
    stats = {"views": len(per_view)}
    if len(per_view) < min_views:
        stats["note"] = f"{len(per_view)} views see a ceiling (need {min_views})"
        return None, stats
    hs = np.array(list(per_view.values()))
    height = float(np.median(hs))
    stats.update(height=round(height, 4), spread=round(float(np.percentile(hs, 75) - np.percentile(hs, 25)), 4))
    return height, stats


def _footprint(feet: np.ndarray, basis: np.ndarray):
    """(in-plane coordinates [F, 2] of ``feet``, their Delaunay triangulation or None when they lie
    on one line or are fewer than 3)."""
    from scipy.spatial import Delaunay, QhullError

    uv = np.asarray(feet, np.float64).reshape(-1, 3) @ basis.T
    if len(uv) < 3:
        return uv, None
    try:
        return uv, Delaunay(uv)
    except QhullError:
        return uv, None


def ceiling_edges(feet: np.ndarray, up: np.ndarray, basis: np.ndarray, floor_height: float, height: float
                  ) -> np.ndarray:
    """The edges [E, 2, 3] of the footprint's convex hull (see :func:`ceiling_anchors`) at the
    ceiling: where the walls meet it. A bare junction shows no edge the images' segmentation could
    follow, so one weak region holds a wall and the strip of ceiling above it, too small a share for
    a plane of its own; the plane stage cuts the regions along these as along the 3D lines."""
    from scipy.spatial import ConvexHull

    uv, tri = _footprint(feet, basis)
    if tri is None:
        return np.zeros((0, 2, 3))
    corner = uv[ConvexHull(uv).vertices]  # [E, 2] counter-clockwise, feet along an edge left out
    lift = (floor_height + height) * np.asarray(up, np.float64)
    return np.stack([corner, np.roll(corner, -1, axis=0)], axis=1) @ basis + lift


def ceiling_anchors(feet: np.ndarray, up: np.ndarray, basis: np.ndarray, floor_height: float, height: float,
                    step: float, piece: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A grid (spacing ``step``) at ``height`` above the floor (``up`` . X = floor_height, in-plane
    axes ``basis`` [2, 3]) over the convex hull of ``feet`` [F, 3] (the raised walls' foot points).
    Returns (points [Q, 3], row index [Q]: pieces of ``piece`` points along basis[0]). The plane
    stage counts an assumed row only whole, where all of its points near a region lie on the
    region's prior plane: a row across the whole room would fail on every view whose prior tilts the
    ceiling by its warp, short pieces hold where the prior is near."""
    uv, hull = _footprint(feet, basis)
    if hull is None:  # fewer than 3 feet, or all on one line: no footprint
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    a = np.arange(lo[0] + step / 2, hi[0], step)
    b = np.arange(lo[1] + step / 2, hi[1], step)
    A, B = np.meshgrid(a, b)  # rows: B constant
    grid = np.stack([A.ravel(), B.ravel()], -1)
    row = np.repeat(np.arange(len(b)), len(a)) * (len(a) // piece + 1) + np.tile(np.arange(len(a)) // piece, len(b))
    inside = hull.find_simplex(grid) >= 0
    grid, row = grid[inside], row[inside]
    _, row = np.unique(row, return_inverse=True)
    pts = grid @ basis + (floor_height + height) * np.asarray(up, np.float64)
    return pts, row.astype(np.int64)


def add_level_grids(W: np.ndarray, WL: np.ndarray, up: np.ndarray, floor_height: float, ceiling: float | None,
                    floor_grid: bool, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The raised walls' points ``W`` [Q, 3] and row index ``WL`` [Q] with the ceiling's grid (at
    ``ceiling`` above the floor, when not None) and the floor's (``floor_grid``) appended as further
    rows, and the ceiling's edges [E, 2, 3] that cut the regions. Returns (points, rows, edges,
    {"ceiling_samples", "floor_samples"} for the report)."""
    cuts, stats = np.zeros((0, 2, 3)), {}
    if not len(W):
        return W, WL, cuts, stats
    basis = Floor(np.asarray(up, np.float64), floor_height, 0).basis()
    feet = W
    for name, height in (("ceiling", ceiling), ("floor", 0.0 if floor_grid else None)):
        if height is None:
            continue
        G, GL = ceiling_anchors(feet, up, basis, floor_height, height, step)
        stats[f"{name}_samples"] = len(G)
        W, WL = np.concatenate([W, G]), np.concatenate([WL, GL + int(WL.max()) + 1])
    if ceiling is not None:
        cuts = ceiling_edges(feet, up, basis, floor_height, ceiling)
    return W, WL, cuts, stats


def level_plane_points(cam, rays: np.ndarray, z: np.ndarray, levels: np.ndarray, rel: float,
                       min_share: float = 0.8) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A region's pixels cut onto the level plane its prior lies on (the one holding most), or None.

    ``rays`` [m, 3] (camera frame, z = 1) and prior depths ``z`` [m] of the region's pixels;
    ``levels`` [L, 4] world planes n . X + d = 0. The region lies on a plane when the prior's points
    of at least ``min_share`` of its pixels are within ``rel`` x depth of it (measured along its
    normal: a ceiling seen at a grazing angle moves far along the rays for a small error in height)
    and their rays meet it in front of the camera. Returns (indices of those pixels, their
    camera-frame points on the plane [k, 3], the plane's camera-frame normal [3])."""
    if len(z) == 0:
        return None
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    Xp = rays * z[:, None]  # [m, 3] the prior's points
    best = None  # (share, ok, zk, n_c) of the plane holding most of the pixels (ties: the first)
    for plane in np.asarray(levels, np.float64).reshape(-1, 4):
        n_c = R @ plane[:3]  # n . X + d = 0 with X = R^T (Xc - t): (R n) . Xc + d - (R n) . t = 0
        d_c = float(plane[3] - n_c @ t)
        zk = ray_plane_depth(rays, n_c, d_c)  # [m]
        ok = np.isfinite(zk) & (zk > 0) & (np.abs(Xp @ n_c + d_c) <= rel * z)
        if ok.mean() >= min_share and (best is None or ok.mean() > best[0]):
            best = (ok.mean(), ok, zk, n_c)
    if best is None:
        return None
    _, ok, zk, n_c = best
    keep = np.flatnonzero(ok)
    return keep, rays[keep] * zk[keep, None], n_c
