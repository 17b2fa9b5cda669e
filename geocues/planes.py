"""Plane-like cues (paper §4.1): 3D points for weak-texture regions, where SfM finds nothing.

Two modes per image:

* **with a depth prior** (:func:`plane_cues_with_prior`): back-project the region's pixels with the
  aligned prior, find its planes by sequential RANSAC (Open3D ``segment_plane``), keep a plane only
  if the line / SfM cues near the region agree with it, and keep its pixels within ``keep_dist``;
* **prior-free** (:func:`plane_cues_prior_free`): fit one plane to the line / SfM cues that project
  into the region or onto its border and intersect the region's pixel rays with it
  (:func:`ray_plane_depth`).

The points of all images are merged by :func:`voxel_downsample`, which also counts how many images
support each voxel (the cue's confidence). Every rejected region is counted under a reason.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from geocues.scene import Camera

log = logging.getLogger(__name__)


@dataclass
class PlaneConfig:
    """Plane-like cues from weak-texture regions (with or without depth priors)."""

    pixel_stride: int = 2
    """Use every n-th pixel of a region (at 640 px width); the voxel grid thins the rest."""
    voxel_size: float = 0.02
    """Voxel edge (metres) of the final downsampling."""
    min_region_points: int = 100
    """Regions with fewer sampled pixels than this are skipped."""
    cut_px: float = 3.0
    """Cut weak regions along the projected 3D lines seen in the image, this wide (px at 640; 0 = off)."""
    border_px: int = 12
    """Anchors projecting into the region dilated by this many pixels (at 640 px) are 'nearby'."""
    max_depth: float = 20.0
    """Points farther than this from the camera (metres) are dropped."""
    min_ray_cos: float = 0.17
    """Drop pixels whose ray meets the plane at a grazing angle (|cos| below this, ~80 deg)."""
    # ---- with depth priors
    ransac_dist: float = 0.02
    """RANSAC inlier distance (metres) of the planes fitted to the back-projected prior."""
    max_planes: int = 3
    """At most this many planes per region (sequential RANSAC)."""
    min_plane_frac: float = 0.2
    """A plane must hold at least this fraction of the region's pixels."""
    keep_dist: float = 0.02
    """Keep back-projected points within this distance (metres) of an accepted plane."""
    agree_dist: float = 0.03
    """A plane agrees with the cues if the median distance of the nearby anchors is below this."""
    min_agree_anchors: int = 5
    """Anchors needed to test agreement (with fewer, see require_anchors)."""
    require_anchors: bool = True
    """Reject planes that no nearby line / SfM cue can confirm (the paper's line-distance test)."""
    snap_to_plane: bool = True
    """Move kept points onto their plane, itself moved onto the agreeing anchors (removes prior noise)."""
    # ---- prior-free
    free_min_anchors: int = 8
    """Prior-free: anchors (near the region) needed to fit its plane."""
    free_min_groups: int = 2
    """Prior-free: the inlier anchors must come from at least this many lines / SfM points."""
    free_min_off_line: int = 3
    """Prior-free: with fewer than two lines among the inliers, SfM points needed among them."""
    free_ransac_dist: float = 0.02
    """Prior-free: RANSAC inlier distance (metres) of the plane fitted to the anchors."""
    free_min_inlier_ratio: float = 0.3
    """Prior-free: the plane must hold at least this (group-weighted) share of the region's anchors."""
    free_min_spread: float = 0.1
    """Prior-free: least 2nd principal std (metres) of the inlier anchors (one line fixes no plane)."""
    free_local_k: int = 8
    """Prior-free: keep a pixel if most of its k nearest anchors in the image are plane inliers (0 = off)."""
    free_local_ratio: float = 0.6
    """Prior-free: share of those k anchors that must be inliers."""
    free_max_extrapolation: float = 1.0
    """Prior-free: drop points farther than this (metres) from every inlier anchor."""
    min_views: int = 1
    """Keep voxels supported by at least this many images."""


@dataclass
class PlanePoints:
    """Plane-like points of one image before merging."""

    xyz: np.ndarray  # [N, 3] world
    rgb: np.ndarray  # [N, 3] float32 in [0, 1]
    normal: np.ndarray  # [N, 3] plane normal, facing the camera
    n_regions: int = 0
    n_accepted: int = 0  # regions that produced points
    rejected: dict[str, int] = field(default_factory=dict)  # reason -> regions (or planes)

    @staticmethod
    def empty(n_regions: int = 0, rejected: dict | None = None) -> "PlanePoints":
        return PlanePoints(np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                           n_regions, 0, dict(rejected or {}))


