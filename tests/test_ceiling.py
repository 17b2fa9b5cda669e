"""The ceiling as a level plane (geocues.ceiling, `geocues extract --floor.ceiling`): its height from the
views' aligned priors, the anchor grid over the walls' footprint, and the plane check it enables."""

from __future__ import annotations

import numpy as np
import pytest

from geocues.ceiling import ceiling_anchors, ceiling_edges, ceiling_height, view_ceiling_height
from geocues.floor import Floor
from geocues.floor_lines import FloorLineConfig

from test_floor_lines import H, W, camera

LO, HI = np.array([0.0, 0.0, 0.0]), np.array([4.0, 3.6, 2.5])  # the room box; floor z = 0, ceiling z = 2.5
UP = np.array([0.0, 0.0, 1.0])


def box_depth(cam, step: int = 4) -> np.ndarray:
    """z-depth of the room box's inside at every ``step``-th pixel of ``cam`` (inside the box)."""
    rows, cols = np.mgrid[0:cam.height:step, 0:cam.width:step]
    d = cam.rays_at(rows, cols) @ np.asarray(cam.R)  # world directions, camera z = 1
    C = cam.center
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (HI - C) / d, np.where(d < 0, (LO - C) / d, np.inf)).min(-1)
    return t.astype(np.float64)


def upward_views(n: int = 5):
    """Views 1.5 m up in the room, looking 15 degrees up towards its walls in every direction."""
    out = []
    for k, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False)):
        c = np.array([2.0, 1.8, 1.5]) + 0.4 * np.array([np.cos(a), np.sin(a), 0.0])
        out.append(camera(k, c, c + np.array([np.cos(a), np.sin(a), np.tan(np.radians(15))])))
    return out


def test_one_view_reads_the_ceiling_height_from_an_exact_prior():
    cam = upward_views(1)[0]
    h = view_ceiling_height(cam, box_depth(cam), UP, 0.0, above=2.0)
    assert h == pytest.approx(2.5, abs=1e-6)


def test_walls_above_the_cameras_are_not_the_ceiling_and_a_view_looking_down_sees_none():
    cam = upward_views(1)[0]
    depth = box_depth(cam)
    X = cam.center + (cam.rays_at(*np.mgrid[0:H:4, 0:W:4]) @ np.asarray(cam.R)) * depth[..., None]
    walls_only = np.where(X[..., 2] < 2.5 - 1e-6, depth, np.nan)  # the ceiling's pixels have no prior
    assert view_ceiling_height(cam, walls_only, UP, 0.0, above=1.8) is None
    down = camera(0, (2.0, 1.8, 1.5), (3.5, 1.8, 0.5))
    assert view_ceiling_height(down, box_depth(down), UP, 0.0, above=1.8) is None


def test_height_is_the_median_of_the_views_and_one_warped_view_does_not_move_it():
    cams = upward_views(5)
    scale = [1.0, 1.01, 0.99, 1.0, 1.25]  # the last prior 25 % too far: its ceiling 25 % too high
    priors = {c.index: box_depth(c) * s for c, s in zip(cams, scale)}
    h, stats = ceiling_height(cams, priors, UP, 0.0, margin=0.3, min_views=3)
    assert stats["views"] == 5
    assert h == pytest.approx(2.5, abs=0.02)  # the median of 2.5, 2.51, 2.49, 2.5 and ~2.75
    per_view = [view_ceiling_height(c, priors[c.index], UP, 0.0, above=1.8) for c in cams]
    assert abs(np.mean(per_view) - 2.5) > 0.04  # a mean would have followed it


def test_too_few_views_place_no_ceiling_and_say_why():
    cams = upward_views(2)
    h, stats = ceiling_height(cams, {c.index: box_depth(c) for c in cams}, UP, 0.0, margin=0.3, min_views=3)
    assert h is None and "2 views" in stats["note"]


def test_grid_covers_the_walls_footprint_at_the_ceiling():
    feet = np.array([[0, 0, 0], [4, 0, 0], [4, 3.6, 0], [0, 3.6, 0], [2, 0, 0], [4, 1.8, 0]], float)
    basis = Floor(UP, 0.0, 0).basis()
    pts, row = ceiling_anchors(feet, UP, basis, 0.0, 2.5, 0.1)
    assert len(pts) == pytest.approx(40 * 36, rel=0.05)
    assert np.allclose(pts[:, 2], 2.5)
    assert (pts[:, :2] > -1e-9).all() and (pts[:, 0] < 4.0).all() and (pts[:, 1] < 3.6).all()
    for r in np.unique(row):  # each row is a straight piece along basis[0], of at most 5 points
        q = pts[row == r] @ basis.T
        assert np.ptp(q[:, 1]) < 1e-9 and np.ptp(q[:, 0]) < 0.4 + 1e-9 and len(q) <= 5
    empty, _ = ceiling_anchors(feet[:2], UP, basis, 0.0, 2.5, 0.1)  # feet on one line: no footprint
    assert len(empty) == 0


