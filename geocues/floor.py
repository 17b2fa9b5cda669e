"""The floor plane of a scene from its PLANE cues, levelled by the 3D line cues lying on it.

Up is the mean of the cameras' up vectors (-R[1]) snapped to the horizontal PLANE cues' normals; the
floor is the lowest well-filled 2 cm height bin of the horizontal PLANE cues below the cameras, then a
plane through the median heights of 25 cm cells (:func:`_level_fit`), then refitted through the 3D line
cues lying on it (:func:`snap_to_lines`, :func:`snap_iterated`; ``--floor.line-snap``: the plane cues'
floor sat 1 cm high on a benchmark room, which put a far wall's lifted foot 5 cm in front of it). With
no such cues there is no floor; nor when the scene's SfM points and line samples lie under it and form
no lower layer (a table top: :data:`BELOW_SHARE`), or its cues lie in a strip (:data:`MIN_ACROSS_STD`).
Used by the floor lines (geocues.floor_lines), the walls and the ceiling.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from geocues.floor_lines import FloorLineConfig


@dataclass
class Floor:
    """The plane n . X = height (n: unit, up)."""

    normal: np.ndarray  # [3]
    height: float
    n_points: int  # cues it was fitted to (horizontal PLANE cues; SfM points and line samples under a table)
    cue_cov: np.ndarray | None = None  # [3, 3] covariance of those cues' positions (how far they spread)

    def basis(self) -> np.ndarray:
        """[2, 3] orthonormal in-plane axes."""
        a = np.eye(3)[int(np.argmin(np.abs(self.normal)))]
        e1 = np.cross(self.normal, a)
        e1 /= np.linalg.norm(e1)
        return np.stack([e1, np.cross(self.normal, e1)])


def up_direction(cameras) -> np.ndarray | None:
    """Mean of the cameras' up vectors (-R[1], OpenCV y points down), unit; None when they do not
    agree (norm of the mean < 0.5: cameras rolled every way)."""
    m = -np.mean([np.asarray(c.R)[1] for c in cameras], axis=0)
    n = float(np.linalg.norm(m))
    return m / n if n >= 0.5 else None


MIN_ACROSS_STD = 0.05
"""A floor whose cues lie in a patch narrower than this (metres, standard deviation across its longer
direction) is not found: nothing there fixes its tilt across the patch (two 24-view benchmark rooms saw
their bare floor only in a strip 0.07 m wide (std 0.02 m): fitted 9 and 15 degrees off level)."""
BELOW_MARGIN = 0.05
"""3D cues (SfM points, line samples) more than this (metres) below a floor candidate are under it ..."""
MAX_DROP = 3.0
"""... down to this far (metres) below it: farther ones are outliers (no room's floor lies so far under
its lowest horizontal surface)."""
BELOW_SHARE = 0.05
"""... and a candidate with this share of the 3D cues below the cameras under it and outside its own
cues' footprint (and at least ``min_floor_points``) is no floor: a table top whose plane cues are the
lowest horizontal ones (a textured floor is SfM points, not plane cues). Points under the candidate's
own footprint do not count: reflections in a glossy floor are triangulated below it."""


def _lowest_layer(h: np.ndarray, min_points: int) -> float | None:
    """Height of the lowest well-filled 2 cm layer of heights ``h`` [N]: the peak bin of the lowest
    run of three bins holding ``min_points`` and a fifth of the fullest run; None when none does."""
    if len(h) < min_points:
        return None
    bins = np.floor((h - h.min()) / 0.02).astype(np.int64)
    count = np.bincount(bins)
    width3 = np.convolve(count, np.ones(3, np.int64), mode="same")  # a surface spreads over a few bins
    full = np.flatnonzero(width3 >= max(min_points, 0.2 * width3.max()))
    if not len(full):
        return None
    b = max(int(full[0]) - 1, 0)
    b += int(np.argmax(count[b:int(full[0]) + 2]))  # the peak bin of that surface
    return float(h.min() + 0.02 * (b + 0.5))


def _outside(X: np.ndarray, cues: np.ndarray, basis: np.ndarray, margin: float = 0.1) -> np.ndarray:
    """[M] bool: the points ``X`` [M, 3] lie outside the convex hull of ``cues`` [N, 3] (in-plane axes
    ``basis`` [2, 3]) by more than ``margin`` metres (every point, when the cues span no area)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        eq = ConvexHull(cues @ basis.T).equations  # [E, 3]: inside where a . uv + b <= 0 for every edge
    except (QhullError, ValueError):
        return np.ones(len(X), bool)
    return ((X @ basis.T) @ eq[:, :2].T + eq[:, 2]).max(axis=1, initial=-np.inf) > margin


