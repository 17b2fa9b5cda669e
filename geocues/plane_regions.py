"""Region geometry of the plane-like cues: cutting regions along lines, anchors near a region,
occluding-edge and evidence tests, the anchors' image hull. Used by ``geocues.planes``."""

from __future__ import annotations

import numpy as np

from geocues.scene import Camera


def split_regions_by_lines(cam: Camera, regions: np.ndarray, segments: np.ndarray, width_px: float,
                           min_pixels: int) -> np.ndarray:
    """Cut weak regions along the projections of 3D line segments [M, 2, 3] seen by ``cam``:
    lines lie on creases and occluding edges, where one weak region may cover two surfaces (a
    white wall and the floor behind a soft shading edge). Pieces smaller than ``min_pixels`` are
    dropped. Returns new region ids [H, W] (-1 = none)."""
    import cv2

    if regions.max(initial=-1) < 0 or len(segments) == 0:
        return regions
    Xc = np.asarray(segments, np.float64).reshape(-1, 3) @ cam.R.T + cam.t
    a, b = Xc[0::2], Xc[1::2]  # [M, 3] endpoints in the camera frame
    near = 1e-2
    keep = (a[:, 2] > near) | (b[:, 2] > near)
    a, b = a[keep], b[keep]
    for p, q in ((a, b), (b, a)):  # clip each segment to the near plane
        behind = p[:, 2] <= near
        t = (near - p[behind, 2]) / (q[behind, 2] - p[behind, 2])
        p[behind] = p[behind] + t[:, None] * (q[behind] - p[behind])
    K = cam.K
    uv_a = a[:, :2] / a[:, 2:3] * np.diag(K)[:2] + K[:2, 2] - 0.5  # COLMAP -> OpenCV pixel centres
    uv_b = b[:, :2] / b[:, 2:3] * np.diag(K)[:2] + K[:2, 2] - 0.5
    cut = np.zeros(regions.shape, np.uint8)
    th = max(1, int(round(width_px)))
    lim = 4 * max(regions.shape)  # keep cv2's integer coordinates sane
    for (x0, y0), (x1, y1) in zip(np.clip(uv_a, -lim, lim), np.clip(uv_b, -lim, lim)):
        cv2.line(cut, (int(round(x0)), int(round(y0))), (int(round(x1)), int(round(y1))), 1, th)
    out = np.full(regions.shape, -1, np.int32)
    n_out = 0
    for k in range(int(regions.max()) + 1):
        mask = ((regions == k) & (cut == 0)).astype(np.uint8)
        n_cc, cc, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=4)
        for c in range(1, n_cc):
            if stats[c, cv2.CC_STAT_AREA] >= min_pixels:
                out[cc == c] = n_out
                n_out += 1
    return out


def in_anchor_hull(cam: Camera, anchors_c: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                    margin_px: float) -> np.ndarray:
    """[m] True for the pixels (rows, cols) inside the image convex hull of the camera-frame
    anchors [A, 3], grown by ``margin_px``: a plane is interpolated between its anchors, never
    extrapolated beyond them (anchors near a region may sit slightly off its surface)."""
    import cv2

    uv = anchors_c[:, :2] / anchors_c[:, 2:3] * np.diag(cam.K)[:2] + cam.K[:2, 2]  # COLMAP pixels
    lim = 4.0 * max(cam.width, cam.height)
    uv = np.clip(uv, -lim, lim).astype(np.float32)
    hull = cv2.convexHull(uv.reshape(-1, 1, 2))[:, 0].astype(np.float64)  # [V, 2]
    if margin_px > 0:  # grow the polygon by a disc (Minkowski sum, 16-gon): works for thin hulls too
        a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        disc = margin_px * np.stack([np.cos(a), np.sin(a)], axis=1)
        grown = (hull[:, None, :] + disc[None]).reshape(-1, 1, 2).astype(np.float32)
        hull = cv2.convexHull(grown)[:, 0].astype(np.float64)
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull - 0.5).astype(np.int32), 1)
    return mask[rows, cols] > 0


def lines_confirm_plane(X: np.ndarray, groups: np.ndarray, parallel_deg: float = 15.0) -> bool:
    """Whether the lines among anchors X [A, 3] (groups >= 0) are evidence of a plane: two
    non-parallel coplanar lines are (generic 3D lines are skew), and so are three parallel ones;
    two parallel lines are not (any two parallel lines are coplanar)."""
    dirs = []
    for g in np.unique(groups[groups >= 0]):
        P = X[groups == g]
        if len(P) >= 2:
            dirs.append(np.linalg.svd(P - P.mean(axis=0), full_matrices=False)[2][0])
    if len(dirs) < 2:
        return False
    D = np.array(dirs)
    cos = np.abs(D @ D.T)
    if np.any(cos < np.cos(np.radians(parallel_deg))):
        return True
    return len(dirs) >= 3


