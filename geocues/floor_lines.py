"""Floor-contact lines as plane-stage anchors (an extension; `geocues extract --floor.lines`).

Where the views that see a wall stand far from it and move along their viewing direction, its lines
triangulate badly and no 3D line cue reaches it (docs/training.md, "Which wall, and what could pin
it"). Its foot, though, lies on the floor, whose plane a first pass of the plane stage gives to a
millimetre: a 2D segment along the foot, lifted onto that plane from its own view (both end rays
cut with the plane), is placed in 3D from one image. Lifted segments of objects above the floor land
somewhere on it too, so a segment is kept only when ``min_views`` other images lift one onto the same
floor line (within ``angle_deg`` and ``dist``) and one of them sees its midpoint from at least
``min_azimuth_deg`` away in azimuth (a horizontal edge above the floor seen by views that move
along their viewing direction lifts consistently from all of them; from another azimuth it does not).
Kept segments are sampled every ``step`` metres and join the line anchors of the plane stage (with
the views that lifted them; the prior alignment takes them only in a view with too few measured
anchors, geocues.depth_align); they are not written as cue points.

The floor (geocues.floor): the lowest horizontal surface of the PLANE cues below the cameras, levelled
by the 3D line cues lying on it (``line_snap``). With no such cues there is no floor and nothing is
lifted. ``prior_check`` also asks each kept segment's own view's aligned depth prior
(:func:`on_floor_by_prior`).

``walls``, ``wall_check`` and ``wall_front_gap`` raise the kept segments into walls (geocues.walls).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from geocues.floor import Floor, find_floor, snap_iterated, strip_width

log = logging.getLogger(__name__)


@dataclass
class FloorLineConfig:
    """Floor-contact lines (an extension, off by default): 2D segments lifted onto the floor plane
    from single views, kept when other views agree, used as anchors of the plane stage."""

    lines: bool = False
    """Lift 2D segments onto the floor found by a first plane pass and anchor the plane stage with the
    ones other views agree on (an extension: pins walls no 3D line reaches; runs the plane stage twice)."""
    min_views: int = 4
    """A lifted segment is kept when this many other images lift one onto the same floor line ..."""
    angle_deg: float = 2.0
    """... within this angle (degrees) ..."""
    dist: float = 0.03
    """... with its midpoint within this distance (metres) of the line ..."""
    min_azimuth_deg: float = 15.0
    """... and one of them sees its midpoint from a horizontal direction at least this far (degrees)
    from its own view's (0 = no such test)."""
    step: float = 0.02
    """Spacing (metres) of the anchor samples along a kept segment."""
    max_range: float = 8.0
    """End rays that meet the floor farther than this (metres) from the camera are not lifted."""
    min_length: float = 0.2
    """Lifted segments shorter than this on the floor (metres) are dropped."""
    prior_check: bool = False
    """Also drop a kept segment unless its own view's aligned depth prior is within prior_rel of the
    floor's depth at 3 of 5 points along it (views without an aligned prior, or with prior depth at
    fewer than 3 of the points, pass)."""
    prior_rel: float = 0.05
    """That test's tolerance, a fraction of the depth (the warp a monocular prior keeps after alignment)."""
    horizontal_deg: float = 20.0
    """PLANE cues whose normal is within this angle of up are horizontal (floor candidates)."""
    min_floor_points: int = 50
    """The floor needs at least this many horizontal PLANE cues near its height."""
    line_snap: bool = True
    """Refit the floor through the 3D line cues lying on it (the plane cues' floor can sit a centimetre
    high, which moves a far wall's lifted foot several centimetres toward the cameras)."""
    walls: bool = False
    """Also raise each kept segment into a vertical sheet of anchors for the plane checks only, not the
    prior alignment (an extension on top of --floor.lines: assumes walls stand vertical on their foot)."""
    wall_step: float = 0.1
    """Spacing (metres) of those anchors, along the segment and upwards."""
    wall_height: float = 0.0
    """How high they reach above the floor (metres); 0 = the higher of the first pass's plane cues
    (99th percentile) and the highest camera + 1 m. Anchors behind a view's aligned surface are dropped."""
    wall_check: bool = False
    """Raise a kept segment only as far as the aligned depth priors of the views that lifted it show a
    surface there: its rows stop below the first two in a row that they contradict (a sofa's foot is
    raised to the sofa's top, not to the ceiling), and a segment none of whose rows from 0.3 m up they
    confirm is not raised (a texture line on the floor, whose raised rows float in front of what the
    views see). Segments without prior evidence are raised as without the check. An extension; needs walls."""
    wall_check_rel: float = 0.1
    """That check's tolerance, a fraction of the depth (loose: the prior only says yes or no here)."""
    wall_front_gap: float = 0.0
    """With wall_check, > 0: a raised segment whose foot lies less than this (metres) in front of a
    parallel raised segment (as seen from the cameras' centroid) that overlaps half its length and
    reaches as high is not raised: a floor line near a wall, closer than the priors' tolerance tells
    apart. 0 = off. An extension."""

    ceiling: bool = False
    """Also place the ceiling (geocues.ceiling): a level plane at the median over the views of the
    height their aligned priors give the horizontal surfaces above the cameras, anchored by a grid
    over the raised walls' footprint; the walls are raised up to it. An extension; needs
    wall_check (its aligned priors)."""
    floor_grid: bool = False
    """Also lay a grid of assumed anchors on the floor plane over the raised walls' footprint (an
    extension; needs walls): a floor region whose anchors are one wall's foot line leaves its plane
    free to turn about it, and only a band along the foot was kept."""
    level_snap: bool = False
    """With ceiling or floor_grid: a weak region whose aligned prior lies on the ceiling's (or the
    floor's) level plane -- 80 % of its pixels' prior points within level_rel of their depth from it,
    along its normal -- is cut onto that plane (those pixels), instead of passing the anchors' check
    of its own prior plane, which a warped prior fails on a ceiling seen in a strip at the top of a
    few views. An extension; an assumption like the grids."""
    level_rel: float = 0.05
    """That test's tolerance, a fraction of the depth (the warp an aligned monocular prior keeps)."""
    wall_snap: bool = False
    """With level_snap and wall_check: the walls' vertical planes (each run of collinear kept segments
    raised to wall_snap_height of the walls' top or higher, refitted to the first pass's plane cues on
    it, dropped where none lie) take what the anchored planes leave: the pixels of a region's RANSAC
    plane that no anchored plane took (no anchor near, outside their hull) are cut onto the wall plane
    their prior lies on (level_rel, as level_snap), unless the region's cue anchors put the surface
    3 cm or more off it. For the part of a wall no cue reaches. An extension; an assumption like the grids."""
    wall_snap_height: float = 0.6
    """A raised segment defines a wall plane for wall_snap when its rows reach this share of the top
    (a cabinet's or a sofa's foot, stopped by the wall check lower, does not)."""
    ceiling_margin: float = 0.3
    """Only surfaces more than this (metres) above the highest camera count as the ceiling."""
    ceiling_min_views: int = 3
    """Views that must see such a surface; with fewer no ceiling is placed."""

    def validate(self) -> None:
        for name in ("angle_deg", "dist", "step", "max_range", "min_length", "prior_rel", "wall_step",
                     "wall_check_rel", "level_rel", "wall_snap_height"):
            if not getattr(self, name) > 0:
                raise ValueError(f"--floor.{name.replace('_', '-')} must be > 0, got {getattr(self, name)}")
        if self.min_views < 1:
            raise ValueError(f"--floor.min-views must be >= 1, got {self.min_views}")
        if not 0 <= self.min_azimuth_deg < 180:
            raise ValueError(f"--floor.min-azimuth-deg must be in [0, 180), got {self.min_azimuth_deg}")
        if self.min_floor_points < 3:
            raise ValueError(f"--floor.min-floor-points must be >= 3, got {self.min_floor_points}")
        if self.wall_height < 0:
            raise ValueError(f"--floor.wall-height must be >= 0 (0 = automatic), got {self.wall_height}")
        if self.walls and not self.lines:
            raise ValueError("--floor.walls raises the floor lines: it needs --floor.lines")
        if self.wall_check and not self.walls:
            raise ValueError("--floor.wall-check checks the raised walls: it needs --floor.walls")
        if self.wall_front_gap < 0 or (self.wall_front_gap > 0 and not self.wall_check):
            raise ValueError("--floor.wall-front-gap must be >= 0 and, when > 0, needs --floor.wall-check")
        if self.ceiling and not self.wall_check:
            raise ValueError("--floor.ceiling reads the aligned priors of --floor.wall-check: it needs it")
        if self.floor_grid and not self.walls:
            raise ValueError("--floor.floor-grid spans the raised walls' footprint: it needs --floor.walls")
        if self.level_snap and not (self.ceiling or self.floor_grid):
            raise ValueError("--floor.level-snap cuts regions onto the ceiling's or the floor's level plane: "
                             "it needs --floor.ceiling or --floor.floor-grid")
        if self.wall_snap and not (self.level_snap and self.wall_check):
            raise ValueError("--floor.wall-snap adds the checked walls' planes to --floor.level-snap: it needs "
                             "--floor.level-snap and --floor.wall-check (--floor.no-wall-snap turns it off, "
                             "also in --preset room)")
        if self.wall_snap_height > 1:
            raise ValueError(f"--floor.wall-snap-height is a share of the walls' top, in (0, 1]; got "
                             f"{self.wall_snap_height}")
        if self.ceiling_margin < 0 or self.ceiling_min_views < 1:
            raise ValueError("--floor.ceiling-margin must be >= 0 and --floor.ceiling-min-views >= 1")
        if not 0 < self.horizontal_deg < 90:
            raise ValueError(f"--floor.horizontal-deg must be in (0, 90), got {self.horizontal_deg}")


