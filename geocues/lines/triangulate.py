"""Two-view line triangulation: plane-plane intersection, endpoints by back-projection.

A 2D segment (p1, p2) in camera k spans the plane through the camera centre C_k and the two
viewing rays; its world normal is n = (R^T K^-1 p1) x (R^T K^-1 p2) / |.|, offset n . C_k.
The 3D line of a match (a in view i, b in view j) is the intersection of the two planes; its
endpoints are where a's endpoint rays meet b's plane (LIMAP ``triangulate``), so the segment is
asymmetric: its extent is a's.
"""

from __future__ import annotations

import numpy as np

from geocues.lines.config import LineConfig


def pixel_rays(uv: np.ndarray, cam) -> np.ndarray:
    """Unit world directions [N, 3] of the viewing rays through pixels uv [N, 2] (COLMAP)."""
    x = np.stack([(uv[:, 0] - cam.K[0, 2]) / cam.K[0, 0], (uv[:, 1] - cam.K[1, 2]) / cam.K[1, 1],
                  np.ones(len(uv))], -1)  # [N, 3] camera frame, z = 1 (no skew)
    r = x @ cam.R  # camera -> world: R^T x
    return r / np.linalg.norm(r, axis=-1, keepdims=True)


def segment_planes(segs: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray]:
    """Planes of 2D segments [N, 4] in camera ``cam``: unit world normals n [N, 3] and offsets
    d [N] with n . X = d for the points X of the plane (it contains the camera centre)."""
    n = np.cross(pixel_rays(segs[:, :2], cam), pixel_rays(segs[:, 2:], cam))
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-15)
    return n, n @ cam.center


def ray_plane_depth(C: np.ndarray, rays: np.ndarray, n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance s [N] along rays [N, 3] from C [3] (or [N, 3]) to planes n . X = d [N, 3], [N]:
    s = (d - n . C) / (n . r); nan where the ray is parallel to the plane."""
    den = (n * rays).sum(-1)
    num = d - (n * np.broadcast_to(C, rays.shape)).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(den) > 1e-12, num / den, np.nan)


def line_from_planes(n1: np.ndarray, d1: np.ndarray, n2: np.ndarray, d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane-plane intersection: the line X = P + s u of planes n1 . X = d1 and n2 . X = d2
    ([N, 3], [N]). u = n1 x n2 / |n1 x n2|; P = the point of the line nearest the origin,
    P = (d1 (n2 x u) + d2 (u x n1)) / (u . (n1 x n2)). Returns (P [N, 3], u [N, 3]); nan rows
    for parallel planes."""
    c = np.cross(n1, n2)
    norm = np.linalg.norm(c, axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(norm > 1e-12, c / norm, np.nan)
        den = (u * c).sum(-1, keepdims=True)
        P = (d1[:, None] * np.cross(n2, u) + d2[:, None] * np.cross(u, n1)) / den
    return P, u


def triangulate_matches(segs_a: np.ndarray, cam_a, segs_b: np.ndarray, cam_b,
                        cfg: LineConfig) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """3D segments [M, 2, 3] of matched rows of segs_a, segs_b [M, 4]: a's endpoint rays cut by
    b's plane, X_e = C_a + s_e r_e with s_e = (d_b - n_b . C_a) / (n_b . r_e) (see
    :func:`ray_plane_depth`). Returns the segments, the kept-row mask [M] and rejection counts:
    ``behind_camera`` (an endpoint behind either camera), ``too_far`` (> cfg.max_depth_m) and
    ``ray_aligned`` (within cfg.min_ray_angle_deg of the viewing ray in both views)."""
    counts = {"behind_camera": 0, "too_far": 0, "ray_aligned": 0}
    M = len(segs_a)
    if M == 0:
        return np.zeros((0, 2, 3)), np.zeros(0, bool), counts
    n_b, d_b = segment_planes(segs_b, cam_b)
    X = np.empty((M, 2, 3))
    depth_a = np.empty((M, 2))
    for e, sl in enumerate((slice(0, 2), slice(2, 4))):
        r = pixel_rays(segs_a[:, sl], cam_a)
        s = ray_plane_depth(cam_a.center, r, n_b, d_b)
        X[:, e] = cam_a.center + s[:, None] * r
        depth_a[:, e] = s
    z_b = (X.reshape(-1, 3) @ cam_b.R.T + cam_b.t)[:, 2].reshape(M, 2)
    finite = np.isfinite(X).all(axis=(1, 2))
    behind = ~finite | (np.nan_to_num(depth_a, nan=-1.0) <= 1e-6).any(1) | (np.nan_to_num(z_b, nan=-1.0) <= 1e-6).any(1)
    far = ~behind & (np.maximum(depth_a.max(1), z_b.max(1)) > cfg.max_depth_m)
    # LIMAP sensitivity: a line within min_ray_angle_deg of the viewing rays of both views
    u = np.nan_to_num(X[:, 1] - X[:, 0])
    u /= np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-12)
    mid = np.nan_to_num(X.mean(1))
    cos_max = np.cos(np.deg2rad(cfg.min_ray_angle_deg))
    aligned = np.ones(M, bool)
    for C in (cam_a.center, cam_b.center):
        r = mid - C
        r /= np.maximum(np.linalg.norm(r, axis=-1, keepdims=True), 1e-12)
        aligned &= np.abs((u * r).sum(-1)) > cos_max
    aligned &= ~(behind | far)
    counts["behind_camera"], counts["too_far"] = int(behind.sum()), int(far.sum())
    counts["ray_aligned"] = int(aligned.sum())
    return X, ~(behind | far | aligned), counts