def _bump(d: dict[str, int], key: str, n: int = 1) -> None:
    d[key] = d.get(key, 0) + n


def fit_plane_ransac(points: np.ndarray, dist: float, seed: int = 0, iters: int = 500
                     ) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane n·x + d = 0 (‖n‖ = 1) through ``points`` [N, 3], N >= 3, via Open3D
    ``segment_plane``. Returns (n [3], d, inlier mask [N])."""
    import open3d as o3d

    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ValueError(f"need [N >= 3, 3] points, got shape {pts.shape}")
    o3d.utility.random.seed(seed)
    pcd = o3d.geometry.PointCloud(points=o3d.utility.Vector3dVector(pts))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        model, idx = pcd.segment_plane(distance_threshold=dist, ransac_n=3, num_iterations=iters)
    model = np.asarray(model, np.float64).ravel()
    norm = np.linalg.norm(model[:3])
    mask = np.zeros(len(pts), bool)
    if norm < 1e-12 or not np.all(np.isfinite(model)):
        return np.array([0.0, 0.0, 1.0]), 0.0, mask
    mask[np.asarray(idx, np.int64)] = True
    return model[:3] / norm, float(model[3] / norm), mask


def _group_weights(groups: np.ndarray) -> np.ndarray:
    """w_i = 1 / |group(i)|: every line (all its samples together) weighs as much as one SfM point."""
    _, inv, cnt = np.unique(groups, return_inverse=True, return_counts=True)
    return 1.0 / cnt[inv.ravel()]


def fit_plane_groups(points: np.ndarray, groups: np.ndarray, dist: float, rng: np.random.Generator,
                     iters: int = 300) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Group-weighted RANSAC plane through cue points (prior-free plane cues, paper §4.1).

        π* = argmax_π Σ_i w_i [|n·p_i + d| < τ],   w_i = 1 / |group(i)|

    so a line sampled every centimetre counts once, like one SfM point, and a plane is not chosen
    just because it contains one long line. Minimal samples are drawn with probability ∝ w; the
    winner is refined by weighted least squares on its inliers. points: [P, 3], groups: [P].
    Returns (n [3], d, inlier mask [P], inlier weight / total weight)."""
    P = len(points)
    if P < 3:
        return np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(P, bool), 0.0
    w = _group_weights(groups)
    idx = rng.choice(P, size=(iters, 3), p=w / w.sum())
    a, b, c = points[idx[:, 0]], points[idx[:, 1]], points[idx[:, 2]]
    n = np.cross(b - a, c - a)  # [iters, 3]
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    if not ok.any():
        return np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(P, bool), 0.0
    n = n[ok] / norm[ok, None]
    d = -np.sum(n * a[ok], axis=1)
    score = (np.abs(points @ n.T + d) < dist).T.astype(np.float64) @ w  # [iters]
    best = int(np.argmax(score))
    n_b, d_b = n[best], float(d[best])
    for _ in range(2):  # weighted least-squares refinement on the inliers
        inl = np.abs(points @ n_b + d_b) < dist
        if inl.sum() < 3:
            break
        wi = w[inl]
        mu = wi @ points[inl] / wi.sum()
        cov = (points[inl] - mu).T @ ((points[inl] - mu) * wi[:, None])
        n_new = np.linalg.eigh(cov)[1][:, 0]
        n_b = n_new if n_new @ n_b >= 0 else -n_new
        d_b = -float(n_b @ mu)
    inl = np.abs(points @ n_b + d_b) < dist
    return n_b, d_b, inl, float(w[inl].sum() / w.sum())


def ray_plane_depth(rays: np.ndarray, n_cam: np.ndarray, d_cam: float) -> np.ndarray:
    """Intersect camera rays with a plane (prior-free plane cues, paper §4.1).

        x(z) = z · r  (r = (x, y, 1): z-depth parametrisation),   n·x + d = 0  ⇒  z = −d / (n·r)

    rays: [N, 3] camera-frame directions with r_z = 1; n_cam, d_cam: the plane in the camera frame.
    Returns z [N] (inf where the ray is parallel to the plane, negative behind the camera).
    """
    denom = rays @ n_cam
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -d_cam / denom
    return np.where(np.abs(denom) > 1e-12, z, np.inf)