@dataclass
class Lifted:
    """2D segments lifted onto the floor."""

    view: np.ndarray  # [N] image index
    seg: np.ndarray  # [N] index of the 2D segment in its image's list
    ends: np.ndarray  # [N, 2, 3] world end points on the floor
    uv: np.ndarray  # [N, 2, 2] the same in the floor's in-plane coordinates

    def __len__(self) -> int:
        return len(self.view)


def floor_depth(cam, px: np.ndarray, floor: Floor) -> tuple[np.ndarray, np.ndarray]:
    """(z-depth [M] at which the rays through COLMAP pixels ``px`` [M, 2] of ``cam`` meet the floor
    -- inf or negative where they do not --, the rays' world directions [M, 3], camera z = 1)."""
    d = (np.c_[px, np.ones(len(px))] @ np.linalg.inv(cam.K).T) @ np.asarray(cam.R)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (floor.height - np.asarray(cam.center) @ floor.normal) / (d @ floor.normal), d


def depth_along(cam, seg: np.ndarray, floor: Floor, depth: np.ndarray, n: int = 5
                ) -> tuple[np.ndarray, np.ndarray]:
    """(the floor's z-depth [n], ``depth``'s value [n]) at ``n`` points from 10 to 90 % along the 2D
    segment ``seg`` [4] of ``cam``; ``depth`` may have any resolution (nearest pixel)."""
    px = seg[:2] + np.linspace(0.1, 0.9, n)[:, None] * (seg[2:] - seg[:2])  # [n, 2] COLMAP pixels
    return floor_depth(cam, px, floor)[0], sample_nearest(depth, cam, px)


