"""Plane-like cues (paper §4.1): 3D points for weak-texture regions, where SfM finds nothing.

Two modes per image (details and the reasons for each choice in docs/geocues.md):

* **with a depth prior** (:func:`plane_cues_with_prior`): back-project the region's pixels with the
  aligned prior, split them into planes by sequential seeded RANSAC (:func:`~geocues.plane_fit.fit_plane_ransac`), refit each
  plane to the nearby line / SfM cues with the prior normal as a pseudo-observation
  (:class:`~geocues.plane_fit.AnchoredPlane`), keep it if those cues agree with it, and cut the
  pixels' rays with it;
* **prior-free** (:func:`geocues.planes_free.plane_cues_prior_free`): fit the plane of the line / SfM cues that border
  or project into the region (group-weighted RANSAC, then the same anchored fit) and intersect the
  region's pixel rays with it (:func:`~geocues.plane_fit.ray_plane_depth`); anchor groups that
  the plane of the others does not predict are dropped first (leave-one-group-out test,
  :func:`~geocues.plane_fit.loo_group_residuals`).

Both keep a pixel only where the anchors pin the plane down (offset std and anchor hull). Regions
can first be cut along projected 3D lines (:func:`split_regions_by_lines`). Merging across images
(multi-view support and conflict votes, voxel grid) is in ``geocues.plane_merge``. Every rejected region or plane is
counted under a reason.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from geocues.ceiling import level_plane_points
from geocues.plane_fit import AnchoredPlane, fit_plane_ransac, group_weights, ray_plane_depth, weighted_median
from geocues.plane_regions import in_anchor_hull, nearby_anchor_ids, on_occluder, region_pixels
from geocues.scene import Camera
from geocues.walls import wall_snap_points

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
    sfm_anchors: bool = True
    """Use SfM points as plane anchors besides the line samples (they are biased on weak texture)."""
    sfm_min_angle_deg: float = 15.0
    """Plane anchors: only SfM points seen from rays at least this far apart, degrees (0 = all)."""
    anchor_sigma: float = 0.01
    """Assumed error (metres) of one anchor group (a line or an SfM point) when fitting a plane."""
    max_plane_std: float = 0.015
    """Keep pixels where the anchored plane's offset is known to this std (metres)."""
    hull_margin_px: float = 16.0
    """Keep pixels inside the image convex hull of a plane's anchors grown by this (px at 640; <0 = off)."""
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
    """Least RANSAC inlier distance (metres) of the planes fitted to the back-projected prior."""
    ransac_rel: float = 0.015
    """RANSAC inlier distance as a fraction of the region's median depth (the larger one is used)."""
    max_planes: int = 3
    """At most this many planes per region (sequential RANSAC)."""
    min_plane_frac: float = 0.2
    """A plane must hold at least this fraction of the region's pixels."""
    occlusion_rel: float = 0.06
    """Anchors farther than the aligned prior by this fraction of its depth are hidden (not used)."""
    agree_search_rel: float = 0.05
    """Anchors within this fraction of the region's depth of a prior plane are its candidates."""
    agree_dist: float = 0.03
    """A (snapped) plane agrees with the cues if their median distance to it is below this (metres)."""
    min_agree_anchors: int = 5
    """Anchors needed to test agreement (with fewer, see require_anchors)."""
    require_anchors: bool = True
    """Reject planes that no nearby line / SfM cue can confirm (the paper's line-distance test)."""
    snap_to_plane: bool = True
    """Refit each prior plane to its agreeing anchors and cut the pixel rays with it."""
    occluder_jump: float = 0.03
    """Drop line anchors bounding an object in front of the region (prior depth jump; 0 = off)."""
    occluder_step_px: float = 8.0
    """Pixels (at 640) stepped to each side of a projected line for that test."""
    prior_normal_std_deg: float = 5.0
    """Trust in the prior plane's normal when refitting it to the anchors (degrees, 1 sigma)."""
    fill_holes: bool = False
    """Sparse priors (`geocues mvs` finds no depth on textureless surfaces): the pixels of a region
    where the prior has no depth are cut with the anchored plane of their nearest pixel that has
    one (same pins: max_plane_std, anchor hull), and regions with no prior depth at all get
    prior-free plane cues (an extension)."""
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
    free_loo_dist: float = 0.02
    """Prior-free: the plane fitted to the other inlier lines / SfM points must pass within this
    distance (metres) of each one (leave-one-group-out test; 0 = off)."""
    free_loo_drop: bool = True
    """Prior-free: drop the anchor groups that fail that test, worst first (False: reject the plane)."""
    free_local_k: int = 8
    """Prior-free: keep a pixel if most of its k nearest anchors in the image are plane inliers (0 = off)."""
    free_local_ratio: float = 0.6
    """Prior-free: share of those k anchors that must be inliers."""
    # ---- merging the images' planes
    fuse_planes: bool = False
    """Fuse the planes of different images that describe one surface (geocues.plane_merge)."""
    fuse_angle_deg: float = 5.0
    """Planes closer than this angle ..."""
    fuse_dist: float = 0.05
    """... and passing within this distance (metres) of each other's centroid are one surface."""
    fuse_surfaces: bool = False
    """Group the prior planes of all images into surfaces and pin each surface with the anchors of
    every image that sees it, before cutting the rays (an extension, geocues.plane_surfaces): walls
    whose images each see one border line get cues across, not only along that line."""
    surface_angle_deg: float = 20.0
    """Surface fusion: an image's prior plane joins a surface if their normals differ by less than this
    (the warp of a monocular prior tilts its planes: 9-19 degrees measured on the bare room) ..."""
    surface_consensus_deg: float = 5.0
    """... and a plane refitted to the anchors it brings stays within this angle of the mean of the
    surface's prior normals (each prior plane is tilted by its own warp; their mean much less) ..."""
    fuse_prior_rel: float = 0.05
    """... and its aligned prior lies within this fraction of its depth of the surface (the prior's
    low-frequency warp; also the per-pixel test of the cut) ..."""
    fuse_prior_dist: float = 0.05
    """... or within this distance (metres), whichever is larger."""
    min_plane_views: int = 1
    """With fusion: drop points of surfaces found in fewer images than this."""
    min_views: int = 3
    """Keep plane points that at least this many images (itself included) put within support_radius."""
    support_radius: float = 0.02
    """Radius (metres) of that multi-view agreement test."""
    support_angle_deg: float = 5.0
    """... and whose plane normals differ from the point's by at most this angle (degrees; 180 = off)."""
    conflict_radius: float = 0.05
    """Drop plane points for which fewer images agree (same plane: support_angle_deg, support_radius
    along the normal) than disagree, among the images with plane points this close (metres; 0 = off)."""


