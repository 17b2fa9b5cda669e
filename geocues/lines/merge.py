"""Line tracks: link 2D segments through their best hypotheses, fit one 3D line per track to all
its segment planes (weighted least squares, vectorised over tracks), drop outlier segments,
refine endpoints from all supports, merge duplicate 3D lines, colour and sample them.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from geocues.lines.config import LineConfig

log = logging.getLogger(__name__)

FIT_ITERS = 3
MIN_RAY_LINE_ANGLE_DEG = 2.0  # endpoint rays closer than this to the 3D line do not set its extent


class Views:
    """Stacked intrinsics/extrinsics of all cameras, for per-member vectorised projection."""

    def __init__(self, cameras: list):
        self.cameras = cameras
        self.K = np.stack([c.K for c in cameras])  # [V, 3, 3]
        self.R = np.stack([c.R for c in cameras])  # [V, 3, 3]
        self.t = np.stack([c.t for c in cameras])  # [V, 3]
        self.C = np.stack([c.center for c in cameras])  # [V, 3]
        self.width = np.array([c.width for c in cameras], np.float64)  # [V]

    def rays(self, uv: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit world directions [M, 3] of the rays through pixels uv [M, 2] of views v [M]."""
        K = self.K[v]
        x = np.stack([(uv[:, 0] - K[:, 0, 2]) / K[:, 0, 0], (uv[:, 1] - K[:, 1, 2]) / K[:, 1, 1],
                      np.ones(len(uv))], -1)
        r = np.einsum("mji,mj->mi", self.R[v], x)  # R^T x
        return r / np.linalg.norm(r, axis=-1, keepdims=True)

    def to_pixels(self, X: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Homogeneous pixels [M, 3] of points X [M, 3] in views v [M]."""
        Xc = np.einsum("mij,mj->mi", self.R[v], X) + self.t[v]
        return np.einsum("mij,mj->mi", self.K[v], Xc)


def consistent_3d(Xa: np.ndarray, Xb: np.ndarray, cfg: LineConfig, depth: np.ndarray) -> np.ndarray:
    """Whether segments Xa, Xb [E, 2, 3] can be the same 3D line: angle <= support_angle_deg and
    b's endpoints within merge_dist_m + link_depth_rel * depth [E] of a's line, [E]."""
    ua = Xa[:, 1] - Xa[:, 0]
    ua /= np.maximum(np.linalg.norm(ua, axis=-1, keepdims=True), 1e-12)
    ub = Xb[:, 1] - Xb[:, 0]
    ub /= np.maximum(np.linalg.norm(ub, axis=-1, keepdims=True), 1e-12)
    ok = np.abs((ua * ub).sum(-1)) >= np.cos(np.deg2rad(cfg.support_angle_deg))
    tol = cfg.merge_dist_m + cfg.link_depth_rel * depth
    for e in (0, 1):
        w = Xb[:, e] - Xa[:, 0]
        perp = np.linalg.norm(w - (w * ua).sum(-1, keepdims=True) * ua, axis=-1)
        ok &= perp <= tol
    return ok


def _greedy_components(n: int, src: np.ndarray, dst: np.ndarray, rank: np.ndarray,
                       node_X: np.ndarray, depth: np.ndarray, cfg: LineConfig) -> np.ndarray:
    """Union-find over edges (best-ranked first) that joins two components only when their
    representatives (the member with the highest ``rank``) are :func:`consistent_3d`, so that
    chains of small steps cannot merge different lines (LIMAP's greedy track building)."""
    parent = np.arange(n)
    rep = np.arange(n)  # representative node of each root

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    order = np.argsort(-(rank[src] + rank[dst]), kind="stable")
    for e in order:
        a, b = find(int(src[e])), find(int(dst[e]))
        if a == b:
            continue
        ra, rb = rep[a], rep[b]
        if not consistent_3d(node_X[[ra]], node_X[[rb]], cfg, depth[[ra]])[0]:
            continue
        if rank[rb] > rank[ra]:
            a, b = b, a
        parent[b] = a  # a keeps the better representative
    return np.array([find(i) for i in range(n)])


def link_tracks(node_X: np.ndarray, node_valid: np.ndarray, node_view: np.ndarray, node_rank: np.ndarray,
                edges: np.ndarray, views: Views, cfg: LineConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """Tracks from the graph of 2D segments (nodes). ``edges`` [E, 2] join a valid node (its best
    hypothesis has >= min_views) to the segments supporting it. Valid-valid edges whose best
    hypotheses agree in 3D join tracks greedily (see :func:`_greedy_components`, ``node_rank``
    [N] orders the nodes, e.g. by supporting views); a track needs ``cfg.min_track_nodes``
    valid nodes, and a non-valid support joins the track(s) of the node(s) it supports.
    Returns (member node ids [M], member track ids [M], number of tracks dropped for too few
    valid nodes)."""
    n = len(node_X)
    valid_idx = np.nonzero(node_valid)[0]
    if len(valid_idx) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), 0
    src, dst = edges[:, 0], edges[:, 1]
    vv = node_valid[dst]
    depth = np.full(n, np.inf)
    depth[valid_idx] = np.linalg.norm(0.5 * (node_X[valid_idx, 0] + node_X[valid_idx, 1])
                                      - views.C[node_view[valid_idx]], axis=-1)
    keep = np.zeros(len(edges), bool)
    if vv.any():
        keep[vv] = consistent_3d(node_X[src[vv]], node_X[dst[vv]], cfg, depth[src[vv]])
    # compact the valid nodes for the union-find
    local = np.full(n, -1, np.int64)
    local[valid_idx] = np.arange(len(valid_idx))
    comp = _greedy_components(len(valid_idx), local[src[keep]], local[dst[keep]], node_rank[valid_idx],
                              node_X[valid_idx], depth[valid_idx], cfg)
    _, comp_of_valid, size = np.unique(comp, return_inverse=True, return_counts=True)
    big = size >= cfg.min_track_nodes
    new_id = np.cumsum(big) - 1
    track = np.full(n, -1, np.int64)
    track[valid_idx] = np.where(big[comp_of_valid], new_id[comp_of_valid], -1)
    leaf = ~vv & (track[src] >= 0)
    mem_node = np.concatenate([valid_idx, dst[leaf]])
    mem_track = np.concatenate([track[valid_idx], track[src[leaf]]])
    keep_m = mem_track >= 0
    pair = np.unique(np.stack([mem_track[keep_m], mem_node[keep_m]], 1), axis=0)  # a node once per track
    return pair[:, 1], pair[:, 0], int((~big).sum())


def _group_sum(values: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n,) + values.shape[1:])
    np.add.at(out, groups, values)
    return out


def fit_lines(mem_track: np.ndarray, normals: np.ndarray, offsets: np.ndarray, weights: np.ndarray,
              P0: np.ndarray, n_tracks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares 3D line of each track from its members' planes n . X = d:
    u = argmin_{|u|=1} sum w^2 (n . u)^2 (smallest eigenvector of A = sum w^2 n n^T), then
    P = argmin sum w^2 (n . P - d)^2 subject to u . P = u . P0. With w in pixels per metre the
    residuals are pixels, so sigma = 1 / sqrt(lambda_2) is the line's worst-direction position
    std (metres) for 1 px of noise. Returns (P [T, 3], u [T, 3], sigma [T])."""
    w2 = weights ** 2
    A = _group_sum(w2[:, None, None] * normals[:, :, None] * normals[:, None, :], mem_track, n_tracks)
    b = _group_sum((w2 * offsets)[:, None] * normals, mem_track, n_tracks)  # [T, 3]
    evals, evecs = np.linalg.eigh(A)  # ascending
    u = evecs[:, :, 0]
    sigma = 1.0 / np.sqrt(np.maximum(evals[:, 1], 1e-30))
    P = np.full((n_tracks, 3), np.nan)
    g = evals[:, 2] > 1e-20  # tracks with members
    scale = evals[g, 2][:, None, None]
    uu = u[g, :, None] * u[g, None, :]
    rhs = b[g] + scale[:, :, 0] * (u[g] * (u[g] * P0[g]).sum(-1, keepdims=True))
    ridge = 1e-9 * scale * np.eye(3)  # keeps single-plane tracks solvable (rejected by spread)
    P[g] = np.linalg.solve(A[g] + scale * uu + ridge, rhs[..., None] + ridge @ P0[g][..., None])[..., 0]
    return P, u, sigma


def plane_angle_groups(mem_track: np.ndarray, normals: np.ndarray, u: np.ndarray, n_tracks: int,
                       min_angle_deg: float) -> np.ndarray:
    """Number of distinct viewpoints per track [T]: the members' planes all contain the line u
    and differ by a rotation theta about it; views whose theta (mod 180 deg) lie within
    ``min_angle_deg`` of each other form one group (near-duplicate frames of a video count once)."""
    if len(mem_track) == 0:
        return np.zeros(n_tracks, np.int64)
    ut = u[mem_track]
    e1 = np.cross(ut, np.where(np.abs(ut[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(ut, e1)
    theta = np.mod(np.arctan2((normals * e2).sum(-1), (normals * e1).sum(-1)), np.pi)
    order = np.lexsort((theta, mem_track))
    tr, th = mem_track[order], theta[order]
    start = np.r_[True, tr[1:] != tr[:-1]]
    nxt = np.r_[th[1:], 0.0]
    last = np.r_[tr[1:] != tr[:-1], True]
    first_of = np.maximum.accumulate(np.where(start, np.arange(len(th)), 0))
    nxt = np.where(last, th[first_of] + np.pi, nxt)  # circular gap from the last to the first
    big = (nxt - th) >= np.deg2rad(min_angle_deg)
    groups = np.bincount(tr[big], minlength=n_tracks)
    present = np.bincount(tr, minlength=n_tracks) > 0
    return np.where(present, np.maximum(groups, 1), 0)


def member_residuals(P: np.ndarray, u: np.ndarray, segs: np.ndarray, view: np.ndarray,
                     views: Views) -> tuple[np.ndarray, np.ndarray]:
    """Largest endpoint distance (pixels) and sine of the angle between each member's 2D segment
    [M, 4] and the projection of its track's line (P, u [M, 3]) in its view [M]."""
    line = np.cross(views.to_pixels(P, view), views.to_pixels(P + u, view))  # [M, 3]
    ln = np.maximum(np.linalg.norm(line[:, :2], axis=-1), 1e-12)
    dist = np.maximum(np.abs(segs[:, 0] * line[:, 0] + segs[:, 1] * line[:, 1] + line[:, 2]),
                      np.abs(segs[:, 2] * line[:, 0] + segs[:, 3] * line[:, 1] + line[:, 2])) / ln
    d = segs[:, 2:] - segs[:, :2]
    sin = np.abs(d[:, 0] * line[:, 0] + d[:, 1] * line[:, 1]) / np.maximum(np.linalg.norm(d, axis=-1) * ln, 1e-12)
    return dist, sin


def endpoint_params(P: np.ndarray, u: np.ndarray, segs: np.ndarray, view: np.ndarray,
                    views: Views) -> tuple[np.ndarray, np.ndarray]:
    """Positions s along each member's line (P + s u) closest to the rays through the member's
    endpoints: s = ((u.r)(r.w) - u.w) / (1 - (u.r)^2), w = P - C. Returns ([M, 2] sorted per
    row, [M] valid: both rays at least MIN_RAY_LINE_ANGLE_DEG off the line and in front)."""
    s = np.empty((len(P), 2))
    ok = np.ones(len(P), bool)
    w = P - views.C[view]
    for e, sl in enumerate((slice(0, 2), slice(2, 4))):
        r = views.rays(segs[:, sl], view)
        b = (u * r).sum(-1)
        den = 1.0 - b * b
        ok &= den >= np.sin(np.deg2rad(MIN_RAY_LINE_ANGLE_DEG)) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            s[:, e] = (b * (r * w).sum(-1) - (u * w).sum(-1)) / den
            t_ray = ((r * w).sum(-1) - b * (u * w).sum(-1)) / den  # position along the ray
        ok &= t_ray > 0
    return np.sort(np.nan_to_num(s), axis=1), ok


def robust_extent(track: np.ndarray, view: np.ndarray, s: np.ndarray, n_tracks: int,
                  min_share: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Extent [lo, hi] per track: the part of the line covered by at least
    k = max(2, ceil(min_share * views)) of its views (k = 1 for a single view), where each view
    covers the union of its members' intervals s [M, 2] (positions along the line). A few
    views whose segments overshoot (a contour, a badly conditioned endpoint ray) cannot stretch
    it. nan for tracks without members; hi <= lo when no part reaches k."""
    lo, hi = np.full(n_tracks, np.nan), np.full(n_tracks, np.nan)
    if len(track) == 0:
        return lo, hi
    V = int(view.max()) + 1
    key, inv = np.unique(track * V + view, return_inverse=True)
    g_track = key // V
    g_lo, g_hi = np.full(len(key), np.inf), np.full(len(key), -np.inf)
    np.minimum.at(g_lo, inv, s[:, 0])
    np.maximum.at(g_hi, inv, s[:, 1])
    n_views = np.bincount(g_track, minlength=n_tracks)
    k = np.where(n_views >= 2, np.maximum(2, np.ceil(min_share * n_views)), 1)
    # sweep: +1 at each view's start, -1 at its end, ordered by position within each track
    ev_t = np.r_[g_track, g_track]
    ev_pos = np.r_[g_lo, g_hi]
    ev_d = np.r_[np.ones(len(key)), -np.ones(len(key))]
    order = np.lexsort((-ev_d, ev_pos, ev_t))  # starts before ends at equal positions
    ev_t, ev_pos, ev_d = ev_t[order], ev_pos[order], ev_d[order]
    cum = np.cumsum(ev_d)
    start = np.r_[0, np.nonzero(ev_t[1:] != ev_t[:-1])[0] + 1]
    base = np.repeat(cum[start] - ev_d[start], np.diff(np.r_[start, len(ev_t)]))
    after = cum - base  # coverage just after each event
    before = after - ev_d
    need = k[ev_t]
    lo_cand = np.where(after >= need, ev_pos, np.inf)
    hi_cand = np.where(before >= need, ev_pos, -np.inf)
    lo_t = np.full(n_tracks, np.inf)
    hi_t = np.full(n_tracks, -np.inf)
    np.minimum.at(lo_t, ev_t, lo_cand)
    np.maximum.at(hi_t, ev_t, hi_cand)
    has = n_views > 0
    lo[has], hi[has] = lo_t[has], hi_t[has]
    return lo, hi


def duplicate_pairs(seg3d: np.ndarray, cfg: LineConfig) -> np.ndarray:
    """Pairs [Q, 2] of 3D segments [L, 2, 3] that are duplicates: angle <= merge_angle_deg, the
    shorter's endpoints within merge_dist_m of the longer's line and a gap along it <= merge_gap_m.
    Candidates come from a k-d tree of samples, so the cost grows with the total length."""
    L = len(seg3d)
    if L < 2:
        return np.zeros((0, 2), np.int64)
    step = max(cfg.merge_dist_m, 0.02)
    length = np.linalg.norm(seg3d[:, 1] - seg3d[:, 0], axis=-1)
    n = np.maximum(2, np.ceil(length / step).astype(np.int64) + 1)
    owner = np.repeat(np.arange(L), n)
    t = np.concatenate([np.linspace(0.0, 1.0, k) for k in n])
    pts = seg3d[owner, 0] + t[:, None] * (seg3d[owner, 1] - seg3d[owner, 0])
    pp = cKDTree(pts).query_pairs(r=cfg.merge_gap_m + step, output_type="ndarray")
    if len(pp) == 0:
        return np.zeros((0, 2), np.int64)
    cand = np.unique(np.sort(np.stack([owner[pp[:, 0]], owner[pp[:, 1]]], 1), axis=1), axis=0)
    cand = cand[cand[:, 0] != cand[:, 1]]
    longer = np.where(length[cand[:, 0]] >= length[cand[:, 1]], cand[:, 0], cand[:, 1])
    shorter = np.where(longer == cand[:, 0], cand[:, 1], cand[:, 0])
    A, B = seg3d[longer], seg3d[shorter]
    ua = (A[:, 1] - A[:, 0]) / np.maximum(length[longer], 1e-12)[:, None]
    ub = (B[:, 1] - B[:, 0]) / np.maximum(length[shorter], 1e-12)[:, None]
    ok = np.abs((ua * ub).sum(-1)) >= np.cos(np.deg2rad(cfg.merge_angle_deg))
    tb = np.empty((len(cand), 2))
    for e in (0, 1):
        w = B[:, e] - A[:, 0]
        tb[:, e] = (w * ua).sum(-1)
        ok &= np.linalg.norm(w - tb[:, e:e + 1] * ua, axis=-1) <= cfg.merge_dist_m
    gap = np.maximum(tb.min(1) - length[longer], -tb.max(1))  # > 0: apart along the line
    ok &= gap <= cfg.merge_gap_m
    return cand[ok]


def sample_segments(seg3d: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every <= ``step`` metres along segments [L, 2, 3], endpoints included.
    Returns (points [P, 3], line index [P])."""
    if len(seg3d) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    length = np.linalg.norm(seg3d[:, 1] - seg3d[:, 0], axis=-1)
    n = np.maximum(2, np.ceil(length / step).astype(np.int64) + 1)
    line = np.repeat(np.arange(len(seg3d)), n)
    t = np.concatenate([np.linspace(0.0, 1.0, k) for k in n])
    return seg3d[line, 0] + t[:, None] * (seg3d[line, 1] - seg3d[line, 0]), line


def member_planes(segs: np.ndarray, view: np.ndarray, views: Views) -> tuple[np.ndarray, np.ndarray]:
    """Planes (unit normals [M, 3], offsets [M]) of 2D segments [M, 4] seen from views [M]."""
    n = np.cross(views.rays(segs[:, :2], view), views.rays(segs[:, 2:], view))
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-15)
    return n, (n * views.C[view]).sum(-1)


def refine_tracks(mem_track: np.ndarray, mem_view: np.ndarray, mem_segs: np.ndarray,
                  P0: np.ndarray, u0: np.ndarray, views: Views,
                  cfg: LineConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Alternate inlier selection (members within support_dist_px and support_angle_deg of the
    projected line) and :func:`fit_lines` with pixel weights w = f / (z |n_xy|) (pixels per
    metre off the plane), FIT_ITERS times, from lines (P0, u0) [T, 3]. A refit is refused when
    it is ill-conditioned (sigma for 1 px at reference_width > max_line_sigma_m) or turns the line by more than
    support_angle_deg: a track whose inliers shrink to one plane group could otherwise rotate
    freely inside that plane. Returns (P, u, inlier [M], sigma [T] (inf: never fitted),
    distinct viewpoints [T] (see :func:`plane_angle_groups`))."""
    T = len(P0)
    P, u = P0.copy(), u0 / np.linalg.norm(u0, axis=-1, keepdims=True)
    normals, offsets = member_planes(mem_segs, mem_view, views)
    n_cam = np.einsum("mij,mj->mi", views.R[mem_view], normals)  # camera-frame plane normals
    n_xy = np.maximum(np.linalg.norm(n_cam[:, :2], axis=-1), 0.1)
    tol = cfg.support_dist_px * views.width[mem_view] / cfg.reference_width
    sin_tol = np.sin(np.deg2rad(cfg.support_angle_deg))
    sigma = np.full(T, np.inf)
    inlier = np.zeros(len(mem_track), bool)
    for it in range(FIT_ITERS + 1):
        dist, sin = member_residuals(P[mem_track], u[mem_track], mem_segs, mem_view, views)
        inlier = (dist <= tol) & (sin <= sin_tol)
        if it == FIT_ITERS:
            break
        z = np.abs(views.to_pixels(P[mem_track], mem_view)[:, 2])
        w = views.K[mem_view, 0, 0] / (np.clip(z, 0.1, cfg.max_depth_m) * n_xy)
        n_in = np.bincount(mem_track[inlier], minlength=T)
        P_new, u_new, sigma_new = fit_lines(mem_track[inlier], normals[inlier], offsets[inlier],
                                            w[inlier], P, T)
        ok = (n_in >= 2) & np.isfinite(P_new).all(1) & np.isfinite(u_new).all(1)
        width = np.bincount(mem_track, weights=views.width[mem_view], minlength=T) / np.maximum(
            np.bincount(mem_track, minlength=T), 1)  # mean image width per track
        sigma_ref = sigma_new * width / cfg.reference_width  # std for 1 px at reference_width
        ok &= (sigma_ref <= cfg.max_line_sigma_m) & (np.abs((u_new * u).sum(-1)) >= np.cos(np.deg2rad(cfg.support_angle_deg)))
        P[ok], u[ok], sigma[ok] = P_new[ok], u_new[ok], sigma_new[ok]
    groups = plane_angle_groups(mem_track[inlier], normals[inlier], u, T, cfg.min_tri_angle_deg)
    return P, u, inlier, sigma, groups


def ray_angle_views(mem_track: np.ndarray, mem_view: np.ndarray, mem_segs: np.ndarray, u: np.ndarray,
                    mask: np.ndarray, views: Views, min_angle_deg: float) -> np.ndarray:
    """Per track [T], the number of distinct views (among members in ``mask``) that see its
    line at least ``min_angle_deg`` away from the viewing ray through the segment's midpoint
    (LIMAP's sensitivity = 90 - that angle); a line seen end-on cannot be located."""
    T = len(u)
    m = np.nonzero(mask)[0]
    if len(m) == 0:
        return np.zeros(T, np.int64)
    r = views.rays(0.5 * (mem_segs[m, :2] + mem_segs[m, 2:]), mem_view[m])
    ok = np.abs((r * u[mem_track[m]]).sum(-1)) <= np.cos(np.deg2rad(min_angle_deg))
    V = len(views.cameras)
    key = np.unique(mem_track[m][ok] * V + mem_view[m][ok])
    return np.bincount(key // V, minlength=T)