def sample_nearest(depth: np.ndarray, cam, px: np.ndarray) -> np.ndarray:
    """``depth`` (any resolution of ``cam``'s image: every 4th pixel in `geocues extract`) at COLMAP
    pixels ``px`` [M, 2] of ``cam``, nearest pixel, float64 [M]."""
    rows = np.clip((px[:, 1] * depth.shape[0] / cam.height).astype(int), 0, depth.shape[0] - 1)
    cols = np.clip((px[:, 0] * depth.shape[1] / cam.width).astype(int), 0, depth.shape[1] - 1)
    return depth[rows, cols].astype(np.float64)


def lift_segments(cameras, segments: list[np.ndarray], floor: Floor, cfg: FloorLineConfig) -> Lifted:
    """Every segment (``segments[i]``: [S, 4] x1 y1 x2 y2 in COLMAP pixels of ``cameras[i]``) whose
    two end rays meet the floor within ``cfg.max_range`` and ``cfg.min_length`` apart."""
    views, index, ends = [], [], []
    for cam, segs in zip(cameras, segments):
        segs = np.asarray(segs, np.float64).reshape(-1, 4)
        if not len(segs):
            continue
        t, d = floor_depth(cam, segs.reshape(-1, 2), floor)  # [2S], [2S, 3]: both ends of each segment
        ok = (np.abs(d @ floor.normal) > 1e-9) & (t > 0) & (t * np.linalg.norm(d, axis=1) <= cfg.max_range)
        X = (np.asarray(cam.center) + np.where(ok, t, 0.0)[:, None] * d).reshape(-1, 2, 3)
        ok = ok.reshape(-1, 2).all(axis=1) & (np.linalg.norm(X[:, 1] - X[:, 0], axis=1) > cfg.min_length)
        views.append(np.full(int(ok.sum()), cam.index, np.int64))
        index.append(np.flatnonzero(ok))
        ends.append(X[ok])
    if not views:
        return Lifted(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2, 3)), np.zeros((0, 2, 2)))
    ends_ = np.concatenate(ends)
    return Lifted(np.concatenate(views), np.concatenate(index), ends_, ends_ @ floor.basis().T)