@dataclass
class PlanePoints:
    """Plane-like points of one image before merging."""

    xyz: np.ndarray  # [N, 3] world
    rgb: np.ndarray  # [N, 3] float32 in [0, 1]
    normal: np.ndarray  # [N, 3] plane normal, facing the camera
    plane_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [N] row of planes
    planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # [K, 4] world (n, d), n·X + d = 0
    n_regions: int = 0
    n_accepted: int = 0  # regions that produced points
    rejected: dict[str, int] = field(default_factory=dict)  # reason -> regions (or planes)
    no_depth_regions: list[int] = field(default_factory=list)  # regions without prior depth (fill_holes)
    candidates: list = field(default_factory=list)  # SurfaceCandidate per prior plane (fuse_surfaces)

    def concat(self, other: "PlanePoints") -> "PlanePoints":
        """These points and ``other``'s (of the same image and regions: their planes follow ours)."""
        rej = dict(self.rejected)
        for k, v in other.rejected.items():
            rej[k] = rej.get(k, 0) + v
        return PlanePoints(np.concatenate([self.xyz, other.xyz]), np.concatenate([self.rgb, other.rgb]),
                           np.concatenate([self.normal, other.normal]),
                           np.concatenate([self.plane_id, other.plane_id + len(self.planes)]),
                           np.concatenate([self.planes.reshape(-1, 4), other.planes.reshape(-1, 4)]),
                           self.n_regions, self.n_accepted + other.n_accepted, rej)

    @staticmethod
    def empty(n_regions: int = 0, rejected: dict | None = None) -> "PlanePoints":
        return PlanePoints(np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                           n_regions=n_regions, rejected=dict(rejected or {}))