def _fit_layer(pts: np.ndarray, up: np.ndarray, h0: float, level: bool = False) -> tuple[Floor, np.ndarray]:
    """The floor through the points ``pts`` [N, 3] within 3 cm of height ``h0`` (:func:`_level_fit`;
    ``level``: normal ``up`` at their median height); (floor, their mask)."""
    near = np.abs(pts @ up - h0) < 0.03
    normal, height = (up, float(np.median(pts[near] @ up))) if level else _level_fit(pts[near], up)
    return Floor(normal, height, int(near.sum()), np.cov(pts[near].T)), near


def _under(floor: Floor, support: np.ndarray, cues: np.ndarray, min_points: int) -> int | None:
    """How many of the 3D cues ``support`` [M, 3] (already below the cameras) lie more than
    BELOW_MARGIN under ``floor`` and outside the footprint of its ``cues`` [N, 3], when that many say
    it is no floor; else None."""
    under = support @ floor.normal - floor.height < -BELOW_MARGIN
    n = int(np.sum(_outside(support[under], cues, floor.basis()))) if under.any() else 0
    return n if n >= max(min_points, BELOW_SHARE * len(support)) else None


def find_floor(xyz: np.ndarray, normal: np.ndarray, cameras, cfg: FloorLineConfig,
               support: np.ndarray | None = None) -> tuple[Floor | None, str]:
    """The floor from PLANE cues ``xyz`` / ``normal`` [N, 3]; (None, why) when there is none.
    ``support`` [M, 3]: the scene's 3D cues (SfM points, line samples), which a floor has (almost)
    none of under it: when the lowest horizontal plane cues have (BELOW_SHARE), the floor is the lowest
    well-filled layer of the 3D cues under them (parallel to the plane fitted to those plane cues, at
    the layer's median height: a few dozen points tilted it 0.3 degrees), or there is none."""
    up = up_direction(cameras)
    if up is None:
        return None, "the cameras agree on no up direction"
    n = np.asarray(normal, np.float64).reshape(-1, 3)
    x = np.asarray(xyz, np.float64).reshape(-1, 3)
    for deg in (min(2 * cfg.horizontal_deg, 60.0), cfg.horizontal_deg):  # cameras pitched down tilt
        horiz = np.abs(n @ up) > np.cos(np.radians(deg))  # their mean up: snap it to the horizontal
        if horiz.sum() < cfg.min_floor_points:  # cues' mean normal, first in a wider cone
            return None, f"{int(horiz.sum())} horizontal plane cues (fewer than {cfg.min_floor_points})"
        up = (n[horiz] * np.sign(n[horiz] @ up)[:, None]).mean(axis=0)
        up /= np.linalg.norm(up)
    horiz = np.abs(n @ up) > np.cos(np.radians(cfg.horizontal_deg))
    lowest_camera = min(float(np.asarray(c.center) @ up) for c in cameras)
    pts = x[horiz][x[horiz] @ up < lowest_camera]
    if len(pts) < cfg.min_floor_points:
        return None, f"{len(pts)} horizontal plane cues below the cameras (fewer than {cfg.min_floor_points})"
    h0 = _lowest_layer(pts @ up, cfg.min_floor_points)
    if h0 is None:
        return None, f"no height holds {cfg.min_floor_points} of the {len(pts)} horizontal plane cues below the cameras"
    floor, near = _fit_layer(pts, up, h0)
    if near.sum() < cfg.min_floor_points:
        return None, f"{int(near.sum())} plane cues on the lowest horizontal surface (fewer than {cfg.min_floor_points})"
    if support is not None and len(support):
        s = np.asarray(support, np.float64).reshape(-1, 3)
        s = s[(s @ up < lowest_camera) & (s @ up > floor.height - MAX_DROP)]
        if (under := _under(floor, s, pts[near], cfg.min_floor_points)) is not None:
            n_top = floor.normal  # the lowest horizontal plane cues' fitted plane: the floor is parallel to it
            h0 = _lowest_layer(s[s @ n_top - floor.height < -BELOW_MARGIN] @ n_top, cfg.min_floor_points)
            both = np.r_[pts, s]
            lower, near = _fit_layer(both, n_top, h0, level=True) if h0 is not None else (None, None)
            if lower is None or near.sum() < cfg.min_floor_points \
                    or _under(lower, s, both[near], cfg.min_floor_points) is not None:
                return None, (f"{under} of the {len(s)} SfM points and line samples below the cameras lie under the "
                              f"lowest horizontal plane cues ({lowest_camera - floor.height:.2f} m below the lowest "
                              "camera: a table?) and no layer of them is a floor")
            return lower, ""  # its tilt is the plane cues' above it: a strip of it is no matter
    across = strip_width(floor)
    if across < MIN_ACROSS_STD:
        return None, (f"the floor's {floor.n_points} cues lie in a strip {across * 12 ** 0.5:.2f} m wide (std "
                      f"{across:.3f} m < {MIN_ACROSS_STD}): nothing fixes its tilt across it")
    return floor, ""


