"""Multi-view scoring of two-view line hypotheses: support by 2D segments of the other neighbour
views (angle, perpendicular distance, depth consistency), and the best hypothesis per 2D segment.

Candidate supporting segments are found through a per-image label map (segment ids drawn as
thick lines), so scoring costs a few lookups per hypothesis and view, not a loop over segments.
"""

from __future__ import annotations

import cv2
import numpy as np

from geocues.lines.config import LineConfig
from geocues.lines.detect import segment_lengths
from geocues.lines.triangulate import ray_plane_depth, segment_planes

N_SAMPLES = 12  # points per projected hypothesis looked up in a label map


class LabelMaps:
    """Per image: a uint16 map (0 = no segment, k + 1 = segment k) with every segment drawn
    ``2 * support_dist_px + 1`` pixels thick (longest drawn last), and the segments' planes."""

    def __init__(self, segments: list, cameras: list, cfg: LineConfig):
        self.segments, self.cameras, self.cfg = segments, cameras, cfg
        self._maps: dict[int, np.ndarray] = {}
        self._planes: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def label_map(self, k: int) -> np.ndarray:
        if k not in self._maps:
            cam, segs = self.cameras[k], self.segments[k].segs
            if len(segs) >= np.iinfo(np.uint16).max:
                raise ValueError(f"too many segments in image {k}: {len(segs)}")
            lab = np.zeros((cam.height, cam.width), np.uint16)
            thick = max(1, int(round(2 * self.cfg.px(self.cfg.support_dist_px, cam.width))) + 1)
            for s in np.argsort(segment_lengths(segs), kind="stable"):  # longest drawn last
                x1, y1, x2, y2 = np.floor(segs[s]).astype(int)  # COLMAP pixel -> index
                cv2.line(lab, (int(x1), int(y1)), (int(x2), int(y2)), int(s) + 1, thick)
            self._maps[k] = lab
        return self._maps[k]

    def planes(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        if k not in self._planes:
            self._planes[k] = segment_planes(self.segments[k].segs, self.cameras[k])
        return self._planes[k]


def _informative(X: np.ndarray, Ci: np.ndarray, cam_k, n: np.ndarray, tol: float, cfg: LineConfig) -> np.ndarray:
    """Whether view k can tell the depths of X's endpoints [M, 2, 3] (on rays from Ci) apart
    from a relative error of support_depth_rel, given the plane (normal n [M, 3]) through C_k
    that should contain X: the error must move the endpoints >= tol pixels off that plane's
    image line, f_k s sin(a) rel / z_k >= tol, and the ray-plane angle a >= min_tri_angle_deg."""
    ok = np.ones(len(X), bool)
    for e in (0, 1):
        r = X[:, e] - Ci
        s = np.linalg.norm(r, axis=-1)
        sin_a = np.abs((r * n).sum(-1)) / np.maximum(s, 1e-12)
        z_k = np.maximum((X[:, e] @ cam_k.R.T + cam_k.t)[:, 2], 1e-6)
        ok &= (sin_a >= np.sin(np.deg2rad(cfg.min_tri_angle_deg)))
        ok &= cam_k.K[0, 0] * s * sin_a * cfg.support_depth_rel / z_k >= tol
    return ok


def support_in_view(X: np.ndarray, cam_i, cam_k, segs_k: np.ndarray, lab_k: np.ndarray,
                    planes_k: tuple[np.ndarray, np.ndarray],
                    cfg: LineConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which hypotheses X [H, 2, 3] (endpoints on the rays of view i) are supported in view k.

    A segment c of k is consistent with X when (1) it lies under a sample of X's projection in
    the label map, (2) its angle to the projected line is <= support_angle_deg, (3) both its
    endpoints are within support_dist_px of the projected line, and (4) depth consistency: the
    rays of X's endpoints from C_i meet c's plane at depths within support_depth_rel of X's.
    X is *checkable* in k when at least half its samples project inside the image and k can
    tell depths apart (:func:`_informative`); it is *supported* when, in addition, consistent
    segments cover >= support_coverage of its samples inside the image.
    Returns (supported [H], supporting segment [H] (most samples; -1 where none), checkable [H])."""
    H = len(X)
    sup, best = np.zeros(H, bool), np.full(H, -1, np.int64)
    if H == 0:
        return sup, best, np.zeros(H, bool)
    t = (np.arange(N_SAMPLES) + 0.5) / N_SAMPLES
    P = X[:, :1] + t[None, :, None] * (X[:, 1:] - X[:, :1])  # [H, S, 3]
    uv, z = cam_k.project(P.reshape(-1, 3))
    uv, z = uv.reshape(H, N_SAMPLES, 2), z.reshape(H, N_SAMPLES)
    inside = (z > 1e-6) & (uv[..., 0] >= 0) & (uv[..., 0] < cam_k.width) & (uv[..., 1] >= 0) & (uv[..., 1] < cam_k.height)
    n_inside = inside.sum(1)
    tol = cfg.px(cfg.support_dist_px, cam_k.width)
    Ck, Ci = cam_k.center, cam_i.center
    n_own = np.cross(X[:, 0] - Ck, X[:, 1] - Ck)  # plane through C_k and X
    n_own /= np.maximum(np.linalg.norm(n_own, axis=-1, keepdims=True), 1e-15)
    checkable = (n_inside >= N_SAMPLES // 2) & _informative(X, Ci, cam_k, n_own, tol, cfg)
    if len(segs_k) == 0 or not checkable.any():
        return sup, best, checkable
    col = np.clip(np.nan_to_num(np.floor(uv[..., 0]), nan=0).astype(np.int64), 0, cam_k.width - 1)
    row = np.clip(np.nan_to_num(np.floor(uv[..., 1]), nan=0).astype(np.int64), 0, cam_k.height - 1)
    cand = np.where(inside & checkable[:, None], lab_k[row, col].astype(np.int64) - 1, -1)  # [H, S]
    h_idx, s_idx = np.nonzero(cand >= 0)
    if len(h_idx) == 0:
        return sup, best, checkable
    base = len(segs_k) + 1
    key, inv, hits = np.unique(h_idx * base + cand[h_idx, s_idx], return_inverse=True, return_counts=True)
    h_idx, c = key // base, key % base  # unique (hypothesis, segment) candidates
    # projected infinite line of each hypothesis in k (homogeneous; fine with a point behind)
    x = (X[h_idx] @ cam_k.R.T + cam_k.t) @ cam_k.K.T  # [M, 2, 3] homogeneous pixels
    line = np.cross(x[:, 0], x[:, 1])  # [M, 3]
    ln = np.linalg.norm(line[:, :2], axis=-1)
    seg = segs_k[c]  # [M, 4]
    with np.errstate(invalid="ignore", divide="ignore"):
        dist = np.maximum(np.abs(seg[:, 0] * line[:, 0] + seg[:, 1] * line[:, 1] + line[:, 2]),
                          np.abs(seg[:, 2] * line[:, 0] + seg[:, 3] * line[:, 1] + line[:, 2])) / ln
        d = seg[:, 2:] - seg[:, :2]
        sin = np.abs(d[:, 0] * line[:, 0] + d[:, 1] * line[:, 1]) / (np.linalg.norm(d, axis=-1) * ln)
    ok = (np.nan_to_num(dist, nan=np.inf) <= tol)
    ok &= np.nan_to_num(sin, nan=1.0) <= np.sin(np.deg2rad(cfg.support_angle_deg))
    n_c, d_c = planes_k[0][c], planes_k[1][c]
    for e in (0, 1):  # depth consistency along the source rays
        r = X[h_idx, e] - Ci
        s_h = np.linalg.norm(r, axis=-1)
        s_c = ray_plane_depth(Ci, r / np.maximum(s_h, 1e-12)[:, None], n_c, d_c)
        ok &= np.abs(np.nan_to_num(s_c, nan=np.inf) - s_h) <= cfg.support_depth_rel * s_h
    if not ok.any():
        return sup, best, checkable
    covered = np.bincount(h_idx[ok], weights=hits[ok], minlength=H)  # samples on consistent segments
    sup = checkable & (covered >= cfg.support_coverage * np.maximum(n_inside, 1))
    h_ok, c_ok, hits_ok = h_idx[ok], c[ok], hits[ok]
    order = np.lexsort((-hits_ok, h_ok))  # per hypothesis, the segment under the most samples first
    h_ok, c_ok = h_ok[order], c_ok[order]
    first = np.r_[True, h_ok[1:] != h_ok[:-1]]
    best[h_ok[first]] = c_ok[first]
    best[~sup] = -1
    return sup, best, checkable


def score_hypotheses(X: np.ndarray, src_view: np.ndarray, i: int, neighbors: np.ndarray,
                     labels: LabelMaps, cfg: LineConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Support of hypotheses X [H, 2, 3] of image i (triangulated with views src_view [H]) in the
    neighbour views [K] of i. Returns (n_views [H] = 2 + number of supporting neighbours,
    n_checkable [H] = 2 + number of neighbours where X is checkable, support [H, K] supporting
    segment per neighbour, -1 where none; a hypothesis' own partner view is not counted)."""
    H, K = len(X), len(neighbors)
    support = np.full((H, K), -1, np.int64)
    n_check = np.full(H, 2, np.int64)
    cam_i = labels.cameras[i]
    for col, k in enumerate(neighbors):
        rows = np.nonzero(src_view != k)[0]
        if len(rows) == 0:
            continue
        sup, best, checkable = support_in_view(X[rows], cam_i, labels.cameras[k], labels.segments[k].segs,
                                               labels.label_map(int(k)), labels.planes(int(k)), cfg)
        support[rows[sup], col] = best[sup]
        n_check[rows] += checkable
    return 2 + (support >= 0).sum(1), n_check, support


def best_per_segment(seg_ids: np.ndarray, n_views: np.ndarray, ratio: np.ndarray, n_segments: int) -> np.ndarray:
    """Index of the best hypothesis (most supporting views, then highest support ratio, then
    first) for each of ``n_segments`` 2D segments given each hypothesis' segment id [H];
    -1 for none, [n_segments]."""
    best = np.full(n_segments, -1, np.int64)
    if len(seg_ids) == 0:
        return best
    order = np.lexsort((np.arange(len(seg_ids)), -ratio, -n_views, seg_ids))
    s = seg_ids[order]
    first = np.r_[True, s[1:] != s[:-1]]
    best[s[first]] = order[first]
    return best


def collect_supports(seg3d: np.ndarray, labels: LabelMaps, cfg: LineConfig,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Guided matching: project every 3D segment [T, 2, 3] into every view and collect the 2D
    segments consistent with it (under a label-map sample, angle <= support_angle_deg, both
    endpoints within support_dist_px of the projected line), for the views where such segments
    cover >= support_coverage of its projection. Returns (track [M], view [M], segment [M] of
    the supporting segments, n_visible [T] = views where >= half its samples project inside
    and its projection is at least min_length_px long, i.e. where a detector could see it)."""
    T = len(seg3d)
    out_t, out_v, out_c = [], [], []
    n_visible = np.zeros(T, np.int64)
    if T == 0:
        return (np.zeros(0, np.int64),) * 3 + (n_visible,)
    t = (np.arange(N_SAMPLES) + 0.5) / N_SAMPLES
    P = (seg3d[:, :1] + t[None, :, None] * (seg3d[:, 1:] - seg3d[:, :1])).reshape(-1, 3)  # [T*S, 3]
    sin_tol = np.sin(np.deg2rad(cfg.support_angle_deg))
    for v, cam in enumerate(labels.cameras):
        uv, z = cam.project(P)
        uv, z = uv.reshape(T, N_SAMPLES, 2), z.reshape(T, N_SAMPLES)
        inside = (z > 1e-6) & (uv[..., 0] >= 0) & (uv[..., 0] < cam.width) & (uv[..., 1] >= 0) & (uv[..., 1] < cam.height)
        n_in = inside.sum(1)
        proj_len = np.linalg.norm(uv[:, -1] - uv[:, 0], axis=-1) * N_SAMPLES / (N_SAMPLES - 1)
        long_enough = proj_len >= cfg.px(cfg.min_length_px, cam.width)
        rows = np.nonzero((n_in >= N_SAMPLES // 2) & np.nan_to_num(long_enough))[0]
        n_visible[rows] += 1
        segs = labels.segments[v].segs
        if len(rows) == 0 or len(segs) == 0:
            continue
        lab = labels.label_map(v)
        col = np.clip(np.floor(uv[rows, :, 0]).astype(np.int64), 0, cam.width - 1)
        row = np.clip(np.floor(uv[rows, :, 1]).astype(np.int64), 0, cam.height - 1)
        cand = np.where(inside[rows], lab[row, col].astype(np.int64) - 1, -1)  # [R, S]
        r_idx, s_idx = np.nonzero(cand >= 0)
        if len(r_idx) == 0:
            continue
        base = len(segs) + 1
        key, hits = np.unique(r_idx * base + cand[r_idx, s_idx], return_counts=True)
        r_idx, c = key // base, key % base
        x = (seg3d[rows[r_idx]] @ cam.R.T + cam.t) @ cam.K.T  # [M, 2, 3] homogeneous pixels
        line = np.cross(x[:, 0], x[:, 1])
        ln = np.maximum(np.linalg.norm(line[:, :2], axis=-1), 1e-12)
        sg = segs[c]
        dist = np.maximum(np.abs(sg[:, 0] * line[:, 0] + sg[:, 1] * line[:, 1] + line[:, 2]),
                          np.abs(sg[:, 2] * line[:, 0] + sg[:, 3] * line[:, 1] + line[:, 2])) / ln
        d = sg[:, 2:] - sg[:, :2]
        sin = np.abs(d[:, 0] * line[:, 0] + d[:, 1] * line[:, 1]) / np.maximum(np.linalg.norm(d, axis=-1) * ln, 1e-12)
        ok = (dist <= cfg.px(cfg.support_dist_px, cam.width)) & (sin <= sin_tol)
        covered = np.bincount(r_idx[ok], weights=hits[ok], minlength=len(rows))
        enough = covered >= cfg.support_coverage * np.maximum(n_in[rows], 1)
        ok &= enough[r_idx]
        out_t.append(rows[r_idx[ok]]), out_v.append(np.full(int(ok.sum()), v)), out_c.append(c[ok])
    if not out_t:
        return (np.zeros(0, np.int64),) * 3 + (n_visible,)
    return np.concatenate(out_t), np.concatenate(out_v), np.concatenate(out_c), n_visible
