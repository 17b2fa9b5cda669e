"""Walls raised from their floor-contact lines (an extension; `geocues extract --floor.walls`).

``walls`` (:func:`wall_anchors`) raises every kept floor segment (geocues.floor_lines) straight up
into rows of anchors for the plane checks of the second plane pass (not for the prior alignment): a
foot line alone leaves a wall's plane free to turn about it, so only a band above the foot was cut;
with the vertical-wall assumption the foot places the whole wall. Rows that stand in free space (a
floor texture line's) agree with no region's prior plane and are not used; rows behind a view's
aligned surface are left out of its checks.

``wall_check`` asks the aligned depth priors of the views that lifted a segment whether its rows lie
on a surface (:func:`row_evidence`, :func:`confirmed_rows`): rows stop below two contradicted rows,
and a segment with no confirmed row from :data:`WALL_CHECK_MIN` up is not raised. ``wall_front_gap``
also leaves out a segment just in front of a parallel raised one (:func:`in_front_of_walls`): a floor
line near a wall, closer than the priors' tolerance tells apart.

``wall_snap`` makes the raised walls planes (:func:`wall_planes`, :func:`refit_wall_planes`) and cuts
onto them what the anchored plane cues of a region leave (:func:`wall_snap_points`), unless the
measured anchors put the wall elsewhere (:func:`cues_contradict`).
"""

from __future__ import annotations

import logging

import numpy as np

from geocues.ceiling import level_plane_points
from geocues.floor_lines import FloorLineConfig, sample_nearest
from geocues.plane_fit import weighted_median

log = logging.getLogger(__name__)

WALL_CHECK_MIN = 0.3  # metres above the floor: lower rows of a raised floor-texture line lie so close to
# the floor the views see behind them that a loose tolerance cannot tell them from a wall


def row_evidence(cameras, views: np.ndarray, priors: dict[int, np.ndarray], pts: np.ndarray, rel: float) -> int:
    """+1 when the aligned priors of ``views`` agree (within ``rel`` of the depth) with the points ``pts``
    [n, 3] of one raised row at half or more of the >= 3 pixels where they have depth, -1 when they
    do not, 0 without such evidence (fewer than 3 pixels with prior depth)."""
    n_valid = n_agree = 0
    for v in views:
        prior = priors.get(int(v))
        if prior is None:
            continue
        cam = cameras[int(v)]
        uv, z = cam.project(pts)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if not ok.any():
            continue
        p = sample_nearest(prior, cam, uv[ok])
        has = (p > 0) & np.isfinite(p)
        n_valid += int(has.sum())
        n_agree += int((has & (np.abs(p - z[ok]) <= rel * z[ok])).sum())
    if n_valid < 3:
        return 0
    return 1 if 2 * n_agree >= n_valid else -1


def confirmed_rows(evidence: np.ndarray, heights: np.ndarray) -> int:
    """How many of a segment's rows (bottom up, ``evidence`` [H] of :func:`row_evidence` at
    ``heights`` [H]) to raise: those below the first two contradicted rows in a row, and none when
    no row from :data:`WALL_CHECK_MIN` up among them is confirmed while one there has evidence, or
    when they all lie below it (all rows when no row has evidence: the assumption unchecked)."""
    n = len(heights)
    for i in range(len(evidence) - 1):
        if evidence[i] < 0 and evidence[i + 1] < 0:
            n = i
            break
    high = evidence[:n][heights[:n] >= WALL_CHECK_MIN - 1e-9]
    if not evidence.any():
        return n
    if not len(high) or (high.any() and not (high > 0).any()):
        return 0
    return n


SAME_LINE = 0.05  # metres: raised segments closer than this across are one line lifted twice (no front / back)


