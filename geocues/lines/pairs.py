"""View pairs for line matching: the overlap of frustum samples (placed at the depths of each
camera's SfM points when it has enough, else at fixed depths), raised by the covisibility of
SfM points where the model has them; weighted by the pair's triangulation angle so that the
near-duplicate frames of a video do not crowd out the pairs that can triangulate.
"""

from __future__ import annotations

import logging

import numpy as np

from geocues.lines.config import LineConfig

log = logging.getLogger(__name__)


def _centers_axes(cams) -> tuple[np.ndarray, np.ndarray]:
    C = np.stack([c.center for c in cams])  # [n, 3]
    axes = np.stack([c.R[2] for c in cams])  # [n, 3] optical axes (world)
    return C, axes


def _pair_angle(X: np.ndarray, Ci: np.ndarray, Cj: np.ndarray) -> np.ndarray:
    """Angle (degrees) at points X [..., 3] between the rays from camera centres Ci and Cj."""
    a, b = X - Ci, X - Cj
    cos = (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def covisibility_scores(scene, cams_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Overlap [n, n] (shared SfM points / fewer of the two) and the triangulation angle [n, n]
    (degrees) at the centroid of the shared points, for the cameras ``cams_idx``."""
    from scipy import sparse

    n, pts = len(cams_idx), scene.points
    rows, cols = [], []
    for r, i in enumerate(cams_idx):
        vis = pts.visible_in.get(int(i), np.zeros(0, np.int64))
        rows.append(np.full(len(vis), r)), cols.append(vis)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    M = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, len(pts)))  # [n, P]
    shared = (M @ M.T).toarray()  # [n, n]
    count = np.diag(shared).copy()
    overlap = shared / np.maximum(np.minimum(count[:, None], count[None, :]), 1.0)
    centroid = np.stack([(M @ sparse.diags(pts.xyz[:, k]) @ M.T).toarray() for k in range(3)], -1)
    centroid = centroid / np.maximum(shared, 1.0)[..., None]  # [n, n, 3]
    C, _ = _centers_axes([scene.cameras[i] for i in cams_idx])
    angle = _pair_angle(centroid, C[:, None], C[None, :])
    np.fill_diagonal(overlap, 0.0)
    return overlap, np.where(shared > 0, angle, 0.0)


def frustum_scores(cams, depths: list[tuple[float, ...]], grid: tuple[int, int] = (8, 6)) -> tuple[np.ndarray, np.ndarray]:
    """Overlap [n, n] (share of frustum samples of each view seen by the other, the smaller of
    the two directions) and the median triangulation angle [n, n] (degrees) at the shared
    samples. Samples: a ``grid`` of pixels at each camera's ``depths`` (z, metres; the same
    number per camera)."""
    n = len(cams)
    C, _ = _centers_axes(cams)
    samples = []
    for cam, cam_depths in zip(cams, depths):
        u = (np.arange(grid[0]) + 0.5) / grid[0] * cam.width
        v = (np.arange(grid[1]) + 0.5) / grid[1] * cam.height
        uu, vv = np.meshgrid(u, v)
        rays = np.stack([(uu.ravel() - cam.K[0, 2]) / cam.K[0, 0],
                         (vv.ravel() - cam.K[1, 2]) / cam.K[1, 1], np.ones(uu.size)], -1)
        Xc = (rays[None] * np.asarray(cam_depths, float)[:, None, None]).reshape(-1, 3)  # z-depths
        samples.append((Xc - cam.t) @ cam.R)  # camera -> world
    X = np.stack(samples)  # [n, S, 3]
    seen = np.zeros((n, n, X.shape[1]), bool)  # [viewer j, source i, sample]
    for j, cam in enumerate(cams):
        uv, z = cam.project(X.reshape(-1, 3))
        ok = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
        seen[j] = ok.reshape(n, -1)
    seen_by = np.transpose(seen, (1, 0, 2))  # [source i, viewer j, S]
    frac = seen_by.mean(-1)
    overlap = np.minimum(frac, frac.T)
    angle = _pair_angle(X[:, None], C[:, None, None], C[None, :, None])  # [i, j, S]
    angle = np.where(seen_by, angle, np.nan)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(angle, axis=-1)
    med = np.nan_to_num(med, nan=0.0)
    np.fill_diagonal(overlap, 0.0)
    return overlap, 0.5 * (med + med.T)


def select_neighbors(scene, cfg: LineConfig, cams_idx: list[int] | None = None) -> tuple[list[np.ndarray], dict]:
    """Up to ``cfg.n_neighbors`` neighbour views per camera (camera indices, best first).

    score(i, j) = overlap(i, j) * min(1, angle(i, j) / good_pair_angle_deg); a pair needs
    overlap >= min_pair_overlap, a triangulation angle >= min_tri_angle_deg and optical axes
    within max_axis_angle_deg. Returns the neighbour lists (indexed like ``scene.cameras``;
    cameras outside ``cams_idx`` get none) and statistics for the report."""
    n_all = len(scene.cameras)
    idx = np.arange(n_all) if cams_idx is None else np.asarray(sorted(cams_idx), np.int64)
    if len(idx) and (idx.min() < 0 or idx.max() >= n_all):
        raise ValueError(f"camera indices must lie in [0, {n_all}), got {idx.min()}..{idx.max()}")
    cams = [scene.cameras[i] for i in idx]
    neighbors = [np.zeros(0, np.int64) for _ in range(n_all)]
    if len(idx) < 2:
        return neighbors, {"source": "none", "pairs": 0, "images_without_neighbors": int(len(idx))}
    # frustum samples at each camera's SfM depths (quartiles, >= 20 points) or at pair_depths_m
    depths, n_sfm = [], 0
    for cam in cams:
        vis = scene.points.visible_in.get(cam.index, np.zeros(0, np.int64)) if len(scene.points) else []
        z = (scene.points.xyz[vis] @ cam.R.T + cam.t)[:, 2] if len(vis) else np.zeros(0)
        z = z[z > 0]
        if len(z) >= 20:
            n_sfm += 1
            q = np.percentile(z, np.linspace(25, 75, len(cfg.pair_depths_m)))
            depths.append(tuple(q))
        else:
            depths.append(tuple(cfg.pair_depths_m))
    overlap, angle = frustum_scores(cams, depths)
    source = f"frustum ({n_sfm} of {len(cams)} cameras at SfM depths)"
    if len(scene.points) and sum(len(v) for v in scene.points.visible_in.values()):
        covis, _ = covisibility_scores(scene, idx)  # shared points can only add overlap
        overlap = np.maximum(overlap, covis)
        source += " + covisibility"
    _, axes = _centers_axes(cams)
    axis_angle = np.degrees(np.arccos(np.clip(axes @ axes.T, -1.0, 1.0)))
    valid = ((overlap >= cfg.min_pair_overlap) & (angle >= cfg.min_tri_angle_deg)
             & (axis_angle <= cfg.max_axis_angle_deg))
    np.fill_diagonal(valid, False)
    score = np.where(valid, overlap * np.minimum(1.0, angle / cfg.good_pair_angle_deg), -1.0)
    n_pairs, lonely = 0, 0
    for r, i in enumerate(idx):
        order = np.argsort(-score[r], kind="stable")[: cfg.n_neighbors]
        order = order[score[r, order] > 0]
        neighbors[i] = idx[order]
        n_pairs += len(order)
        lonely += len(order) == 0
    if lonely:
        log.info("lines: %d of %d images have no neighbour view (overlap >= %.2f, angle >= %.1f deg)",
                 lonely, len(idx), cfg.min_pair_overlap, cfg.min_tri_angle_deg)
    log.info("lines: view pairs from %s, %d directed pairs, %.1f neighbours per image",
             source, n_pairs, n_pairs / max(len(idx), 1))
    return neighbors, {"source": source, "pairs": int(n_pairs), "images_without_neighbors": int(lonely)}
