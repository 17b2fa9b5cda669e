"""Fusing the images' prior planes into surfaces before cutting rays (our extension,
``--plane.fuse-surfaces``; docs/geocues.md, "Surface fusion").

One image's plane is pinned by the cues it sees near its region. On a weak-texture wall these are
often a single border line: the line fixes the plane along itself, its tilt about the line comes
only from the prior's normal (a few degrees), so ``max_plane_std`` keeps a strip along the border
and the middle of the wall gets no cue (the bare benchmark room: 14 % of its surface covered).
Other images see the wall's other borders. Here the prior planes of all images that describe one
surface are grouped -- normals within ``surface_angle_deg``, each image's prior within its warp
tolerance of the group's plane, its own agreeing anchors within ``agree_dist`` of it -- and the
group's plane is fitted to the union of their anchors (:class:`AnchoredPlane`, every line and SfM
point once). Each member image's pixels are then cut with that plane and kept where it is pinned to
``max_plane_std``, inside the image hull of its anchors, and where the image's own prior agrees.
Pixels of a plane that no anchor confirms in its own image can join a surface that other images'
anchors pin down; a surface with no anchors at all gives nothing (as ``require_anchors``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from geocues.plane_fit import AnchoredPlane, group_weights, ray_plane_depth
from geocues.plane_regions import in_anchor_hull

if TYPE_CHECKING:
    from geocues.planes import PlaneConfig
    from geocues.scene import Camera


@dataclass
class SurfaceCandidate:
    """One image's plane of one weak-texture region, before any cut: world plane n·X + d = 0 from
    RANSAC on the aligned prior, its pixels, their prior depth and colour, and the global ids of the
    anchors (lines' samples, SfM points) that agree with it in that image (empty if none)."""

    view: int
    n: np.ndarray  # [3] world
    d: float
    rows: np.ndarray  # [m] int
    cols: np.ndarray  # [m] int
    z_prior: np.ndarray  # [m] float32, aligned prior depth (metres)
    rgb: np.ndarray  # [m, 3] float32 in [0, 1]
    anchor_ids: np.ndarray  # [a] int64

    @staticmethod
    def from_camera_plane(cam: Camera, n_c: np.ndarray, d_c: float, rows: np.ndarray, cols: np.ndarray,
                          z_prior: np.ndarray, rgb: np.ndarray, anchor_ids: np.ndarray) -> "SurfaceCandidate":
        """x_cam = R X + t: n_c·(R X + t) + d_c = 0  =>  n = Rᵀ n_c, d = d_c + n_c·t."""
        n_c = np.asarray(n_c, np.float64)
        return SurfaceCandidate(cam.index, cam.R.T @ n_c, float(d_c + n_c @ cam.t), rows.astype(np.int32),
                                cols.astype(np.int32), z_prior.astype(np.float32), rgb.astype(np.float32),
                                np.unique(np.asarray(anchor_ids, np.int64)))

    def prior_points(self, cam: Camera, max_n: int = 256) -> np.ndarray:
        """Up to ``max_n`` of the pixels' prior points in world coordinates [k, 3] (evenly spaced)."""
        step = max(1, len(self.rows) // max_n)
        r = cam.rays_at(self.rows[::step], self.cols[::step]) * self.z_prior[::step, None]
        return (r - cam.t) @ cam.R


@dataclass
class Surface:
    """A fused surface: its member candidates (indices) and the plane fitted to their anchors."""

    members: list[int]
    plane: AnchoredPlane
    anchor_ids: np.ndarray


def _tolerance(z: np.ndarray | float, cfg: PlaneConfig) -> np.ndarray | float:
    """How far an aligned prior may lie from the true surface at depth z: its low-frequency warp."""
    return np.maximum(cfg.fuse_prior_dist, cfg.fuse_prior_rel * np.asarray(z))


def _fit(ids: np.ndarray, n0: np.ndarray, xyz: np.ndarray, group: np.ndarray, cfg: PlaneConfig
         ) -> tuple[AnchoredPlane, np.ndarray]:
    """The plane of anchors ``ids`` and the ids it keeps: anchor groups (a line, an SfM point) whose
    mean absolute residual exceeds ``anchor_sigma`` are dropped, worst first, and the
    plane refitted. Images accept anchors within ``agree_dist`` of their own plane; a line a few
    centimetres off the surface (a threshold's edge beside the floor line) then gets in, and the
    fit of all of them would split the difference, tilting the plane across the whole surface."""
    while True:
        g = group[ids]
        ap = AnchoredPlane(xyz[ids], group_weights(g), n0, cfg.anchor_sigma,
                           np.radians(cfg.prior_normal_std_deg), huber=cfg.agree_dist)
        uniq, inv = np.unique(g, return_inverse=True)
        inv = inv.ravel()
        mean = np.bincount(inv, np.abs(ap.residual)) / np.bincount(inv)  # mean |residual| per group
        worst = int(np.argmax(mean))
        if mean[worst] <= cfg.anchor_sigma or len(uniq) <= 1:
            return ap, ids
        drop = (mean > 3.0 * cfg.anchor_sigma) | (np.arange(len(uniq)) == worst)  # clear outliers at once
        if drop.all():
            drop = np.arange(len(uniq)) == worst
        ids = ids[~drop[inv]]


def group_surfaces(cands: list[SurfaceCandidate], cams: list[Camera], anchors_xyz: np.ndarray,
                   anchors_group: np.ndarray, cfg: PlaneConfig) -> list[Surface]:
    """Greedy grouping, the candidate with the most anchors first. A candidate joins a surface if
    its anchors and the surface's are coplanar -- the plane refitted to all of them keeps every
    line of both (:func:`_fit`) -- and that plane is within ``surface_angle_deg`` of the candidate's
    prior plane and of the surface's plane before, within ``surface_consensus_deg`` of the mean of
    the members' prior normals, with every member's prior points within the warp tolerance of it
    (median). A candidate without anchors joins on the last two tests alone.
    Candidates are visited in up to 3 rounds, so a plane pinned by a new line can take more."""
    if not cands:
        return []
    pts = [c.prior_points(cams[c.view]) for c in cands]
    cen = np.array([p.mean(axis=0) if len(p) else np.zeros(3) for p in pts])
    zmed = np.array([float(np.median(c.z_prior)) if len(c.z_prior) else 0.0 for c in cands])
    normals = np.array([c.n for c in cands])
    n_anchor = np.array([len(c.anchor_ids) for c in cands])
    cos_max = np.cos(np.radians(cfg.surface_angle_deg))
    owner = np.full(len(cands), -1, np.int64)
    surfaces: list[Surface] = []
    for s in np.argsort(-n_anchor, kind="stable"):
        if owner[s] >= 0 or n_anchor[s] < cfg.min_agree_anchors:
            continue
        members = [int(s)]
        plane, ids = _fit(cands[s].anchor_ids, cands[s].n, anchors_xyz, anchors_group, cfg)
        owner[s] = len(surfaces)
        for _ in range(3):
            free = np.flatnonzero(owner < 0)
            near = free[(np.abs(normals[free] @ plane.n) >= cos_max)
                        & (np.abs(cen[free] @ plane.n + plane.d) <= 2.0 * _tolerance(zmed[free], cfg))]
            added = 0
            for q in near:
                joined = _join(cands[q], pts[q], zmed[q], plane, ids, anchors_xyz, anchors_group, cos_max, cfg,
                               [(pts[m], zmed[m]) for m in members], normals[members + [int(q)]])
                if joined is None:
                    continue
                plane, ids = joined
                owner[q] = len(surfaces)
                members.append(int(q))
                added += 1
            if not added:
                break
        surfaces.append(Surface(members, plane, ids))
    return surfaces


def _join(cand: SurfaceCandidate, pts: np.ndarray, zmed: float, plane: AnchoredPlane, ids: np.ndarray,
          anchors_xyz: np.ndarray, anchors_group: np.ndarray, cos_max: float, cfg: PlaneConfig,
          members: list[tuple[np.ndarray, float]], member_normals: np.ndarray
          ) -> tuple[AnchoredPlane, np.ndarray] | None:
    """The surface's (plane, anchor ids) with ``cand`` in it, or None if it does not belong.
    ``members``: (prior points, median depth) of the surface's members so far."""
    new = plane, ids
    if len(cand.anchor_ids):
        union = np.union1d(ids, cand.anchor_ids)
        joint, kept = _fit(union, plane.n, anchors_xyz, anchors_group, cfg)
        if len(np.setdiff1d(anchors_group[union], anchors_group[kept])):
            return None  # not coplanar: its cues put it elsewhere (a cabinet front before a wall)
        if abs(float(joint.n @ plane.n)) < cos_max:
            return None  # two parallel lines are always coplanar: the plane must stay the surface's
        if any(np.median(np.abs(mp @ joint.n + joint.d)) > _tolerance(mz, cfg) for mp, mz in members):
            return None  # ... and its members' priors must still lie on it (two vertical corner lines
            #              of different walls span a plane through the room that no image sees)
        signs = np.where(member_normals @ joint.n < 0, -1.0, 1.0)  # the members' prior planes, on average,
        consensus = (member_normals * signs[:, None]).mean(axis=0)  # must not be turned away from: each
        if float(joint.n @ consensus) < np.linalg.norm(consensus) * np.cos(np.radians(cfg.surface_consensus_deg)):
            return None  # is tilted by its own warp, their mean much less (a line of an object before a
            #              wall, parallel to the wall's only line, turned it by 11 degrees on a held-out room)
        new = joint, kept
    p = new[0]
    if abs(float(cand.n @ p.n)) < cos_max or np.median(np.abs(pts @ p.n + p.d)) > _tolerance(zmed, cfg):
        return None
    return new


def cut_with_surface(cand: SurfaceCandidate, cam: Camera, surface: Surface, anchors_xyz: np.ndarray,
                     cfg: PlaneConfig) -> tuple[np.ndarray, np.ndarray]:
    """The candidate's pixels on the surface's plane: (kept pixel mask [m], world points [k, 3]).
    Kept where the ray meets the plane in front of the camera at a non-grazing angle, within
    ``max_depth``, where the plane is pinned to ``max_plane_std``, inside the image hull of the
    surface's anchors in front of the camera (grown by ``hull_margin_px``), and where the image's
    own prior depth is within the warp tolerance of the cut."""
    ap = surface.plane
    n_c = cam.R @ ap.n
    d_c = ap.d - float(n_c @ cam.t)
    r = cam.rays_at(cand.rows, cand.cols)
    z = ray_plane_depth(r, n_c, d_c)
    ok = np.isfinite(z) & (z > 0) & (z < cfg.max_depth) & \
        (np.abs(r @ n_c) / np.linalg.norm(r, axis=1) >= cfg.min_ray_cos)
    z = np.where(ok, z, 0.0)
    ok &= np.abs(z - cand.z_prior) <= _tolerance(cand.z_prior, cfg)
    Xw = (r * z[:, None] - cam.t) @ cam.R
    ok &= ap.std_at(Xw) <= cfg.max_plane_std
    if cfg.hull_margin_px >= 0 and ok.any():
        a_c = anchors_xyz[surface.anchor_ids] @ cam.R.T + cam.t
        a_c = a_c[a_c[:, 2] > 0.05]
        if len(a_c) >= 3:
            ok &= in_anchor_hull(cam, a_c, cand.rows, cand.cols, cfg.hull_margin_px * cam.width / 640.0)
        else:
            ok[:] = False
    return ok, Xw[ok]


def fuse_surfaces(cands: list[SurfaceCandidate], cams: list[Camera], anchors_xyz: np.ndarray,
                  anchors_group: np.ndarray, cfg: PlaneConfig) -> tuple[list[tuple], dict[str, int]]:
    """Group the candidates into surfaces and cut every member's pixels with its surface.

    Returns ([(view, xyz [k, 3], rgb [k, 3], normal [k, 3] facing the camera, plane [4]) per member
    with points], statistics)."""
    anchors_xyz = np.asarray(anchors_xyz, np.float64)
    surfaces = group_surfaces(cands, cams, anchors_xyz, np.asarray(anchors_group), cfg)
    out = []
    grouped = 0
    for surf in surfaces:
        for q in surf.members:
            cand, cam = cands[q], cams[cands[q].view]
            keep, Xw = cut_with_surface(cand, cam, surf, anchors_xyz, cfg)
            if not len(Xw):
                continue
            mid = Xw.mean(axis=0)
            n = surf.plane.n if float(surf.plane.n @ (cam.center - mid)) > 0 else -surf.plane.n
            out.append((cand.view, Xw, cand.rgb[keep], np.broadcast_to(n, Xw.shape).copy(), np.r_[n, -float(n @ mid)]))
        grouped += len(surf.members)
    stats = {"surface_candidates": len(cands), "surfaces": len(surfaces),
             "surfaces_of_several_images": sum(len({cands[q].view for q in s.members}) > 1 for s in surfaces),
             "candidates_without_surface": len(cands) - grouped}
    return out, stats