def on_occluder(cam: Camera, regions: np.ndarray, k: int, depth: np.ndarray, X: np.ndarray,
                 groups: np.ndarray, jump: float, step: int) -> np.ndarray:
    """[a] True for line samples that lie on an occluding edge in front of region ``k``.

    A line next to a region either lies on its surface (a crease or the region's own boundary) or
    on an object in front of it. The prior tells them apart locally, where its low-frequency error
    cancels: at each sample, step ``step`` px to both sides of the projected line; if the side in
    region k is farther than the other side by more than ``jump`` (relative), the line bounds the
    occluder. A line is dropped when most of its samples say so. SfM points (group < 0) are kept."""
    out = np.zeros(len(X), bool)
    h, w = regions.shape
    uv, z = cam.project(X)
    for g in np.unique(groups[groups >= 0]):
        m = np.flatnonzero(groups == g)
        if len(m) < 2:
            continue
        p = uv[m] - 0.5  # COLMAP -> array indices (pixel centres at integers)
        c = p - p.mean(axis=0)
        t = np.linalg.svd(c, full_matrices=False)[2][0]  # 2D direction of the projected line
        nrm = np.array([-t[1], t[0]])
        votes = []
        for sgn in (1.0, -1.0):
            q = np.round(p + sgn * step * nrm).astype(np.int64)
            ok = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
            qq = np.where(ok[:, None], q, 0)
            votes.append((ok & (regions[qq[:, 1], qq[:, 0]] == k), np.where(ok, depth[qq[:, 1], qq[:, 0]], 0.0)))
        (in_a, d_a), (in_b, d_b) = votes
        one_side = in_a ^ in_b
        d_in = np.where(in_a, d_a, d_b)
        d_out = np.where(in_a, d_b, d_a)
        valid = one_side & (d_in > 0) & (d_out > 0)
        if valid.sum() >= 2 and np.mean(d_in[valid] > (1.0 + jump) * d_out[valid]) > 0.5:
            out[m] = True
    return out


def region_pixels(regions: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Strided pixels inside weak regions: (rows [M], cols [M], region id [M])."""
    sub = regions[::stride, ::stride]
    r, c = np.nonzero(sub >= 0)
    return r * stride, c * stride, sub[r, c]


def nearby_anchor_ids(cam: Camera, regions: np.ndarray, n_regions: int, anchors_xyz: np.ndarray,
                       border: int, inside_only: np.ndarray | None = None,
                       depth: np.ndarray | None = None, occl_rel: float = 0.03) -> list[np.ndarray]:
    """For each region, the anchors projecting into it or within ``border`` pixels of it; anchors
    flagged ``inside_only`` [P] (SfM points: they lie on whatever surface they project to, often
    the textured neighbour) count only inside the region. With a ``depth`` map, anchors more than
    ``occl_rel`` behind its surface (occluded) are left out."""
    import cv2

    uv, z = cam.project(anchors_xyz)
    ok = (z > 1e-6) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    idx = np.flatnonzero(ok)
    cols = np.minimum(uv[idx, 0].astype(np.int64), cam.width - 1)  # COLMAP: pixel j is [j, j+1)
    rows = np.minimum(uv[idx, 1].astype(np.int64), cam.height - 1)
    if depth is not None:
        dz = depth[rows, cols]
        vis = (dz <= 0) | (z[idx] <= dz * (1.0 + occl_rel))
        idx, rows, cols = idx[vis], rows[vis], cols[vis]
    out: list[np.ndarray] = []
    strict = np.zeros(len(idx), bool) if inside_only is None else np.asarray(inside_only, bool)[idx]
    own = regions[rows, cols]
    f = 2 if border >= 4 else 1  # dilate at half resolution (4x cheaper, 1 px coarser)
    regions, rows, cols, border = regions[::f, ::f], rows // f, cols // f, border // f
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * border + 1, 2 * border + 1)) \
        if border > 0 else None
    h, w = regions.shape
    for k in range(n_regions):
        rr, cc = np.nonzero(regions == k)
        if len(rr) == 0:
            out.append(idx[:0])
            continue
        # dilate only the region's bounding box (grown by the border): same result, less work
        r0, r1 = max(rr.min() - border, 0), min(rr.max() + border + 1, h)
        c0, c1 = max(cc.min() - border, 0), min(cc.max() + border + 1, w)
        mask = (regions[r0:r1, c0:c1] == k).astype(np.uint8)
        if kernel is not None:
            mask = cv2.dilate(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        inside = (rows >= r0) & (rows < r1) & (cols >= c0) & (cols < c1)
        hit = np.zeros(len(idx), bool)
        hit[inside] = mask[rows[inside] - r0, cols[inside] - c0] > 0
        out.append(idx[hit & (~strict | (own == k))])
    return out