def test_edges_are_the_walls_tops_and_cut_a_region_holding_a_wall_and_the_ceiling_strip():
    """The hull's edges at the ceiling are the four wall tops; a view's one weak region over the far
    wall and the strip of ceiling above it (about 10 % of it: below the plane stage's 20 % per plane) is
    cut in two along them."""
    from geocues.plane_regions import split_regions_by_lines

    feet = np.array([[0, 0, 0], [4, 0, 0], [4, 3.6, 0], [0, 3.6, 0], [2, 0, 0], [4, 1.8, 0]], float)
    edges = ceiling_edges(feet, UP, Floor(UP, 0.0, 0).basis(), 0.0, 2.5)
    assert edges.shape == (4, 2, 3) and np.allclose(edges[..., 2], 2.5)
    lengths = sorted(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1))
    assert np.allclose(lengths, [3.6, 3.6, 4.0, 4.0])
    cam = camera(0, (1.0, 1.8, 1.5), (4.0, 1.8, 1.4))
    rows, cols = np.mgrid[0:H, 0:W]
    X = cam.center + (cam.rays_at(rows, cols) @ np.asarray(cam.R)) * box_depth(cam, step=1)[..., None]
    ceiling = X[..., 2] > 2.5 - 1e-6
    region = np.where((X[..., 0] > 4.0 - 1e-6) | ceiling, 0, -1).astype(np.int32)  # far wall + ceiling
    assert 0.05 < ceiling[region == 0].mean() < 0.2
    cut = split_regions_by_lines(cam, region, edges, 3.0, 100)
    ids = [np.bincount(cut[m & (cut >= 0)]).argmax() for m in (ceiling & (region == 0), ~ceiling & (region == 0))]
    assert ids[0] != ids[1]
    assert (cut[ceiling & (cut >= 0)] == ids[0]).mean() > 0.99


def test_ceiling_needs_the_wall_check():
    with pytest.raises(ValueError, match="--floor.ceiling"):
        FloorLineConfig(lines=True, walls=True, ceiling=True).validate()
    FloorLineConfig(lines=True, walls=True, wall_check=True, ceiling=True).validate()


def test_the_grid_places_a_ceiling_no_cue_reaches():
    """A view of the bare ceiling whose aligned prior is tilted (5 % too near at the top, 5 % too far
    at the bottom) and whose only anchors are the walls' tops: the region's plane is not confirmed
    (or only near the walls); with the grid at the estimated height the whole ceiling is cut onto
    it to a millimetre."""
    from geocues.planes import PlaneConfig, plane_cues_with_prior

    cam = camera(0, (2.0, 1.8, 1.5), (3.0, 1.8, 2.3))
    rows, cols = np.mgrid[0:H, 0:W]
    depth = box_depth(cam, step=1)
    X = cam.center + (cam.rays_at(rows, cols) @ np.asarray(cam.R)) * depth[..., None]
    ceil = X[..., 2] > 2.5 - 1e-6
    prior = np.where(ceil, depth * (1 + 0.1 * (rows / H - 0.5)), 0.0).astype(np.float32)
    regions = np.where(ceil, 0, -1).astype(np.int32)
    image = np.full((H, W, 3), 0.9, np.float32)
    tops = np.c_[np.full(41, 4.0), np.linspace(0.0, 3.6, 41), np.full(41, 2.5)]  # the far wall's top edge
    cfg = PlaneConfig()
    alone = plane_cues_with_prior(cam, image, regions, prior, tops, cfg, anchors_group=np.zeros(41, np.int64))
    grid, row = ceiling_anchors(np.array([[0, 0, 0], [4, 0, 0], [4, 3.6, 0], [0, 3.6, 0.0]]), UP,
                                Floor(UP, 0.0, 0).basis(), 0.0, 2.5, 0.1)
    placed = plane_cues_with_prior(cam, image, regions, prior, np.r_[tops, grid], cfg,
                                   anchors_group=np.r_[np.zeros(41, np.int64), row + 1],
                                   whole_lines=np.r_[np.zeros(41, bool), np.ones(len(grid), bool)])
    assert len(placed.xyz) > 0
    assert np.abs(placed.xyz[:, 2] - 2.5).max() < 0.002
    assert len(placed.xyz) > 0.5 * (regions == 0)[::2, ::2].sum()  # most of the ceiling (every 2nd pixel)
    assert len(placed.xyz) > 2 * len(alone.xyz)


