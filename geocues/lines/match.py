"""Candidate line matches between two views: epipolar overlap, LBD descriptor ranking, and the
weak epipolar checks of LIMAP (degenerate pairs, triangulation angle, epipolar IoU).

All pair tests are dense [La, Lb] numpy arrays per view pair; there is no Python loop over
segment pairs.
"""

from __future__ import annotations

import numpy as np

from geocues.lines.config import LineConfig


def skew(v: np.ndarray) -> np.ndarray:
    """[v]_x, the 3x3 cross-product matrix of v [3]."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def fundamental(cam_i, cam_j) -> np.ndarray:
    """Fundamental matrix F [3, 3] with x_j^T F x_i = 0 (COLMAP pixels):
    F = K_j^-T [t_ji]_x R_ji K_i^-1, R_ji = R_j R_i^T, t_ji = t_j - R_ji t_i."""
    R = cam_j.R @ cam_i.R.T
    t = cam_j.t - R @ cam_i.t
    return np.linalg.inv(cam_j.K).T @ skew(t) @ R @ np.linalg.inv(cam_i.K)


def homog(pts: np.ndarray) -> np.ndarray:
    """[..., 2] -> [..., 3] homogeneous pixels."""
    return np.concatenate([pts, np.ones(pts.shape[:-1] + (1,))], axis=-1)


def epipolar_iou(segs_a: np.ndarray, segs_b: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Epipolar IoU [La, Lb] in view b (LIMAP ``compute_epipolar_IoU``).

    The epipolar lines l = F p of a's endpoints p1, p2 cut b's line q(c) = q1 + c (q2 - q1) at
    c = -(l . q1~) / (l_xy . (q2 - q1)) (two matrix products); with c1 <= c2 the IoU is
    (min(c2, 1) - max(c1, 0)) / (max(c2, 1) - min(c1, 0)). Pairs whose cuts are undefined
    (b parallel to the epipolar lines) get -inf."""
    q1h = homog(segs_b[:, :2])  # [Lb, 3]
    d = segs_b[:, 2:] - segs_b[:, :2]  # [Lb, 2]
    cuts = []
    for p in (segs_a[:, :2], segs_a[:, 2:]):
        lines = homog(p) @ F.T  # [La, 3] epipolar lines in b
        with np.errstate(divide="ignore", invalid="ignore"):
            cuts.append(-(lines @ q1h.T) / (lines[:, :2] @ d.T))  # [La, Lb]
    lo, hi = np.minimum(*cuts), np.maximum(*cuts)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = (np.minimum(hi, 1.0) - np.maximum(lo, 0.0)) / (np.maximum(hi, 1.0) - np.minimum(lo, 0.0))
    return np.where(np.isfinite(iou), iou, -np.inf)