class _Collector:
    """Accumulates the accepted planes of one image: points in world, colours, facing normals."""

    def __init__(self, cam: Camera, image: np.ndarray, rows: np.ndarray, cols: np.ndarray):
        self.cam, self.image, self.rows, self.cols = cam, image, rows, cols
        self.xyz, self.rgb, self.nrm, self.pid, self.planes = [], [], [], [], []

    def add(self, pix: np.ndarray, Xc: np.ndarray, n_c: np.ndarray) -> None:
        """pix: [m] indices into rows/cols; Xc: [m, 3] camera-frame points on the plane (normal n_c)."""
        n_face = n_c if np.median(Xc @ n_c) < 0 else -n_c  # face the camera (rays are Xc themselves)
        Xw = (Xc - self.cam.t) @ self.cam.R  # x_cam = R X + t
        n_w = self.cam.R.T @ n_face
        self.xyz.append(Xw)
        self.rgb.append(self.image[self.rows[pix], self.cols[pix]])
        self.nrm.append(np.broadcast_to(n_w, (len(pix), 3)))
        self.pid.append(np.full(len(pix), len(self.planes), np.int64))
        self.planes.append(np.r_[n_w, -float(n_w @ Xw.mean(axis=0))])

    def result(self, n_regions: int, accepted: int, rejected: dict[str, int]) -> PlanePoints:
        if not self.xyz:
            return PlanePoints.empty(n_regions, rejected)
        return PlanePoints(np.concatenate(self.xyz), np.concatenate(self.rgb).astype(np.float32),
                           np.concatenate(self.nrm).astype(np.float32), np.concatenate(self.pid),
                           np.array(self.planes), n_regions, accepted, rejected)


def _region_rays(cam: Camera, regions: np.ndarray, cfg: PlaneConfig):
    """(number of regions, image scale against 640 px, then the strided pixels of the regions: rows,
    cols, region id, rays [M, 3] with z = 1) of one image: what both plane modes start from."""
    n_regions = int(regions.max()) + 1 if regions.size else 0
    s = cam.width / 640.0
    rows, cols, rid = region_pixels(regions, max(1, int(round(cfg.pixel_stride * s))))
    return n_regions, s, rows, cols, rid, cam.pixel_rays()[rows, cols]


def _bump(d: dict[str, int], key: str, n: int = 1) -> None:
    d[key] = d.get(key, 0) + n