def _plane_to_camera(n: np.ndarray, d: float, cam: Camera) -> tuple[np.ndarray, float]:
    """World plane n·X + d = 0 -> camera plane n_c·x + d_c = 0 (x = R X + t)."""
    n_c = cam.R @ n
    return n_c, float(d - n_c @ cam.t)


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


def _region_pixels(regions: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Strided pixels inside weak regions: (rows [M], cols [M], region id [M])."""
    sub = regions[::stride, ::stride]
    r, c = np.nonzero(sub >= 0)
    return r * stride, c * stride, sub[r, c]


def _nearby_anchor_ids(cam: Camera, regions: np.ndarray, n_regions: int, anchors_xyz: np.ndarray,
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
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * border + 1, 2 * border + 1)) \
        if border > 0 else None
    strict = np.zeros(len(idx), bool) if inside_only is None else np.asarray(inside_only, bool)[idx]
    own = regions[rows, cols]
    for k in range(n_regions):
        mask = (regions == k).astype(np.uint8)
        if kernel is not None:
            mask = cv2.dilate(mask, kernel)
        near = (mask[rows, cols] > 0) & (~strict | (own == k))
        out.append(idx[near])
    return out


def _snap_plane(n_c: np.ndarray, d_c: float, a_c: np.ndarray, agree: np.ndarray, cfg: PlaneConfig
                ) -> tuple[np.ndarray, float]:
    """Move a prior plane onto the anchors that agree with it, changing its normal by at most
    10 degrees: refit it to them when they span a plane; hinge it onto them (keep the prior normal's
    component across their direction) when they lie along one line; else only shift it by their
    median signed distance."""
    A = a_c[agree]
    c = A.mean(axis=0)
    _, sv, vt = np.linalg.svd(A - c, full_matrices=False)
    sv = sv / np.sqrt(len(A))
    cos_max = np.cos(np.radians(10.0))
    cand = None
    if len(A) >= 3 and sv[1] >= cfg.free_min_spread:
        cand = vt[2]
    elif len(A) >= 2 and sv[0] >= cfg.free_min_spread:
        u = vt[0]
        cand = n_c - (n_c @ u) * u
        cand /= max(np.linalg.norm(cand), 1e-12)
    if cand is not None and abs(cand @ n_c) > cos_max:
        n_new = cand if cand @ n_c > 0 else -cand
        return n_new, -float(n_new @ c)
    return n_c, d_c - float(np.median(A @ n_c + d_c))


def plane_cues_with_prior(cam: Camera, image: np.ndarray, regions: np.ndarray,
                          aligned_depth: np.ndarray, anchors_xyz: np.ndarray, cfg: PlaneConfig,
                          seed: int = 0, inside_only: np.ndarray | None = None) -> PlanePoints:
    """Plane-like points of one image from its aligned depth prior [H, W] (metres, 0 = invalid).
    ``anchors_xyz`` [P, 3]: line / SfM cue points that may be visible in the image; those flagged
    ``inside_only`` [P] (SfM points) count only when they project inside a region."""
    h, w = cam.height, cam.width
    if regions.shape != (h, w) or aligned_depth.shape != (h, w) or image.shape[:2] != (h, w):
        raise ValueError(f"{cam.name}: regions {regions.shape}, depth {aligned_depth.shape} and "
                         f"image {image.shape} must all be ({h}, {w})")
    n_regions = int(regions.max()) + 1 if regions.size else 0
    rej: dict[str, int] = {}
    if n_regions == 0:
        return PlanePoints.empty()
    s = w / 640.0
    stride = max(1, int(round(cfg.pixel_stride * s)))
    rows, cols, rid = _region_pixels(regions, stride)
    z = aligned_depth[rows, cols].astype(np.float64)
    rays = cam.pixel_rays()[rows, cols]  # [M, 3], z = 1
    near = _nearby_anchor_ids(cam, regions, n_regions, anchors_xyz, int(round(cfg.border_px * s)),
                              inside_only=inside_only, depth=aligned_depth)
    Rt = cam.R.T
    out_xyz, out_rgb, out_n = [], [], []
    accepted = 0
    for k in range(n_regions):
        sel = np.flatnonzero((rid == k) & (z > 0) & (z < cfg.max_depth))
        if len(sel) < cfg.min_region_points:
            _bump(rej, "too_small_or_no_depth")
            continue
        Xc = rays[sel] * z[sel, None]  # [m, 3] camera frame
        # anchors near the region and not hidden behind the aligned surface there
        a_ids = near[k]
        a_c = anchors_xyz[a_ids] @ cam.R.T + cam.t  # [a, 3]
        remaining = np.arange(len(sel))
        got_any = False
        for p in range(cfg.max_planes):
            if len(remaining) < max(cfg.min_region_points, cfg.min_plane_frac * len(sel)):
                break
            n_c, d_c, inl = fit_plane_ransac(Xc[remaining], cfg.ransac_dist, seed=seed + 31 * k + p)
            if inl.sum() < cfg.min_plane_frac * len(sel):
                _bump(rej, "not_planar" if p == 0 else "no_further_plane")
                break
            dist_pts = np.abs(Xc[remaining] @ n_c + d_c)
            keep = remaining[dist_pts < cfg.keep_dist]
            remaining = remaining[dist_pts >= cfg.keep_dist]
            # agreement with the nearby cues (paper: keep points close to the 3D line samples)
            sd = a_c @ n_c + d_c  # signed distances of nearby anchors
            agree = np.abs(sd) < cfg.agree_dist
            if len(a_ids) >= cfg.min_agree_anchors:
                if np.median(np.abs(sd)) >= cfg.agree_dist or agree.sum() < cfg.min_agree_anchors:
                    _bump(rej, "disagrees_with_cues")
                    continue
            elif cfg.require_anchors:
                _bump(rej, "no_nearby_cues")
                continue
            if cfg.snap_to_plane:
                if agree.sum() >= cfg.min_agree_anchors:
                    n_c, d_c = _snap_plane(n_c, d_c, a_c, agree, cfg)
                zk = ray_plane_depth(rays[sel[keep]], n_c, d_c)
                ok = np.isfinite(zk) & (zk > 0) & (zk < cfg.max_depth) & \
                    (np.abs(rays[sel[keep]] @ n_c) / np.linalg.norm(rays[sel[keep]], axis=1) >= cfg.min_ray_cos)
                keep, Xk = keep[ok], rays[sel[keep[ok]]] * zk[ok, None]
            else:
                Xk = Xc[keep]
            if len(keep) == 0:
                continue
            n_face = n_c if np.median(rays[sel[keep]] @ n_c) < 0 else -n_c  # face the camera
            out_xyz.append((Xk - cam.t) @ Rt.T)
            out_rgb.append(image[rows[sel[keep]], cols[sel[keep]]])
            out_n.append(np.broadcast_to(Rt @ n_face, (len(keep), 3)))
            got_any = True
        accepted += got_any
    if not out_xyz:
        return PlanePoints.empty(n_regions, rej)
    return PlanePoints(np.concatenate(out_xyz), np.concatenate(out_rgb).astype(np.float32),
                       np.concatenate(out_n).astype(np.float32), n_regions, accepted, rej)


def plane_cues_prior_free(cam: Camera, image: np.ndarray, regions: np.ndarray,
                          anchors_xyz: np.ndarray, anchors_group: np.ndarray, cfg: PlaneConfig,
                          seed: int = 0, inside_only: np.ndarray | None = None) -> PlanePoints:
    """Plane-like points of one image without a depth prior: each region's plane comes from the
    anchors ``anchors_xyz`` [P, 3] (``anchors_group`` [P]: line index >= 0, or < 0 for an SfM point)
    that border or project into it (``inside_only`` [P]: only into it); the region's pixel rays are
    intersected with that plane."""
    from scipy.spatial import cKDTree

    h, w = cam.height, cam.width
    if regions.shape != (h, w) or image.shape[:2] != (h, w):
        raise ValueError(f"{cam.name}: regions {regions.shape} and image {image.shape} must be ({h}, {w})")
    if len(anchors_group) != len(anchors_xyz):
        raise ValueError(f"anchors_group has {len(anchors_group)} entries, expected {len(anchors_xyz)}")
    n_regions = int(regions.max()) + 1 if regions.size else 0
    rej: dict[str, int] = {}
    if n_regions == 0:
        return PlanePoints.empty()
    s = w / 640.0
    stride = max(1, int(round(cfg.pixel_stride * s)))
    rows, cols, rid = _region_pixels(regions, stride)
    rays = cam.pixel_rays()[rows, cols]
    near = _nearby_anchor_ids(cam, regions, n_regions, anchors_xyz, int(round(cfg.border_px * s)),
                              inside_only=inside_only)
    Rt = cam.R.T
    out_xyz, out_rgb, out_n = [], [], []
    accepted = 0
    rng = np.random.default_rng(seed)
    for k in range(n_regions):
        sel = np.flatnonzero(rid == k)
        a_ids = near[k]
        if len(sel) < cfg.min_region_points:
            _bump(rej, "too_small")
            continue
        if len(a_ids) < cfg.free_min_anchors:
            _bump(rej, "too_few_anchors")
            continue
        a_c = anchors_xyz[a_ids] @ cam.R.T + cam.t  # [a, 3] camera frame
        grp = anchors_group[a_ids]
        n_c, d_c, inl, frac = fit_plane_groups(a_c, grp, cfg.free_ransac_dist, rng)
        if frac < cfg.free_min_inlier_ratio or inl.sum() < cfg.free_min_anchors:
            _bump(rej, "anchors_not_coplanar")
            continue
        groups = np.unique(grp[inl])  # >= 0: line index, < 0: SfM point
        n_lines, n_points = int(np.sum(groups >= 0)), int(np.sum(groups < 0))
        if len(groups) < cfg.free_min_groups or (n_lines <= 1 and n_points < cfg.free_min_off_line):
            _bump(rej, "single_line")  # one line (plus a stray point) does not fix a plane
            continue
        w = _group_weights(grp[inl])
        mu = w @ a_c[inl] / w.sum()
        cov = (a_c[inl] - mu).T @ ((a_c[inl] - mu) * w[:, None]) / w.sum()
        if np.sqrt(max(np.linalg.eigvalsh(cov)[1], 0.0)) < cfg.free_min_spread:
            _bump(rej, "degenerate_anchors")
            continue
        r = rays[sel]
        zk = ray_plane_depth(r, n_c, d_c)
        cosang = np.abs(r @ n_c) / np.linalg.norm(r, axis=1)
        ok = np.isfinite(zk) & (zk > 0) & (zk < cfg.max_depth) & (cosang >= cfg.min_ray_cos)
        if not ok.any():
            _bump(rej, "plane_behind_or_grazing")
            continue
        Xc = r[ok] * zk[ok, None]
        dist, _ = cKDTree(a_c[inl]).query(Xc, k=1)
        good = dist <= cfg.free_max_extrapolation
        if cfg.free_local_k > 0:  # local consensus: the anchors nearest in the image lie on the plane
            uv_a = a_c[:, :2] / a_c[:, 2:3]  # normalised image coordinates of the anchors
            k_n = min(cfg.free_local_k, len(a_c))
            _, nn = cKDTree(uv_a).query(r[ok][:, :2], k=k_n)
            good &= inl[nn.reshape(len(Xc), k_n)].mean(axis=1) >= cfg.free_local_ratio
        if not good.any():
            _bump(rej, "no_local_support")
            continue
        keep = sel[ok][good]
        Xc = Xc[good]
        n_face = n_c if np.median(rays[keep] @ n_c) < 0 else -n_c
        out_xyz.append((Xc - cam.t) @ Rt.T)
        out_rgb.append(image[rows[keep], cols[keep]])
        out_n.append(np.broadcast_to(Rt @ n_face, (len(keep), 3)))
        accepted += 1
    if not out_xyz:
        return PlanePoints.empty(n_regions, rej)
    return PlanePoints(np.concatenate(out_xyz), np.concatenate(out_rgb).astype(np.float32),
                       np.concatenate(out_n).astype(np.float32), n_regions, accepted, rej)


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
    _, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    m = len(cnt)

    def mean(a: np.ndarray) -> np.ndarray:
        out = np.zeros((m, a.shape[1]))
        np.add.at(out, inv, a)
        return out / cnt[:, None]

    first = np.full(m, -1, np.int64)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    ref = normal[first]
    sign = np.where(np.sum(normal * ref[inv], axis=1) < 0, -1.0, 1.0)
    nrm = mean(normal * sign[:, None])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    pairs = np.unique(np.stack([inv, np.asarray(view, np.int64)], axis=1), axis=0)
    n_views = np.bincount(pairs[:, 0], minlength=m)
    return mean(xyz), mean(rgb).astype(np.float32), nrm.astype(np.float32), n_views