def epipolar_angle(segs: np.ndarray, epipole: np.ndarray) -> np.ndarray:
    """Angle (degrees, [N]) between each segment [N, 4] and the epipolar line through its
    midpoint (the line joining the midpoint and the homogeneous ``epipole`` [3])."""
    mid = homog(0.5 * (segs[:, :2] + segs[:, 2:]))  # [N, 3]
    ep = np.cross(mid, epipole[None])  # [N, 3] epipolar lines
    ep_dir = np.stack([ep[:, 1], -ep[:, 0]], -1)
    d = segs[:, 2:] - segs[:, :2]
    num = np.abs(d[:, 0] * ep_dir[:, 1] - d[:, 1] * ep_dir[:, 0])
    den = np.linalg.norm(d, axis=-1) * np.linalg.norm(ep_dir, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(den > 1e-12, num / den, 0.0)  # epipole on the segment: degenerate
    return np.degrees(np.arcsin(np.clip(s, 0.0, 1.0)))


def hamming(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """Hamming distances [La, Lb] between binary descriptors [La, 32] and [Lb, 32] uint8:
    |a| + |b| - 2 a . b on the unpacked bits (one matrix product)."""
    a = np.unpackbits(desc_a, axis=1).astype(np.float32)  # [La, 256]
    b = np.unpackbits(desc_b, axis=1).astype(np.float32)
    return a.sum(1)[:, None] + b.sum(1)[None, :] - 2.0 * (a @ b.T)


def match_pair(seg_a, seg_b, cam_a, cam_b, cfg: LineConfig) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Candidate matches (ia [M], ib [M]) from view a to view b that pass the weak epipolar
    checks, and the number of candidates rejected per reason.

    Candidates: for each segment of a, the segments of b that overlap its epipolar band
    (IoU > 0 both ways), or, when both lie along the epipolar direction, that lie on its
    epipolar line; ranked by LBD distance (``cfg.matcher == "lbd"``) or epipolar IoU, the best
    ``cfg.topk_matches`` kept. Then rejected in this order: ``parallel_epipolar`` (both segments
    within ``min_epipolar_angle_deg`` of the epipolar direction), ``small_tri_angle`` (LIMAP's
    ray-plane angle < ``min_tri_angle_deg`` either way), ``low_epipolar_iou`` (< ``min_epipolar_iou``
    in either view)."""
    counts = {"candidates": 0, "parallel_epipolar": 0, "small_tri_angle": 0, "low_epipolar_iou": 0}
    A, B = seg_a.segs, seg_b.segs
    empty = np.zeros(0, np.int64)
    if len(A) == 0 or len(B) == 0:
        return empty, empty, counts
    F = fundamental(cam_a, cam_b)  # a -> lines in b
    iou_b = epipolar_iou(A, B, F)  # [La, Lb] in view b
    iou_a = epipolar_iou(B, A, F.T).T  # [La, Lb] in view a
    iou = np.minimum(iou_a, iou_b)
    # epipoles: centre of the other camera projected (homogeneous, may lie at infinity)
    e_a = cam_a.K @ (cam_a.R @ cam_b.center + cam_a.t)
    e_b = cam_b.K @ (cam_b.R @ cam_a.center + cam_b.t)
    deg_a = epipolar_angle(A, e_a) < cfg.min_epipolar_angle_deg  # [La]
    deg_b = epipolar_angle(B, e_b) < cfg.min_epipolar_angle_deg  # [Lb]
    deg = deg_a[:, None] | deg_b[None, :]
    # along the epipolar direction the band collapses to a line: b must lie on a's epipolar line
    band = cfg.px(4.0 * cfg.support_dist_px, cam_b.width)
    l_mid = homog(0.5 * (A[:, :2] + A[:, 2:])) @ F.T  # [La, 3] epipolar lines of a's midpoints
    dist = np.abs(l_mid @ homog(0.5 * (B[:, :2] + B[:, 2:])).T)  # [La, Lb], times |l_xy|
    on_line = dist <= band * np.linalg.norm(l_mid[:, :2], axis=1, keepdims=True)
    cand = np.where(deg_a[:, None] & deg_b[None, :], on_line, (iou > 0) & ~deg)
    if not cand.any():
        return empty, empty, counts
    if cfg.matcher == "lbd":
        cost = hamming(seg_a.desc, seg_b.desc)
    else:
        cost = -np.where(np.isfinite(iou), iou, -1.0)
    cost = np.where(cand, cost, np.inf)
    k = min(cfg.topk_matches, len(B))
    top = np.argpartition(cost, k - 1, axis=1)[:, :k]  # [La, k]
    ia = np.repeat(np.arange(len(A)), k)
    ib = top.ravel()
    keep = np.isfinite(cost[ia, ib])
    ia, ib = ia[keep], ib[keep]
    counts["candidates"] = int(len(ia))
    bad = deg[ia, ib]
    counts["parallel_epipolar"] = int(bad.sum())
    ia, ib = ia[~bad], ib[~bad]
    tri = np.minimum(ray_plane_angle(A[ia], cam_a, B[ib], cam_b),
                     ray_plane_angle(B[ib], cam_b, A[ia], cam_a))
    bad = tri < cfg.min_tri_angle_deg
    counts["small_tri_angle"] = int(bad.sum())
    ia, ib = ia[~bad], ib[~bad]
    bad = iou[ia, ib] < cfg.min_epipolar_iou
    counts["low_epipolar_iou"] = int(bad.sum())
    return ia[~bad], ib[~bad], counts


def ray_plane_angle(segs_a: np.ndarray, cam_a, segs_b: np.ndarray, cam_b) -> np.ndarray:
    """LIMAP's degeneracy angle (degrees, [M]) for matched rows of segs_a and segs_b [M, 4]: the
    smaller, over a's two endpoints, of the angle between the endpoint's viewing ray and the
    plane through segment b and b's camera centre."""
    from geocues.lines.triangulate import pixel_rays, segment_planes

    n_b, _ = segment_planes(segs_b, cam_b)  # [M, 3]
    s = np.minimum(np.abs((pixel_rays(segs_a[:, :2], cam_a) * n_b).sum(-1)),
                   np.abs((pixel_rays(segs_a[:, 2:], cam_a) * n_b).sum(-1)))
    return np.degrees(np.arcsin(np.clip(s, 0.0, 1.0)))