def kept_segments(lifted: Lifted, centres_uv: np.ndarray, cfg: FloorLineConfig) -> list[tuple[int, np.ndarray]]:
    """(index into ``lifted``, the other images that lift a segment onto the same floor line) of the
    kept segments (module docstring); ``centres_uv`` [V, 2]: camera centres in floor coordinates."""
    if not len(lifted):
        return []
    p, q = lifted.uv[:, 0], lifted.uv[:, 1]
    mids = 0.5 * (p + q)  # [N, 2]
    th = np.arctan2(q[:, 1] - p[:, 1], q[:, 0] - p[:, 0]) % np.pi  # [N] line direction
    nrm = np.stack([-np.sin(th), np.cos(th)], axis=1)  # [N, 2] line normals
    tol = np.radians(cfg.angle_deg)
    out = []
    for a in range(len(lifted)):  # same line: parallel within tol, midpoints within dist of a's line
        same = (np.abs((th - th[a] + np.pi / 2) % np.pi - np.pi / 2) < tol) \
            & (np.abs((mids - p[a]) @ nrm[a]) < cfg.dist)
        others = np.unique(lifted.view[same & (lifted.view != lifted.view[a])])
        if len(others) < cfg.min_views:
            continue
        if cfg.min_azimuth_deg > 0:
            mid = mids[a]
            az = np.arctan2(*(mid - centres_uv[others]).T[::-1])
            az0 = np.arctan2(*(mid - centres_uv[lifted.view[a]])[::-1])
            if not (np.abs((az - az0 + np.pi) % (2 * np.pi) - np.pi) >= np.radians(cfg.min_azimuth_deg)).any():
                continue
        out.append((a, others))
    return out