def in_front_of_walls(feet: list[tuple[np.ndarray, np.ndarray]], raised: np.ndarray, up: np.ndarray,
                      centre: np.ndarray, gap: float, max_angle_deg: float = 5.0) -> np.ndarray:
    """[S] bool: segments (``feet``: end points on the floor; ``raised``: rows raised) that lie less
    than ``gap`` (and :data:`SAME_LINE` or more) in front of another raised segment, seen from
    ``centre``: parallel within ``max_angle_deg``, overlapping half the segment's length, raised at
    least as high."""
    out = np.zeros(len(feet), bool)
    flat = [(p - (p @ up) * up, q - (q @ up) * up) for p, q in feet]
    c = centre - (centre @ up) * up
    cos_max = np.cos(np.radians(max_angle_deg))
    for a, (p, q) in enumerate(flat):
        if raised[a] == 0:
            continue
        da = q - p
        la = np.linalg.norm(da)
        if la < 1e-9:
            continue
        da = da / la
        na = np.cross(up, da)  # in-floor normal of a's line
        side_c = (c - p) @ na
        for b, (r, s) in enumerate(flat):
            if b == a or raised[b] < raised[a]:
                continue
            db = s - r
            lb = np.linalg.norm(db)
            if lb < 1e-9 or abs(db @ da) / lb < cos_max:
                continue
            off = 0.5 * ((r - p) + (s - p)) @ na  # b's offset from a's line, across it
            if not (SAME_LINE <= abs(off) < gap) or np.sign(off) == np.sign(side_c):
                continue  # the same line lifted twice, b not within gap, or b on the cameras' side of a
            t = sorted([(r - p) @ da, (s - p) @ da])
            if min(t[1], la) - max(t[0], 0.0) >= 0.5 * la:
                out[a] = True
                break
    return out


def wall_anchors(points: np.ndarray, line: np.ndarray, floor_normal: np.ndarray, floor_height: float,
                 plane_xyz: np.ndarray, cameras, cfg: FloorLineConfig, views: list[np.ndarray] | None = None,
                 priors: dict[int, np.ndarray] | None = None, report: dict | None = None,
                 raised_out: list | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """The vertical-wall assumption (``--floor.walls``): each kept floor segment (its anchor samples
    ``points`` [P, 3], kept-segment index ``line`` [P]) raised every ``cfg.wall_step`` up to the wall
    top. Returns (points [Q, 3], row index [Q]: one horizontal row per segment and height, the
    height they reach above the floor). The top is ``cfg.wall_height``, or with 0 the higher of the
    99th percentile of ``plane_xyz``'s heights and the highest camera + 1 m. With ``cfg.wall_check``,
    ``views`` (per kept segment, the views that lifted it) and ``priors`` (image index -> aligned prior
    depth, any resolution), each segment is raised only as far as :func:`confirmed_rows` allows;
    ``report`` then receives the counts of segments dropped, cut short and raised unchecked.
    ``raised_out`` receives (foot start [3], foot end [3], height reached in metres) per raised segment."""
    up = np.asarray(floor_normal, np.float64)
    top = cfg.wall_height
    if top <= 0:
        h = np.asarray(plane_xyz, np.float64).reshape(-1, 3) @ up - floor_height
        cam_top = max(float(np.asarray(c.center) @ up) for c in cameras) - floor_height + 1.0
        top = max(float(np.percentile(h, 99)) if len(h) else 0.0, cam_top)
    heights = np.arange(cfg.wall_step, top + 1e-9, cfg.wall_step)  # [H]
    check = cfg.wall_check and views is not None and bool(priors)
    if cfg.wall_check and not check and len(line):
        log.warning("--floor.wall-check: no aligned depth priors to check the walls with (the scene has none, or "
                    "none could be aligned): every floor segment raised unchecked to %.2f m, floor texture lines "
                    "and furniture feet included", top)
    counts = {"dropped": 0, "cut": 0, "unchecked": 0}
    feet, grids, raised = [], [], []
    for k in np.unique(line):
        seg = points[line == k]
        p, q = seg[0], seg[-1]
        n = max(int(round(np.linalg.norm(q - p) / cfg.wall_step)) + 1, 2)
        along = p + np.linspace(0.0, 1.0, n)[:, None] * (q - p)  # [n, 3]
        grids.append(along[None] + heights[:, None, None] * up)  # [H, n, 3]
        feet.append((p, q))
        h = len(heights)
        if check:
            evidence = np.array([row_evidence(cameras, views[int(k)], priors, g, cfg.wall_check_rel)
                                 for g in grids[-1]])
            h = confirmed_rows(evidence, heights)
            counts["unchecked"] += int(not evidence.any())
            counts["dropped"] += int(h == 0)
            counts["cut"] += int(0 < h < len(heights))
        raised.append(h)
    if check and cfg.wall_front_gap > 0:
        centre = np.mean([np.asarray(c.center) for c in cameras], axis=0)
        behind = in_front_of_walls(feet, np.array(raised), up, centre, cfg.wall_front_gap)
        counts["in_front"] = int((behind & (np.array(raised) > 0)).sum())
        raised = [0 if b else h for b, h in zip(behind, raised)]
    pts, row = [], []
    n_rows = 0
    for grid, h, (p, q) in zip(grids, raised, feet):
        if h == 0:
            continue
        if raised_out is not None:
            raised_out.append((p, q, float(heights[h - 1])))
        pts.append(grid[:h].reshape(-1, 3))  # [h * n, 3]
        row.append(np.repeat(n_rows + np.arange(h), grid.shape[1]))
        n_rows += h
    if check and report is not None:
        report.update(counts)
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64), float(top)
    return np.concatenate(pts), np.concatenate(row), float(top)