def plane_cues_with_prior(cam: Camera, image: np.ndarray, regions: np.ndarray,
                          aligned_depth: np.ndarray, anchors_xyz: np.ndarray, cfg: PlaneConfig,
                          seed: int = 0, inside_only: np.ndarray | None = None,
                          anchors_group: np.ndarray | None = None, anchor_ids: np.ndarray | None = None,
                          whole_lines: np.ndarray | None = None, levels: np.ndarray | None = None,
                          level_rel: float = 0.05, walls: np.ndarray | None = None,
                          wall_veto: np.ndarray | None = None) -> PlanePoints:
    """Plane-like points of one image from its aligned depth prior [H, W] (metres, 0 = invalid).

    ``anchors_xyz`` [P, 3]: line / SfM cue points that may be visible in the image; those flagged
    ``inside_only`` [P] (SfM points) count only when they project inside a region;
    ``anchors_group`` [P] (line index, or < 0 for SfM points) weighs each line like one point;
    the lines of anchors flagged ``whole_lines`` [P] (the raised floor lines of `--floor.walls`, an
    assumption rather than a cue) count for a plane only where all their points near the region agree.
    Each region's back-projected prior is split into planes by sequential RANSAC; a plane is kept
    if the nearby anchors agree with it -- after it is snapped onto them (``snap_to_plane``), which
    removes the prior's residual low-frequency error -- and its pixels' rays are cut with it.
    With ``fuse_surfaces`` nothing is cut here: every plane becomes a SurfaceCandidate (in the
    result's ``candidates``, its agreeing anchors named by ``anchor_ids`` [P], default 0..P-1) for
    geocues.plane_surfaces. ``levels`` [L, 4] (world n . X + d = 0, `--floor.level-snap`): a region
    whose prior lies on one of these assumed planes (geocues.ceiling.level_plane_points) is cut onto it
    without the anchors' check. ``walls`` [K, 4] (`--floor.wall-snap`): the pixels of a RANSAC plane of
    the prior that the anchors' check leaves out (no anchor near, outside their hull) are tested the
    same way against these vertical planes and cut onto the one they lie on, unless the region's
    measured anchors (``wall_veto`` [P]: SfM points and 3D lines, not the lifted feet whose offset the
    wall planes may share, nor assumptions; default: those not in ``whole_lines``) put the surface
    3 cm or more off it."""
    h, w = cam.height, cam.width
    if regions.shape != (h, w) or aligned_depth.shape != (h, w) or image.shape[:2] != (h, w):
        raise ValueError(f"{cam.name}: regions {regions.shape}, depth {aligned_depth.shape} and "
                         f"image {image.shape} must all be ({h}, {w})")
    n_regions, s, rows, cols, rid, rays = _region_rays(cam, regions, cfg)
    rej: dict[str, int] = {}
    if n_regions == 0:
        return PlanePoints.empty()
    z = aligned_depth[rows, cols].astype(np.float64)
    near = nearby_anchor_ids(cam, regions, n_regions, anchors_xyz, int(round(cfg.border_px * s)),
                              inside_only=inside_only, depth=aligned_depth, occl_rel=cfg.occlusion_rel)
    groups = np.arange(len(anchors_xyz)) if anchors_group is None else np.asarray(anchors_group)
    out = _Collector(cam, image, rows, cols)
    candidates: list = []
    accepted = 0
    no_depth = []  # regions left to the prior-free fit (fill_holes)
    has_depth = (z > 0) & (z < cfg.max_depth)
    for k in range(n_regions):
        in_k = rid == k
        sel = np.flatnonzero(in_k & has_depth)
        if len(sel) < cfg.min_region_points:
            _bump(rej, "too_small_or_no_depth")
            if cfg.fill_holes and in_k.sum() >= cfg.min_region_points:
                no_depth.append(k)
            continue
        if levels is not None and len(levels) and not cfg.fuse_surfaces:
            snapped = level_plane_points(cam, rays[sel], z[sel], levels, level_rel)
            if snapped is not None:
                keep, Xk, n_c = snapped
                out.add(sel[keep], Xk, n_c)
                accepted += 1
                _bump(rej, "on_a_level_plane")
                continue
        holes = np.flatnonzero(in_k & ~has_depth) if cfg.fill_holes else sel[:0]
        found = []  # (pixel indices, camera-frame points, normal, anchored plane or None) per plane
        Xc = rays[sel] * z[sel, None]  # [m, 3] camera frame
        zmed = float(np.median(z[sel]))
        tau = max(cfg.ransac_dist, cfg.ransac_rel * zmed)  # the prior's error grows with depth
        a_ids = near[k]  # anchors near the region, not hidden behind the aligned surface
        if cfg.occluder_jump > 0 and len(a_ids):
            a_ids = a_ids[~on_occluder(cam, regions, k, aligned_depth, anchors_xyz[a_ids], groups[a_ids],
                                        cfg.occluder_jump, max(2, int(round(cfg.occluder_step_px * s))))]
        a_c = anchors_xyz[a_ids] @ cam.R.T + cam.t  # [a, 3]
        a_w = group_weights(groups[a_ids]) if len(a_ids) else np.zeros(0)
        remaining = np.arange(len(sel))
        ransac_sets: list[np.ndarray] = []  # each RANSAC plane's pixels (into sel), for the wall snap
        got_any = False
        for p in range(cfg.max_planes):
            if len(remaining) < max(cfg.min_region_points, cfg.min_plane_frac * len(sel)):
                break
            n_c, d_c, inl = fit_plane_ransac(Xc[remaining], tau, seed=seed + 31 * k + p)
            if inl.sum() < cfg.min_plane_frac * len(sel):
                _bump(rej, "not_planar" if p == 0 else "no_further_plane")
                break
            keep = remaining[inl]
            remaining = remaining[~inl]
            ransac_sets.append(keep)
            # agreement with the nearby cues (paper: keep points close to the 3D line samples)
            near_plane = np.abs(a_c @ n_c + d_c) < max(cfg.agree_dist, cfg.agree_search_rel * zmed)
            if whole_lines is not None and len(a_ids):  # a raised row crossing the plane is not on it
                w = whole_lines[a_ids]
                near_plane &= ~(w & np.isin(groups[a_ids], groups[a_ids][w & ~near_plane]))
            r = rays[sel[keep]]
            if cfg.fuse_surfaces:
                candidates.append(_candidate(cam, image, n_c, d_c, rows[sel[keep]], cols[sel[keep]], z[sel[keep]],
                                             a_c, a_w, near_plane, a_ids, anchor_ids, cfg))
                continue
            if near_plane.sum() < cfg.min_agree_anchors:
                if cfg.require_anchors:
                    _bump(rej, "no_nearby_cues" if len(a_ids) < cfg.min_agree_anchors else "disagrees_with_cues")
                    continue
                Xk = Xc[keep]  # unconfirmed prior plane (require_anchors off)
            else:
                ap = AnchoredPlane(a_c[near_plane], a_w[near_plane], n_c, cfg.anchor_sigma,
                                   np.radians(cfg.prior_normal_std_deg) if cfg.snap_to_plane else 1e-9,
                                   huber=cfg.agree_dist)
                if weighted_median(np.abs(ap.residual), a_w[near_plane]) >= cfg.agree_dist:
                    _bump(rej, "disagrees_with_cues")
                    continue
                if cfg.snap_to_plane:  # the plane moved onto the anchors; cut the pixels' rays with it
                    n_c, d_c = ap.n, ap.d
                    zk = ray_plane_depth(r, n_c, d_c)
                    ok = np.isfinite(zk) & (zk > 0) & (zk < cfg.max_depth) & \
                        (np.abs(r @ n_c) / np.linalg.norm(r, axis=1) >= cfg.min_ray_cos)
                    Xk = r * np.where(ok, zk, 0.0)[:, None]
                    ok &= ap.std_at(Xk) <= cfg.max_plane_std  # only where the anchors pin it down
                    if cfg.hull_margin_px >= 0:
                        ok &= in_anchor_hull(cam, a_c[near_plane], rows[sel[keep]], cols[sel[keep]],
                                              cfg.hull_margin_px * s)
                    keep, Xk = keep[ok], Xk[ok]
                else:
                    Xk = Xc[keep]
            if len(keep) == 0:
                _bump(rej, "no_points_left")
                continue
            found.append((sel[keep], Xk, n_c, ap if cfg.snap_to_plane and near_plane.sum() >= cfg.min_agree_anchors
                          else None, a_c[near_plane]))
        if walls is not None and len(walls) and not cfg.fuse_surfaces:
            if wall_veto is not None:
                cue = np.asarray(wall_veto, bool)[a_ids]  # the anchors that may veto a wall cut
            else:
                cue = np.ones(len(a_ids), bool) if whole_lines is None else ~whole_lines[a_ids]
            found += wall_snap_points(cam, rays, z, sel, ransac_sets, found, walls, level_rel, a_c[cue], a_w[cue],
                                      cfg.min_region_points, cfg.agree_dist, cfg.min_agree_anchors, rej)
        for (pix, Xk, n_c, _, _), (h_pix, h_X) in zip(found, _fill(cam, rows, cols, holes, found, cfg, s)):
            out.add(np.r_[pix, h_pix], np.r_[Xk, h_X], n_c)
            got_any = True
        accepted += got_any
    res = out.result(n_regions, accepted, rej)
    res.no_depth_regions = no_depth
    res.candidates = candidates
    return res