@pytest.mark.parametrize("fill", [0.0, np.nan, np.inf, -1.0, 1e-6])
def test_degenerate_priors_give_no_ceiling_and_no_warning(fill):
    """Priors with no usable depth (zeros, NaN, Inf, negative, a micrometre everywhere), a map
    smaller than the normals' baseline, and no feet: nothing placed, no NaN, no warning."""
    import warnings

    cams = upward_views(3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        h, stats = ceiling_height(cams, {c.index: np.full((60, 80), fill) for c in cams}, UP, 0.0,
                                  margin=0.3, min_views=1)
        assert h is None and stats["views"] == 0
        assert view_ceiling_height(cams[0], np.ones((3, 3)), UP, 0.0, above=0.0) is None
        pts, row = ceiling_anchors(np.zeros((0, 3)), UP, Floor(UP, 0.0, 0).basis(), 0.0, 2.5, 0.1)
        assert pts.shape == (0, 3) and row.shape == (0,)
        assert ceiling_edges(np.zeros((2, 3)), UP, Floor(UP, 0.0, 0).basis(), 0.0, 2.5).shape == (0, 2, 3)


def _ceiling_and_wall_pixels(cam, step: int = 4):
    """Rays [m, 3] and exact z-depth [m] of ``cam``'s ceiling pixels and of its wall pixels."""
    rows, cols = np.mgrid[0:cam.height:step, 0:cam.width:step]
    depth = box_depth(cam, step)
    rays = cam.rays_at(rows, cols)
    X = cam.center + (rays @ np.asarray(cam.R)) * depth[..., None]
    ceil = X[..., 2] > HI[2] - 1e-6
    wall = (X[..., 2] < HI[2] - 0.3) & (X[..., 2] > 0.3)
    return (rays[ceil], depth[ceil]), (rays[wall], depth[wall])


@pytest.mark.parametrize("tilt_deg", [0.0, 4.0])
def test_level_snap_cuts_a_warped_ceiling_region_onto_the_level_plane(tilt_deg):
    """`--floor.level-snap` (geocues.planes.level_plane_points): a ceiling region whose prior is 4 %
    too far and tilted lands exactly on the level plane; a wall region, or a ceiling whose prior
    puts it 40 cm too high, does not."""
    from geocues.ceiling import level_plane_points

    cam = upward_views(1)[0]
    (r_c, z_c), (r_w, z_w) = _ceiling_and_wall_pixels(cam)
    assert len(z_c) > 200 and len(z_w) > 200
    warp = 1.04 * (1 + np.tan(np.radians(tilt_deg)) * (r_c[:, 0] - r_c[:, 0].mean()) * 0.2)
    levels = np.array([[0.0, 0.0, 1.0, -0.0], [0.0, 0.0, 1.0, -HI[2]]])  # the floor first: not this region's
    got = level_plane_points(cam, r_c, z_c * warp, levels, rel=0.05)
    assert got is not None
    keep, Xc, n_c = got
    assert len(keep) >= 0.8 * len(z_c)
    Xw = (Xc - np.asarray(cam.t)) @ np.asarray(cam.R)
    np.testing.assert_allclose(Xw[:, 2], HI[2], atol=1e-9)  # on the plane ...
    np.testing.assert_allclose(Xc[:, 2], z_c[keep], rtol=1e-9)  # ... where the true ceiling is
    np.testing.assert_allclose(np.abs(np.asarray(cam.R).T @ n_c), [0, 0, 1], atol=1e-12)
    assert level_plane_points(cam, r_w, z_w, levels, rel=0.05) is None
    rise = (HI[2] + 0.4 - cam.center[2]) / (HI[2] - cam.center[2])  # every ceiling point 40 cm higher
    assert level_plane_points(cam, r_c, z_c * rise, levels, rel=0.05) is None
    assert level_plane_points(cam, r_c[:0], z_c[:0], levels, rel=0.05) is None  # no pixels


def test_wall_planes_merge_collinear_feet_and_skip_low_or_short_ones():
    """`--floor.wall-snap` (geocues.walls.wall_planes): two pieces of one wall's foot (one drawn the other
    way round, 0.5 deg apart) are one plane through both; a cabinet's foot 8 cm in front of it, raised
    only 0.8 m, and a 0.3 m stub give none; a perpendicular wall is its own plane."""
    from geocues.walls import wall_planes

    tilt = np.radians(0.5)
    raised = [
        (np.array([0.0, 3.6, 0.0]), np.array([1.5, 3.6, 0.0]), 2.4),  # the north wall, left piece
        (np.array([3.9, 3.6 + 2.0 * np.tan(tilt), 0.0]), np.array([1.9, 3.6, 0.0]), 2.5),  # right piece, reversed
        (np.array([1.0, 3.52, 0.0]), np.array([2.0, 3.52, 0.0]), 0.8),  # a cabinet's front: stops low
        (np.array([4.0, 0.2, 0.0]), np.array([4.0, 3.0, 0.0]), 2.5),  # the east wall
        (np.array([0.0, 0.5, 0.0]), np.array([0.0, 0.8, 0.0]), 2.5),  # a 0.3 m stub of the west wall
    ]
    planes = wall_planes(raised, UP, top=2.5, min_share=0.6)
    assert planes.shape == (2, 4)
    north = planes[np.argmax(np.abs(planes[:, 1]))]
    north = north * np.sign(north[1])
    np.testing.assert_allclose(north[:3], [0, 1, 0], atol=np.radians(0.3))
    for p in (np.array([0.75, 3.6, 0.0]), np.array([2.9, 3.6 + np.tan(tilt), 0.0])):  # both pieces on it
        assert abs(north[:3] @ p + north[3]) < 0.01
    east = planes[np.argmax(np.abs(planes[:, 0]))]
    assert abs(abs(east[0]) - 1) < 1e-12 and abs(east[:3] @ [4.0, 1.0, 0.0] + east[3]) < 1e-12
    assert wall_planes([], UP, 2.5, 0.6).shape == (0, 4)
    assert wall_planes(raised[2:3], UP, 2.5, 0.6).shape == (0, 4)


def test_wall_snap_cuts_the_wall_part_of_a_region_no_cue_reaches():
    """A region holding a wall and the floor below it, whose aligned prior is 4 % too far, no anchor
    near: as a level plane the wall takes nothing (neither plane of the region holds 80 % of it) and
    the anchors' check gives nothing; as a wall plane (`walls`, tested on each RANSAC plane's pixels
    the anchored planes leave) the wall's part is cut exactly onto it, and the floor's part (not a
    level plane here) stays out."""
    from geocues.planes import PlaneConfig, plane_cues_with_prior

    cam = camera(0, (2.0, 1.0, 1.2), (2.0, 3.6, 0.6))
    rows, cols = np.mgrid[0:H, 0:W]
    depth = box_depth(cam, step=1)
    X = cam.center + (cam.rays_at(rows, cols) @ np.asarray(cam.R)) * depth[..., None]
    wall = X[..., 1] > HI[1] - 1e-6
    floor = X[..., 2] < 1e-6
    assert wall.mean() > 0.3 and floor.mean() > 0.2
    region = wall | floor
    prior = np.where(region, 1.04 * depth, 0.0).astype(np.float32)
    regions = np.where(region, 0, -1).astype(np.int32)
    image = np.full((H, W, 3), 0.8, np.float32)
    cfg, none = PlaneConfig(), np.zeros((0, 3))
    north = np.array([[0.0, 1.0, 0.0, -HI[1]]])
    plain = plane_cues_with_prior(cam, image, regions, prior, none, cfg, levels=north, level_rel=0.05)
    assert len(plain.xyz) == 0  # as a level plane: the region as a whole is not on it
    snapped = plane_cues_with_prior(cam, image, regions, prior, none, cfg, walls=north, level_rel=0.05)
    assert np.isfinite(snapped.xyz).all()
    assert len(snapped.xyz) > 0.8 * wall[::2, ::2].sum()
    np.testing.assert_allclose(snapped.xyz[:, 1], HI[1], atol=1e-6)


def test_wall_planes_refit_to_the_wall_cues_and_dropped_without_them():
    """A foot-lifted wall plane 5 cm in front of the wall and turned 1.5 deg is moved onto the wall's
    plane cues (2 mm noise; the perpendicular wall's and a cabinet 12 cm in front are not used); a
    second foot of the same wall lands on it and is not repeated; a plane no cue lies on is dropped."""
    from geocues.walls import refit_wall_planes

    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(0, 4, 3000), 3.6 + rng.normal(0, 0.002, 3000), rng.uniform(0, 2.5, 3000)]
    side = np.c_[4.0 + rng.normal(0, 0.002, 2000), rng.uniform(0, 3.6, 2000), rng.uniform(0, 2.5, 2000)]
    cabinet = np.c_[rng.uniform(1, 2, 500), np.full(500, 3.48), rng.uniform(0, 0.8, 500)]
    xyz = np.r_[wall, side, cabinet]
    normal = np.r_[np.tile([0, -1.0, 0], (3000, 1)), np.tile([1.0, 0, 0], (2000, 1)), np.tile([0, 1.0, 0], (500, 1))]
    a = np.radians(1.5)
    n = np.array([np.sin(a), np.cos(a), 0.0])
    foot = np.r_[n, -(n @ [2.0, 3.55, 0.0])]
    nowhere = np.array([0.0, 1.0, 0.0, -1.5])
    other_piece = -np.r_[n, -(n @ [2.0, 3.57, 0.0])]  # a second foot of that wall, normal the other way
    got = refit_wall_planes(np.array([foot, nowhere, other_piece]), xyz, normal, UP)
    assert got.shape == (1, 4)
    assert abs(got[0, 1]) > np.cos(np.radians(0.1)) and abs(got[0, 2]) < 1e-12
    assert np.abs(wall @ got[0, :3] + got[0, 3]).max() < 0.01
    assert abs(np.array([2.0, 3.6, 1.0]) @ got[0, :3] + got[0, 3]) < 0.002
    assert refit_wall_planes(np.zeros((0, 4)), xyz, normal, UP).shape == (0, 4)