def wall_planes(raised: list, up: np.ndarray, top: float, min_share: float, angle_deg: float = 3.0,
                dist: float = 0.03, min_length: float = 0.5) -> np.ndarray:
    """The vertical planes of the raised walls (``--floor.wall-snap``): [K, 4] world planes n . X + d = 0.

    ``raised``: (foot start, foot end, height reached) per raised segment (:func:`wall_anchors`);
    only segments reaching ``min_share`` x ``top`` count (a cabinet's foot stops lower). Segments
    whose vertical planes agree -- normals within ``angle_deg``, each one's foot midpoint within
    ``dist`` of the other's plane -- are one wall, longest first; its plane is the length-weighted
    mean, and a wall shorter than ``min_length`` in all is dropped."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    segs = []
    for p, q, h in raised:
        p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
        length = float(np.linalg.norm(q - p))
        if h < min_share * top or length < 1e-6:
            continue
        n = np.cross(up, (q - p) / length)
        n /= np.linalg.norm(n)
        segs.append((length, n, 0.5 * (p + q)))
    segs.sort(key=lambda s: -s[0])
    cos_max = np.cos(np.radians(angle_deg))
    walls: list[list] = []  # per wall, its members (length, normal, foot midpoint); the first is the longest
    for length, n, mid in segs:
        for w in walls:
            n0, m0 = w[0][1], w[0][2]
            s = 1.0 if n @ n0 >= 0 else -1.0
            if s * (n @ n0) >= cos_max and abs((mid - m0) @ n0) <= dist and abs((m0 - mid) @ n) <= dist:
                w.append((length, s * n, mid))
                break
        else:
            walls.append([(length, n, mid)])
    out = []
    for w in walls:
        lengths = np.array([m[0] for m in w])
        if lengths.sum() < min_length:
            continue
        n = (lengths[:, None] * np.array([m[1] for m in w])).sum(axis=0)
        n /= np.linalg.norm(n)
        d = -float(lengths @ (np.array([m[2] for m in w]) @ n)) / lengths.sum()
        out.append(np.r_[n, d])
    return np.array(out).reshape(-1, 4)


def refit_wall_planes(planes: np.ndarray, xyz: np.ndarray, normal: np.ndarray, up: np.ndarray,
                      dist: float = 0.1, angle_deg: float = 10.0, min_points: int = 200,
                      inlier: float = 0.02) -> np.ndarray:
    """Each wall plane [K, 4] refitted to the plane cues ``xyz`` [P, 3] (normals [P, 3]) that lie on it:
    a foot lifted onto the floor is a few centimetres off, its plane as much (measured: 4-7 cm on a
    benchmark room's walls), while the walls' plane cues are within millimetres. Points within
    ``dist`` of a plane whose normal is within ``angle_deg`` of it are fitted (least squares, kept
    vertical: the normal in the floor's plane), then again with those within ``inlier`` of that fit;
    a plane with fewer than ``min_points`` such points (no cue confirms it) is dropped, and so is one
    that lands on a plane already refitted."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    xyz, normal = np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(normal, np.float64).reshape(-1, 3)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(up, e1)])  # [2, 3] the floor's plane
    out = []
    for plane in np.asarray(planes, np.float64).reshape(-1, 4):
        n, d = plane[:3], plane[3]
        sel = (np.abs(xyz @ n + d) <= dist) & (np.abs(normal @ n) >= np.cos(np.radians(angle_deg)))
        for _ in range(2):
            if sel.sum() < min_points:
                break
            P = xyz[sel]
            c = P.mean(axis=0)
            Q = (P - c) @ basis.T  # [p, 2] in the floor's plane: a vertical plane is a line there
            _, _, vt = np.linalg.svd(Q, full_matrices=False)
            m = vt[-1] @ basis  # the direction of least spread is the normal
            n = m / np.linalg.norm(m) * (1.0 if m @ plane[:3] >= 0 else -1.0)
            d = -float(c @ n)
            sel = (np.abs(xyz @ n + d) <= inlier) & (np.abs(normal @ n) >= np.cos(np.radians(angle_deg)))
        else:
            same = [o for o in out if abs(o[:3] @ n) >= np.cos(np.radians(1.0))
                    and abs(o[3] * np.sign(o[:3] @ n) - d) <= inlier / 2]  # two feet refitted onto one wall
            if sel.sum() >= min_points and not same:
                out.append(np.r_[n, d])
    return np.array(out).reshape(-1, 4)


def wall_snap_points(cam, rays: np.ndarray, z: np.ndarray, sel: np.ndarray, ransac_sets: list, found: list,
                     walls: np.ndarray, rel: float, a_c: np.ndarray, a_w: np.ndarray, min_points: int,
                     agree_dist: float, min_anchors: int, rejected: dict[str, int]) -> list:
    """`--floor.wall-snap` in one image's region (geocues.planes.plane_cues_with_prior): per RANSAC
    plane of its prior (``ransac_sets``, indices into ``sel``), the pixels no anchored plane of
    ``found`` took -- at least ``min_points`` -- cut onto the wall plane [K, 4] their prior lies on
    (geocues.ceiling.level_plane_points, tolerance ``rel``), unless :func:`cues_contradict` says the
    measured anchors ``a_c`` (camera frame, weights ``a_w``) put the wall elsewhere. Returns entries in
    ``found``'s form; counts in ``rejected``."""
    taken = np.zeros(len(z), bool)
    for f in found:
        taken[f[0]] = True
    out = []
    for keep in ransac_sets:
        left = sel[keep][~taken[sel[keep]]]
        if len(left) < min_points:
            continue
        snapped = level_plane_points(cam, rays[left], z[left], walls, rel)
        if snapped is None:
            continue
        vetoed = cues_contradict(snapped, a_c, a_w, agree_dist, min_anchors)
        reason = "wall_snap_contradicted" if vetoed else "on_a_wall_plane"
        rejected[reason] = rejected.get(reason, 0) + 1
        if not vetoed:
            kk, X_l, n_l = snapped
            out.append((left[kk], X_l, n_l, None, a_c[:0]))
            taken[left[kk]] = True
    return out


def cues_contradict(snapped: tuple, a_c: np.ndarray, a_w: np.ndarray, agree_dist: float, min_anchors: int) -> bool:
    """Whether the measured anchors near a region (camera frame a_c [a, 3], weights a_w [a]) put the
    surface off the assumed plane ``snapped`` (level_plane_points' result) cut it onto: at least
    ``min_anchors`` of them within 2 x ``agree_dist`` of that plane and their weighted median
    distance from it ``agree_dist`` or more (a wall plane from feet and first-pass cues can be a few
    centimetres off or turned where the cues see the wall itself). The band is not the plane check's
    depth-relative one: objects before the wall stay out of it."""
    _, X, n = snapped
    d = -float(X[0] @ n)
    r = np.abs(a_c @ n + d)
    band = r < 2 * agree_dist
    return bool(band.sum() >= min_anchors and weighted_median(r[band], a_w[band]) >= agree_dist)