def anchor_samples(lifted: Lifted, keep: list[tuple[int, np.ndarray]], step: float
                   ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """([P, 3] points every ``step`` along each kept segment, [P] its index in ``keep``, per kept
    segment the views that lifted it, its own included)."""
    pts, lid, views = [], [], []
    for k, (a, others) in enumerate(keep):
        p, q = lifted.ends[a]
        n = max(int(np.linalg.norm(q - p) / step), 2)
        f = np.linspace(0.0, 1.0, n)[:, None]
        pts.append(p + f * (q - p))
        lid.append(np.full(n, k, np.int64))
        views.append(np.union1d(others, [lifted.view[a]]).astype(np.int64))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64), []
    return np.concatenate(pts), np.concatenate(lid), views


def on_floor_by_prior(cam, seg: np.ndarray, floor: Floor, prior: np.ndarray, rel: float) -> bool:
    """Whether the aligned depth ``prior`` of ``cam`` (any resolution: every 4th pixel in
    `geocues extract`) agrees, within ``rel`` of the depth, with the floor's depth at 3 of 5 points
    along the 2D segment ``seg`` [4]; True when fewer than 3 of them have prior depth."""
    z, p = depth_along(cam, seg, floor, prior)
    valid = (p > 0) & np.isfinite(p)
    if valid.sum() < 3:
        return True
    return int((valid & (np.abs(p - z) <= rel * np.abs(z))).sum()) >= 3


def floor_line_anchors(cameras, segments: list[np.ndarray], plane_xyz: np.ndarray, plane_normal: np.ndarray,
                       cfg: FloorLineConfig, priors: dict[int, np.ndarray] | None = None,
                       line_segments: np.ndarray | None = None, support_xyz: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], dict]:
    """The floor-line anchors of a scene: (points [P, 3], kept-segment index [P], views per kept
    segment, statistics for the report; ``"note"`` there when nothing could be lifted). ``priors``:
    image index -> aligned prior depth, for ``cfg.prior_check``; ``line_segments`` [L, 2, 3]: the 3D
    line cues, for ``cfg.line_snap``; ``support_xyz`` [M, 3]: the 3D cues (SfM points, line samples)
    that tell a table top from the floor (geocues.floor.find_floor)."""
    cfg.validate()
    floor, why = find_floor(plane_xyz, plane_normal, cameras, cfg, support_xyz)
    if floor is None:
        return np.zeros((0, 3)), np.zeros(0, np.int64), [], {"floor": None, "note": f"no floor found: {why}"}
    n_snap, cue_floor = 0, floor
    if cfg.line_snap and line_segments is not None and len(line_segments):
        floor, n_snap = snap_iterated(floor, line_segments)
    strip = strip_width(cue_floor)
    if strip is not None and strip < 0.3 and np.array_equal(floor.normal, cue_floor.normal):
        log.warning("the floor's plane cues lie in a strip about %.1f m wide (std %.2f m across it) and no floor "
                    "lines level it: its tilt rests on that strip, and walls far from it may be lifted centimetres "
                    "off (views that see more of the floor help)", strip * 12 ** 0.5, strip)
    lifted = lift_segments(cameras, segments, floor, cfg)
    centres_uv = np.array([np.asarray(c.center) for c in cameras]) @ floor.basis().T
    keep = kept_segments(lifted, centres_uv, cfg)
    n_kept = len(keep)
    if cfg.prior_check and priors:
        keep = [(a, o) for a, o in keep if (v := int(lifted.view[a])) not in priors or on_floor_by_prior(
            cameras[v], np.asarray(segments[v])[lifted.seg[a]], floor, priors[v], cfg.prior_rel)]
    P, L, V = anchor_samples(lifted, keep, cfg.step)
    stats = {"floor": {"normal": floor.normal.round(5).tolist(), "height": round(floor.height, 5),
                       "n_points": floor.n_points, "snapped_to_lines": n_snap},
             "lifted": len(lifted), "kept": len(keep), "samples": len(P)}
    if cfg.prior_check:
        stats["dropped_by_prior"] = n_kept - len(keep)
    return P, L, V, stats