def snap_to_lines(floor: Floor, segments: np.ndarray, band: float = 0.03, min_length: float = 0.3,
                  max_tilt_deg: float = 2.0, min_spread: float = 0.3) -> tuple[Floor, int]:
    """The floor refitted through the 3D line cues ``segments`` [L, 2, 3] lying on it: of the lines
    at least ``min_length`` long with both ends within ``band`` of it, the largest set within a third
    of the band of one plane (tried through each line, tilted from the floor's normal just enough to
    hold it, and through each pair; a skirting board's top is not the floor), then a plane through
    their end points where they span the floor in two directions (``min_spread`` across their main
    direction, or as far as the floor's plane cues spread that way, :func:`_min_spread`), else the
    floor's normal at their ends' median height. Unchanged when no line lies on
    it, or when the fit tilts more than ``max_tilt_deg`` or moves more than ``band``. Returns (floor,
    lines used)."""
    seg = np.asarray(segments, np.float64).reshape(-1, 2, 3)
    on = (np.abs(seg @ floor.normal - floor.height) < band).all(axis=1) \
        & (np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) >= min_length)
    seg = seg[on]
    if not len(seg):
        return floor, 0
    hyps = []  # (normal, height) through each line, and each pair of lines
    for i, (p, q) in enumerate(seg):
        d = (q - p) / np.linalg.norm(q - p)
        n = floor.normal - (floor.normal @ d) * d
        hyps.append((n / np.linalg.norm(n), float(n @ (p + q) / (2 * np.linalg.norm(n)))))
        for j in range(i + 1, len(seg)):
            hyps.append(_plane_through(np.r_[seg[i], seg[j]], floor.normal))
    cos_tilt = np.cos(np.radians(max_tilt_deg))
    best = max(((np.abs(seg @ n - h) < band / 3).all(axis=1) for n, h in hyps
                if n is not None and n @ floor.normal >= cos_tilt), key=np.sum, default=None)
    if best is None:
        return floor, 0
    pts = seg[best].reshape(-1, 3)
    normal, height = _plane_through(pts, floor.normal, min_spread=_min_spread(pts, floor, min_spread))
    if normal is None:  # one direction only: the floor's normal at their height
        normal, height = floor.normal, float(np.median(pts @ floor.normal))
    if np.degrees(np.arccos(min(1.0, float(normal @ floor.normal)))) > max_tilt_deg \
            or abs(height - floor.height) > band:
        return floor, 0
    return Floor(normal, height, floor.n_points, floor.cue_cov), int(best.sum())


def _min_spread(pts: np.ndarray, floor: Floor, min_spread: float, least: float = 0.1) -> float:
    """How far the floor lines' end points ``pts`` [N, 3] must spread across their main direction for a
    plane through them to replace the floor's tilt: ``min_spread``, or less where the plane cues the
    floor was fitted to (``floor.cue_cov``) spread no farther that way -- never below ``least``. The
    plane cues' tilt then comes from as short a lever arm, through the aligned priors' warp (a
    24-view benchmark room's floor cues lay in a strip 1 m wide along one wall, 2 cm higher at its far
    side: the floor came tilted 0.82 deg, 4 cm high at the far wall), while the lines are good to a few
    millimetres (the plane through its eight floor lines, 0.24 m spread, was tilted 0.085 deg)."""
    if floor.cue_cov is None or len(pts) < 2:
        return min_spread
    _, _, vt = np.linalg.svd(pts - pts.mean(axis=0))
    across = vt[1] - (vt[1] @ floor.normal) * floor.normal
    if np.linalg.norm(across) < 1e-9:
        return min_spread
    across /= np.linalg.norm(across)
    return float(np.clip(np.sqrt(max(float(across @ floor.cue_cov @ across), 0.0)), least, min_spread))


