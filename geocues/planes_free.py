"""Prior-free plane-like cues of one image (paper §4.1, for images without a depth prior).

Each weak-texture region's plane comes from the line / SfM cues that border or project into it
(group-weighted RANSAC, then the anchored fit of ``geocues.planes``), after a leave-one-group-out
test drops anchor groups the plane of the others does not predict
(:func:`~geocues.plane_fit.loo_group_residuals`); the region's pixel rays are cut with that plane
(:func:`~geocues.plane_fit.ray_plane_depth`) only where the anchors pin it down. The options are
``PlaneConfig``'s ``free_*`` fields; docs/geocues.md gives the reasons for each test.
"""

from __future__ import annotations

import numpy as np

from geocues.plane_fit import AnchoredPlane, fit_plane_groups, group_weights, loo_group_residuals, ray_plane_depth
from geocues.plane_regions import in_anchor_hull, lines_confirm_plane, nearby_anchor_ids
from geocues.planes import PlaneConfig, PlanePoints, _bump, _Collector, _region_rays
from geocues.scene import Camera


def _lacks_evidence(a_c: np.ndarray, grp: np.ndarray, inl: np.ndarray, cfg: PlaneConfig) -> str | None:
    """Why the inlier anchors ``inl`` [a] (camera frame a_c [a, 3], groups grp [a]) cannot fix a
    plane, or None when they can (prior-free plane cues)."""
    w = group_weights(grp)
    if w[inl].sum() < cfg.free_min_inlier_ratio * w.sum() or inl.sum() < cfg.free_min_anchors:
        return "anchors_not_coplanar"
    groups = np.unique(grp[inl])  # >= 0: line index, < 0: SfM point
    n_lines, n_points = int(np.sum(groups >= 0)), int(np.sum(groups < 0))
    if len(groups) < cfg.free_min_groups or (n_lines <= 1 and n_points < cfg.free_min_off_line):
        return "single_line"  # one line (plus a stray point) does not fix a plane
    if n_points < cfg.free_min_off_line and not lines_confirm_plane(a_c[inl], grp[inl]):
        return "only_parallel_lines"  # two parallel lines are always coplanar: no evidence
    return None


def _held_out_inliers(a_c: np.ndarray, grp: np.ndarray, inl: np.ndarray, n0: np.ndarray,
                      cfg: PlaneConfig) -> tuple[np.ndarray, str | None]:
    """Leave-one-group-out test of the inlier anchors (:func:`loo_group_residuals`): while the plane
    of the other inlier groups misses some group by more than ``free_loo_dist``, drop the worst
    one (``free_loo_drop``; otherwise reject the plane) and re-check that the rest still fixes a
    plane. Returns (inlier mask, None) or (mask, rejection reason)."""
    inl = inl.copy()
    while True:
        ug, r = loo_group_residuals(a_c[inl], grp[inl], n0, cfg.anchor_sigma, cfg.max_plane_std)
        r = np.nan_to_num(r, nan=0.0)  # groups the others cannot pin down are not tested
        k = int(np.argmax(r)) if len(r) else 0
        if len(r) == 0 or r[k] <= cfg.free_loo_dist:
            return inl, None
        if not cfg.free_loo_drop:
            return inl, "anchors_fail_held_out_test"
        inl &= grp != ug[k]
        why = _lacks_evidence(a_c, grp, inl, cfg)
        if why is not None:
            return inl, "anchors_fail_held_out_test"


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
    n_regions, s, rows, cols, rid, rays = _region_rays(cam, regions, cfg)
    rej: dict[str, int] = {}
    if n_regions == 0:
        return PlanePoints.empty()
    near = nearby_anchor_ids(cam, regions, n_regions, anchors_xyz, int(round(cfg.border_px * s)),
                              inside_only=inside_only)
    out = _Collector(cam, image, rows, cols)
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
        n_c, d_c, inl, _ = fit_plane_groups(a_c, grp, cfg.free_ransac_dist, rng)
        _, ginv = np.unique(grp, return_inverse=True)
        share = np.bincount(ginv, weights=inl) / np.bincount(ginv)  # inlier share of each group
        inl &= share[ginv] >= 0.6  # a line supports the plane only if it lies in it, not if it crosses it
        why = _lacks_evidence(a_c, grp, inl, cfg)
        if why is None and cfg.free_loo_dist > 0:
            inl, why = _held_out_inliers(a_c, grp, inl, n_c, cfg)
        if why is not None:
            _bump(rej, why)
            continue
        ap = AnchoredPlane(a_c[inl], group_weights(grp[inl]), n_c, cfg.anchor_sigma)
        n_c, d_c = ap.n, ap.d
        r = rays[sel]
        zk = ray_plane_depth(r, n_c, d_c)
        cosang = np.abs(r @ n_c) / np.linalg.norm(r, axis=1)
        ok = np.isfinite(zk) & (zk > 0) & (zk < cfg.max_depth) & (cosang >= cfg.min_ray_cos)
        if not ok.any():
            _bump(rej, "plane_behind_or_grazing")
            continue
        Xc = r[ok] * zk[ok, None]
        good = ap.std_at(Xc) <= cfg.max_plane_std  # only where the anchors pin the plane down
        if cfg.hull_margin_px >= 0:
            good &= in_anchor_hull(cam, a_c[inl], rows[sel[ok]], cols[sel[ok]], cfg.hull_margin_px * s)
        if not good.any():
            _bump(rej, "anchors_do_not_fix_plane")
            continue
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
        out.add(keep, Xc, n_c)
        accepted += 1
    return out.result(n_regions, accepted, rej)
