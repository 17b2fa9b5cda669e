"""Anchors: the 3D cue points (line samples, SfM points) that depth priors and prior-free planes
are fitted to, with the views each may be seen in."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Anchors:
    """3D cue points (line samples and SfM points) that anchor depth priors and prior-free planes."""

    xyz: np.ndarray  # [P, 3] world, metres
    cue_type: np.ndarray  # [P] uint8 CueType
    group: np.ndarray  # [P] int64: line index for line samples, -1 - point index for SfM points
    views: dict[int, np.ndarray] = field(default_factory=dict)  # camera -> anchors known visible
    unknown: np.ndarray | None = None  # [P] bool: visibility unknown, test by projection in all views

    def __post_init__(self) -> None:
        p = len(self.xyz)
        self.xyz = np.asarray(self.xyz, np.float64).reshape(p, 3)
        if self.cue_type.shape != (p,) or self.group.shape != (p,):
            raise ValueError(f"anchors: cue_type {self.cue_type.shape} / group {self.group.shape} "
                             f"do not match xyz ({p}, 3)")
        if self.unknown is None:
            self.unknown = np.zeros(p, bool)

    def __len__(self) -> int:
        return len(self.xyz)

    def candidates(self, cam_index: int) -> np.ndarray:
        """Indices of anchors that may be seen by camera ``cam_index``: its known-visible anchors
        plus every anchor whose visibility is unknown."""
        known = self.views.get(cam_index, np.zeros(0, np.int64))
        return np.union1d(known, np.flatnonzero(self.unknown)).astype(np.int64)

    def with_unknown(self, xyz: np.ndarray, group: np.ndarray) -> "Anchors":
        """These anchors, then line-like ``xyz`` [Q, 3] (``group`` [Q]: their line index) whose
        visibility is unknown: candidates of every camera, tested by projection (cheaper than
        listing every camera for each of many lines)."""
        from geocues.types import CueType

        q = len(xyz)
        return Anchors(np.concatenate([self.xyz, np.asarray(xyz, np.float64).reshape(q, 3)]),
                       np.concatenate([self.cue_type, np.full(q, int(CueType.LINE), np.uint8)]),
                       np.concatenate([self.group, np.asarray(group, np.int64).reshape(q)]),
                       self.views, np.concatenate([self.unknown, np.ones(q, bool)]))

    @staticmethod
    def build(sfm_xyz: np.ndarray | None = None, sfm_views: dict[int, np.ndarray] | None = None,
              line_points: np.ndarray | None = None, line_of_point: np.ndarray | None = None,
              line_views: list[np.ndarray] | None = None) -> "Anchors":
        """Anchors from SfM cues (``sfm_views``: camera -> row indices into ``sfm_xyz``; empty or
        None = unknown visibility) and line samples (``line_views[l]``: cameras supporting line l)."""
        from geocues.types import CueType

        parts_xyz, parts_type, parts_group, parts_unknown = [], [], [], []
        views: dict[int, list[np.ndarray]] = {}
        off = 0
        if sfm_xyz is not None and len(sfm_xyz):
            n = len(sfm_xyz)
            parts_xyz.append(np.asarray(sfm_xyz, np.float64).reshape(n, 3))
            parts_type.append(np.full(n, int(CueType.SFM), np.uint8))
            parts_group.append(-1 - np.arange(n, dtype=np.int64))
            has = bool(sfm_views) and any(len(v) for v in sfm_views.values())
            parts_unknown.append(np.full(n, not has))
            for cam, idx in (sfm_views or {}).items():
                views.setdefault(cam, []).append(np.asarray(idx, np.int64) + off)
            off += n
        if line_points is not None and len(line_points):
            n = len(line_points)
            lp = np.asarray(line_of_point, np.int64).reshape(n)
            parts_xyz.append(np.asarray(line_points, np.float64).reshape(n, 3))
            parts_type.append(np.full(n, int(CueType.LINE), np.uint8))
            parts_group.append(lp)
            parts_unknown.append(np.full(n, line_views is None))
            if line_views is not None:
                order = np.argsort(lp, kind="stable")
                starts = np.searchsorted(lp[order], np.arange(len(line_views) + 1))
                for li, cams in enumerate(line_views):
                    pts = order[starts[li]:starts[li + 1]] + off
                    for cam in np.asarray(cams, np.int64):
                        views.setdefault(int(cam), []).append(pts)
            off += n
        if not parts_xyz:
            return Anchors(np.zeros((0, 3)), np.zeros(0, np.uint8), np.zeros(0, np.int64))
        return Anchors(np.concatenate(parts_xyz), np.concatenate(parts_type),
                       np.concatenate(parts_group),
                       {c: np.unique(np.concatenate(v)) for c, v in views.items()},
                       np.concatenate(parts_unknown))