def _candidate(cam: Camera, image: np.ndarray, n_c: np.ndarray, d_c: float, rows: np.ndarray, cols: np.ndarray,
               z: np.ndarray, a_c: np.ndarray, a_w: np.ndarray, near_plane: np.ndarray, a_ids: np.ndarray,
               anchor_ids: np.ndarray | None, cfg: PlaneConfig):
    """One prior plane as a SurfaceCandidate; its anchors are the nearby ones it agrees with (the
    same test as without fusion), none if they are too few or disagree."""
    from geocues.plane_surfaces import SurfaceCandidate

    agree = a_ids[:0]
    if near_plane.sum() >= cfg.min_agree_anchors:
        ap = AnchoredPlane(a_c[near_plane], a_w[near_plane], n_c, cfg.anchor_sigma,
                           np.radians(cfg.prior_normal_std_deg), huber=cfg.agree_dist)
        if weighted_median(np.abs(ap.residual), a_w[near_plane]) < cfg.agree_dist:
            agree = a_ids[near_plane][np.abs(ap.residual) < cfg.agree_dist]
    ids = agree if anchor_ids is None else np.asarray(anchor_ids)[agree]
    return SurfaceCandidate.from_camera_plane(cam, n_c, d_c, rows, cols, z, image[rows, cols], ids)