def strip_width(floor: Floor) -> float | None:
    """The smaller in-plane standard deviation of the plane cues the floor was fitted to (metres)."""
    if floor.cue_cov is None:
        return None
    b = floor.basis()
    return float(np.sqrt(max(np.linalg.eigvalsh(b @ floor.cue_cov @ b.T)[0], 0.0)))


def _turn_deg(a: Floor, b: Floor) -> float:
    return float(np.degrees(np.arccos(min(1.0, float(a.normal @ b.normal)))))


def snap_iterated(floor: Floor, segments: np.ndarray, rounds: int = 3, max_tilt_deg: float = 2.0,
                  min_turn_deg: float = 0.3) -> tuple[Floor, int]:
    """:func:`snap_to_lines` again from its own result while the last round turned the floor by more
    than ``min_turn_deg`` and the next holds more lines: a floor that its plane cues tilted leaves its
    far lines outside the first round's band (a benchmark room's bare floor came tilted 1.15°: one
    round left 0.235°, which put a wall 5 m away 4 cm in front of itself). A round that turns it by
    less already had its band (3 cm, about 0.34° at 5 m) where the lines are. Never tilted more than
    ``max_tilt_deg`` from ``floor``. Returns (floor, lines used)."""
    best, n = snap_to_lines(floor, segments, max_tilt_deg=max_tilt_deg)
    prev = floor
    for _ in range(rounds - 1):
        if _turn_deg(best, prev) <= min_turn_deg:
            break
        nxt, m = snap_to_lines(best, segments, max_tilt_deg=max_tilt_deg)
        if m <= n or _turn_deg(nxt, floor) > max_tilt_deg:
            break
        prev, best, n = best, nxt, m
    return best, n


def _plane_through(pts: np.ndarray, up: np.ndarray, min_spread: float = 0.0) -> tuple[np.ndarray | None, float]:
    """(normal on ``up``'s side, height) of the least-squares plane through ``pts`` [N, 3]; (None, 0)
    when they spread less than ``min_spread`` across their main direction (or lie on one line)."""
    c = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts - c)
    if len(sv) < 2 or sv[1] / np.sqrt(len(pts)) < max(min_spread, 1e-6):
        return None, 0.0
    n = vt[2] * np.sign(vt[2] @ up)
    return n, float(n @ c)


def _level_fit(pts: np.ndarray, up: np.ndarray, cell: float = 0.25, band: float = 0.01,
               max_tilt_deg: float = 2.0) -> tuple[np.ndarray, float]:
    """(normal, height) of the plane through floor points ``pts`` [N, 3]: the median height of each
    ``cell``-wide square (things lying on the floor, or a prior's local bump, are not the floor but
    pull a least-squares fit: 0.7 degrees on a benchmark room), then a plane through the cell
    medians, refitted without cells more than ``band`` from it; level (normal ``up``) with fewer
    than three cells or where that plane tilts more than ``max_tilt_deg`` from ``up`` (the floor
    line snap turns a floor no farther either; cells in one row gave 15 degrees on a benchmark room)."""
    floor = Floor(up, 0.0, 0)
    uv, h = pts @ floor.basis().T, pts @ up
    key = np.floor(uv / cell).astype(np.int64)
    _, cell_of, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    cell_of = cell_of.reshape(-1)
    cells = np.flatnonzero(count >= 5)
    if len(cells) < 3:
        return up, float(np.median(h))
    med = np.array([np.median(h[cell_of == c]) for c in cells])
    cuv = np.array([np.median(uv[cell_of == c], axis=0) for c in cells])
    keep = np.ones(len(cells), bool)
    for _ in range(3):
        A = np.c_[cuv[keep], np.ones(keep.sum())]
        coef = np.linalg.lstsq(A, med[keep], rcond=None)[0]
        res = np.abs(np.c_[cuv, np.ones(len(cells))] @ coef - med)
        if (res < band).sum() < 3:
            break
        keep = res < band
    e = floor.basis()
    n = up - coef[0] * e[0] - coef[1] * e[1]  # h = a u + b v + c  <=>  (up - a e1 - b e2) . X = c
    norm = float(np.linalg.norm(n))
    if n @ up / norm < np.cos(np.radians(max_tilt_deg)):  # cells in a row: their tilt across is anything
        return up, float(np.median(h))
    return n / norm, float(coef[2] / norm)
