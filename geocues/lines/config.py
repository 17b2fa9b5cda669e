"""Configuration and result types of the line-cue stage (paper §4.1, "3D lines", after LIMAP).

Pixel thresholds are given for an image ``reference_width`` (640 px) wide and scaled linearly with
the actual width (:meth:`LineConfig.px`). Distances in 3D are metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np


@dataclass
class LineConfig:
    """Line cues: 2D segments -> matched -> triangulated, scored, merged 3D segments."""

    # ---- 2D detection (detect.py)
    detector: Literal["lsd", "fld"] = "lsd"
    """2D segment detector: OpenCV LSD (accurate) or FastLineDetector (faster, fewer segments)."""
    min_length_px: float = 20.0
    """Shortest 2D segment kept, in pixels at reference_width (scaled with the image width)."""
    max_segments: int = 400
    """At most this many (longest) 2D segments per image and source."""
    use_normal_priors: bool = True
    """Also detect segments on the normal priors when the scene has them (paper Fig. 3)."""
    dedup_angle_deg: float = 3.0
    """Segments closer than this angle (and dedup_dist_px) are one segment; RGB ones win."""
    dedup_dist_px: float = 2.0
    """Perpendicular distance (px at reference_width) of duplicates; twice it across RGB/normals."""
    use_test_views: bool = True
    """Use the held-out test views too (as SfM does); False restricts lines to training views."""
    test_every: int = 8
    """With use_test_views False: the held-out views to leave out are every n-th image in name order
    (index % n == 0), as `splat train --test-every n` holds them out (its default 8)."""
    # ---- view pairs (pairs.py)
    n_neighbors: int = 10
    """Neighbour views per image used for matching and multi-view scoring."""
    min_pair_overlap: float = 0.25
    """Smallest share of covisible SfM points / frustum samples for a view pair (pose-only case)."""
    pair_depths_m: tuple[float, ...] = (1.0, 2.0, 3.5)
    """Depths (metres) of the frustum samples used to rate view pairs when there are no SfM points."""
    good_pair_angle_deg: float = 8.0
    """Pairs whose median triangulation angle is below this are down-weighted (linearly)."""
    max_axis_angle_deg: float = 75.0
    """Largest angle between the optical axes of a view pair."""
    # ---- matching and two-view triangulation (match.py, triangulate.py)
    matcher: Literal["lbd", "epipolar"] = "lbd"
    """Rank epipolar candidates by LBD descriptor distance ("lbd") or by epipolar IoU only."""
    topk_matches: int = 3
    """Candidate matches kept per 2D segment and neighbour view."""
    min_epipolar_angle_deg: float = 3.0
    """Segments closer than this to the epipolar direction (in both views) are degenerate."""
    min_tri_angle_deg: float = 1.0
    """Smallest angle between a ray of one view and the segment plane of the other (LIMAP: 1)."""
    min_epipolar_iou: float = 0.1
    """Smallest epipolar IoU (overlap of a segment with the other's epipolar band) (LIMAP: 0.1)."""
    min_ray_angle_deg: float = 15.0
    """Lines closer than this to the viewing rays (LIMAP sensitivity > 75 deg) cannot be located:
    rejected when both views of a match see them so, and tracks need min_views views that do not."""
    max_depth_m: float = 30.0
    """Hypotheses with an endpoint farther than this from the camera are rejected."""
    # ---- multi-view scoring (score.py)
    support_angle_deg: float = 5.0
    """A 2D segment supports a 3D hypothesis if its angle to the projection is at most this."""
    support_dist_px: float = 1.5
    """... and its endpoints lie within this many pixels (at reference_width) of the projection."""
    support_depth_rel: float = 0.05
    """... and the depths it implies along the source rays agree within this relative tolerance."""
    support_coverage: float = 0.3
    """... and consistent segments of that view cover at least this share of its projection."""
    min_support_ratio: float = 0.5
    """Supporting views / views where the hypothesis is checkable (in view, depth-sensitive)."""
    seed_views: int = 0
    """Supporting views a two-view hypothesis needs to seed a track (0: min_views)."""
    min_views: int = 6
    """Minimum number of supporting views (including the two that triangulated it) per 3D line."""
    # ---- tracks, merging and output (merge.py)
    max_line_sigma_m: float = 0.02
    """Largest position std (metres for 1 px of 2D noise at reference_width) of a fitted 3D line."""
    link_depth_rel: float = 0.01
    """Two segments' hypotheses join one track if within merge_dist_m + this * depth (and the angle)."""
    min_track_ratio: float = 0.4
    """A line must be supported in this share of the views it projects into (guided matching)."""
    min_track_nodes: int = 1
    """A track needs this many 2D segments whose own best hypotheses agree (mutual confirmation)."""
    extent_min_share: float = 0.35
    """Segment ends: the line extends as far as this share of its views (at least 2) see it."""
    merge_angle_deg: float = 10.0
    """Two 3D lines closer than this angle and merge_dist_m are duplicates and are merged."""
    merge_dist_m: float = 0.02
    """Largest perpendicular distance (metres) between duplicate 3D lines."""
    merge_gap_m: float = 0.05
    """Largest gap (metres) along the line between two segments that are merged."""
    sample_step: float = 0.01
    """Spacing (metres) of the points sampled along each 3D segment."""
    reference_width: int = 640
    """Image width at which the pixel thresholds above are given."""

    def px(self, value: float, width: int) -> float:
        """A pixel threshold given at ``reference_width``, scaled to an image ``width`` wide."""
        return float(value) * float(width) / float(self.reference_width)

    @property
    def min_seed_views(self) -> int:
        """Supporting views a hypothesis needs to seed a track."""
        return self.seed_views or self.min_views

    def validate(self) -> None:
        """Raise ValueError on an inconsistent configuration."""
        if self.detector not in ("lsd", "fld"):
            raise ValueError(f"detector must be 'lsd' or 'fld', got {self.detector!r}")
        if self.matcher not in ("lbd", "epipolar"):
            raise ValueError(f"matcher must be 'lbd' or 'epipolar', got {self.matcher!r}")
        if self.test_every < 2:  # 1 holds out every view (Scene.load refuses it too)
            raise ValueError(f"--line.test-every must be >= 2 (every n-th image is held out), got {self.test_every}")
        if self.min_views < 2:
            raise ValueError(f"min_views must be >= 2, got {self.min_views}")
        if self.seed_views < 0 or 0 < self.seed_views < 2:
            raise ValueError(f"seed_views must be 0 (= min_views) or >= 2, got {self.seed_views}")
        for name in ("min_length_px", "sample_step", "support_dist_px", "merge_dist_m",
                     "reference_width", "n_neighbors", "topk_matches", "max_segments"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.pair_depths_m or min(self.pair_depths_m) <= 0:
            raise ValueError(f"pair_depths_m must be positive depths, got {self.pair_depths_m}")


@dataclass
class LineCues:
    """3D line cues of a scene: segments, their supporting views, colours and point samples."""

    segments: np.ndarray  # [L, 2, 3] float64 endpoints (metres, world frame)
    n_views: np.ndarray  # [L] int64 number of supporting views
    views: list[np.ndarray]  # L arrays of camera indices supporting each line
    colors: np.ndarray  # [L, 3] float32 in [0, 1], multi-view average
    points: np.ndarray  # [P, 3] float64 samples every cfg.sample_step along the segments
    point_colors: np.ndarray  # [P, 3] float32 in [0, 1]
    point_line: np.ndarray  # [P] int64 index of the line each sample lies on
    normals: np.ndarray  # [P, 3] float32, zeros (lines have no normal)
    rejected: dict[str, int] = field(default_factory=dict)  # reason -> count
    timings: dict[str, float] = field(default_factory=dict)  # stage -> seconds
    per_image: dict = field(default_factory=dict)  # "segments_rgb"/"segments_normal"/... -> per image

    def __post_init__(self) -> None:
        L, P = len(self.segments), len(self.points)
        if self.segments.shape != (L, 2, 3):
            raise ValueError(f"segments must be [L, 2, 3], got {self.segments.shape}")
        if self.n_views.shape != (L,) or len(self.views) != L or self.colors.shape != (L, 3):
            raise ValueError(f"n_views {self.n_views.shape}, views {len(self.views)}, colors "
                             f"{self.colors.shape} do not match {L} segments")
        for name, shape in (("point_colors", (P, 3)), ("point_line", (P,)), ("normals", (P, 3))):
            if getattr(self, name).shape != shape:
                raise ValueError(f"{name} must be {shape}, got {getattr(self, name).shape}")

    def __len__(self) -> int:
        return len(self.segments)

    @classmethod
    def empty(cls, rejected: dict[str, int] | None = None, timings: dict[str, float] | None = None,
              per_image: dict | None = None) -> "LineCues":
        """No lines (well-formed zero-length arrays)."""
        return cls(np.zeros((0, 2, 3)), np.zeros(0, np.int64), [], np.zeros((0, 3), np.float32),
                   np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                   np.zeros((0, 3), np.float32), dict(rejected or {}), dict(timings or {}),
                   dict(per_image or {}))

    def lengths(self) -> np.ndarray:
        """Segment lengths in metres, [L]."""
        return np.linalg.norm(self.segments[:, 1] - self.segments[:, 0], axis=-1)