def _fill(cam: Camera, rows: np.ndarray, cols: np.ndarray, holes: np.ndarray, found: list, cfg: PlaneConfig,
          s: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """For each plane found in a region, the hole pixels (no prior depth) it takes: those whose
    nearest pixel with depth belongs to it, cut with the plane where its anchors pin it down."""
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)))
    if len(holes) == 0 or all(f[3] is None for f in found):
        return [empty] * len(found)
    from scipy.spatial import cKDTree

    owner = np.concatenate([np.full(len(f[0]), j) for j, f in enumerate(found)])
    pix = np.concatenate([f[0] for f in found])
    _, nearest = cKDTree(np.c_[rows[pix], cols[pix]]).query(np.c_[rows[holes], cols[holes]])
    rays = cam.pixel_rays()
    result = []
    for j, (_, _, _, ap, anchors_c) in enumerate(found):
        mine = holes[owner[nearest] == j]
        if ap is None or len(mine) == 0:
            result.append(empty)
            continue
        r = rays[rows[mine], cols[mine]]
        zk = ray_plane_depth(r, ap.n, ap.d)
        ok = np.isfinite(zk) & (zk > 0) & (zk < cfg.max_depth) & \
            (np.abs(r @ ap.n) / np.linalg.norm(r, axis=1) >= cfg.min_ray_cos)
        X = r * np.where(ok, zk, 0.0)[:, None]
        ok &= ap.std_at(X) <= cfg.max_plane_std
        if cfg.hull_margin_px >= 0:
            ok &= in_anchor_hull(cam, anchors_c, rows[mine], cols[mine], cfg.hull_margin_px * s)
        result.append((mine[ok], X[ok]))
    return result