def test_wall_snap_is_vetoed_by_cues_that_put_the_wall_elsewhere():
    """A wall region whose prior lies within level_rel of a wall plane 5 cm in front of the true wall
    and a cue line across it: the anchored plane takes the pixels near the line; the rest, on the
    line's wall, is not cut onto the assumed plane 5 cm off it (the line, 5 samples or more in the
    plane's band, vetoes); with the line on the assumed plane the cut stands and takes more."""
    from geocues.planes import PlaneConfig, plane_cues_with_prior

    cam = camera(0, (2.0, 1.0, 1.2), (2.0, 3.6, 0.6))
    rows, cols = np.mgrid[0:H, 0:W]
    depth = box_depth(cam, step=1)
    X = cam.center + (cam.rays_at(rows, cols) @ np.asarray(cam.R)) * depth[..., None]
    wall = X[..., 1] > HI[1] - 1e-6
    prior = np.where(wall, depth, 0.0).astype(np.float32)  # within level_rel of both planes
    regions = np.where(wall, 0, -1).astype(np.int32)
    image = np.full((H, W, 3), 0.8, np.float32)
    cfg = PlaneConfig()
    off = np.array([[0.0, 1.0, 0.0, -(HI[1] - 0.05)]])  # assumed 5 cm in front
    counts = []
    for y, snapped in ((HI[1], False), (HI[1] - 0.05, True)):
        line = np.c_[np.linspace(1.5, 2.5, 41), np.full(41, y), np.full(41, 1.0)]  # a horizontal cue line
        out = plane_cues_with_prior(cam, image, regions, prior, line, cfg, anchors_group=np.zeros(41, np.int64),
                                    walls=off, level_rel=0.05)
        assert len(out.xyz) > 0 and np.isfinite(out.xyz).all()
        assert ("wall_snap_contradicted" in out.rejected) != snapped, out.rejected
        assert ("on_a_wall_plane" in out.rejected) == snapped, out.rejected
        np.testing.assert_allclose(out.xyz[:, 1], y, atol=0.01)
        counts.append(len(out.xyz))
    assert counts[1] > 2 * counts[0]  # the cut takes the wall beyond the line's hull
    line = np.c_[np.linspace(1.5, 2.5, 41), np.full(41, HI[1]), np.full(41, 1.0)]
    foot = plane_cues_with_prior(cam, image, regions, prior, line, cfg, anchors_group=np.zeros(41, np.int64),
                                 walls=off, level_rel=0.05, wall_veto=np.zeros(41, bool))
    assert "on_a_wall_plane" in foot.rejected  # an anchor that is no measured cue (a lifted foot) vetoes nothing
