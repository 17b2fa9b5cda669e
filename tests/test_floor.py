"""The floor plane (geocues.floor): found from the horizontal plane cues in any world frame (or
nothing, with a reason), levelled by the 3D line cues lying on it, also where its plane cues and
lines lie in one strip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geocues.floor import Floor, find_floor, snap_iterated, snap_to_lines, strip_width, up_direction
from geocues.floor_lines import FloorLineConfig, floor_line_anchors
from geocues.scene import Camera

from test_floor_lines import H, K, W, camera


def room_plane_cues(rng, Q: np.ndarray, n_floor: int = 1500):
    """Plane cues of a 5 x 4 x 2.6 m room in a world rotated by ``Q``: floor (z = 0), a table top
    (z = 0.75), ceiling (above the cameras) and walls, 2 mm noise."""
    parts = [(np.c_[rng.uniform(0, 5, n_floor), rng.uniform(0, 4, n_floor), np.zeros(n_floor)], [0, 0, 1]),
             (np.c_[rng.uniform(1, 2, 800), rng.uniform(1, 2, 800), np.full(800, 0.75)], [0, 0, 1]),
             (np.c_[rng.uniform(0, 5, 2000), rng.uniform(0, 4, 2000), np.full(2000, 2.6)], [0, 0, -1]),
             (np.c_[np.zeros(2000), rng.uniform(0, 4, 2000), rng.uniform(0, 2.6, 2000)], [1, 0, 0])]
    xyz = np.concatenate([p for p, _ in parts]) + rng.normal(0, 0.002, (sum(len(p) for p, _ in parts), 3))
    n = np.concatenate([np.tile(nn, (len(p), 1)) for p, nn in parts]).astype(float)
    return xyz @ Q.T, n @ Q.T


def test_floor_in_a_rotated_world():
    """The floor under a table and a ceiling, in a world frame whose up is not z; the cameras all
    look one way, 23 degrees down (their mean up vector is that far off the floor's normal)."""
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    Q = Rotation.from_euler("xyz", [70, -20, 35], degrees=True).as_matrix()
    cams = [camera(k, (x, 0.5, 1.5), (x, 4.0, 0.0), Q) for k, x in enumerate(np.linspace(1, 4, 8))]
    assert np.degrees(np.arccos(up_direction(cams) @ Q[:, 2])) > 10
    xyz, n = room_plane_cues(rng, Q, n_floor=600)  # the floor is mostly hidden: fewer cues than the table
    floor, why = find_floor(xyz, n, cams, FloorLineConfig())
    assert floor is not None, why
    assert np.degrees(np.arccos(floor.normal @ Q[:, 2])) < 0.2
    assert abs(floor.height) < 0.002


def test_no_floor_gives_nothing_and_a_reason():
    rng = np.random.default_rng(1)
    cams = [camera(k, (2.5, 2.0, 1.5), (2.5 + np.cos(a), 2 + np.sin(a), 1.0))
            for k, a in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False))]
    walls = np.c_[np.zeros(500), rng.uniform(0, 4, 500), rng.uniform(0, 2.6, 500)]
    normals = np.tile([1.0, 0, 0], (500, 1))
    P, L, V, stats = floor_line_anchors(cams, [np.zeros((0, 4))] * len(cams), walls, normals, FloorLineConfig())
    assert len(P) == len(L) == len(V) == 0 and stats["floor"] is None and "horizontal" in stats["note"]
    ceiling = np.c_[rng.uniform(0, 5, 500), rng.uniform(0, 4, 500), np.full(500, 2.6)]  # above the cameras only
    floor, why = find_floor(ceiling, np.tile([0, 0, -1.0], (500, 1)), cams, FloorLineConfig())
    assert floor is None and "below the cameras" in why
    rolled = []  # looking straight down, each rolled 90 degrees more than the last: no up direction
    for k, a in enumerate(np.arange(4) * np.pi / 2):
        down, fwd = np.array([np.cos(a), np.sin(a), 0.0]), np.array([0.0, 0.0, -1.0])
        R = np.stack([np.cross(down, fwd), down, fwd])
        rolled.append(Camera(k, k + 1, f"{k}.png", Path(f"{k}.png"), W, H, K, R, -R @ np.array([2.5, 2.0, 1.5])))
    assert up_direction(rolled) is None
    assert "up direction" in find_floor(ceiling, np.tile([0, 0, -1.0], (500, 1)), rolled, FloorLineConfig())[1]



def test_floor_snapped_to_the_3d_lines_on_it():
    """The plane cues' floor 1 cm high and tilted 0.2 degrees: two wall feet (3D line cues) on the
    true floor z = 0 put it back exactly; one foot alone fixes only the height; lines that do not lie
    on it (an edge 0.5 m up, a line on the floor shorter than 0.3 m) leave it as it was."""
    t = np.radians(0.2)
    off = Floor(np.array([np.sin(t), 0.0, np.cos(t)]), 0.01, 100)
    feet = np.array([[[0.0, 0, 0], [5, 0, 0]], [[0.0, 0, 0], [0, 4, 0]]])
    snapped, n = snap_to_lines(off, feet)
    assert n == 2 and abs(snapped.height) < 1e-9 and snapped.normal[2] > 1 - 1e-12
    one, n = snap_to_lines(off, feet[1:])  # along y: spans the floor in one direction only
    assert n == 1 and np.allclose(one.normal, off.normal) and abs(one.height) < 1e-4
    skirting = np.r_[feet, [[[0.0, 3, 0.025], [4, 3, 0.025]]]]  # 2.5 cm up: in the band, dropped on the refit
    snapped, n = snap_to_lines(off, skirting)
    assert n == 2 and abs(snapped.height) < 1e-9 and snapped.normal[2] > 1 - 1e-12
    stray = np.array([[[0.0, 1, 0.5], [4, 1, 0.5]], [[1.0, 1, 0], [1.2, 1, 0]]])
    same, n = snap_to_lines(off, stray)
    assert n == 0 and same is off
    steep = np.array([[[0.0, 0, 0.029], [1, 0, -0.029]], [[0.0, 2, 0.0], [0, 3, 0.0]]])  # 3.3 degrees
    assert snap_to_lines(Floor(np.array([0, 0, 1.0]), 0.0, 10), steep[:1])[1] == 0  # tilts too far
    assert snap_to_lines(Floor(np.array([0, 0, 1.0]), 0.0, 10), steep)[1] == 1  # the level one wins



def test_snap_iterated_levels_a_floor_its_plane_cues_tilted():
    """A level floor whose plane cues came tilted 1°: the far lines lie outside the first snap's band,
    so one round fits the near lines alone (2 mm up on one side, down on the other: it tilts); rounds
    from its own result take the far lines in and level it."""
    near = [np.array([[0.1 + 0.8 * (k % 2), 0.5 + 0.6 * k, 0.0], [0.4 + 0.8 * (k % 2), 0.5 + 0.6 * k, 0.0]])
            + [0.0, 0.0, 0.002 - 0.004 * (k % 2)] for k in range(6)]  # x 0.1-1.2 m, y 0.5-3.5 m, 2 mm off
    far = [np.array([[4.2, 0.5 + 1.2 * k, 0.0], [4.8, 0.5 + 1.2 * k, 0.0]]) for k in range(3)]  # x 4.2-4.8 m
    seg = np.array(near + far)
    t = np.radians(1.0)
    tilted = Floor(np.array([-np.sin(t), 0.0, np.cos(t)]), 0.0, 100)
    tilt = lambda f: np.degrees(np.arccos(min(1.0, f.normal[2])))  # noqa: E731
    one, n1 = snap_to_lines(tilted, seg)
    many, n = snap_iterated(tilted, seg)
    assert n1 == 6 and n == 9
    assert tilt(one) > 0.2 and tilt(many) < 0.05 and abs(many.height) < 0.002
    level = Floor(np.array([0.0, 0.0, 1.0]), 0.0, 100)  # every line in the first band: one round, the same floor
    a, b = snap_to_lines(level, seg), snap_iterated(level, seg)
    assert a[1] == b[1] == 9 and np.array_equal(a[0].normal, b[0].normal) and a[0].height == b[0].height


def test_snap_levels_a_floor_whose_plane_cues_and_lines_lie_in_one_strip():
    """A 24-view benchmark room saw its floor only in a strip 1 m wide along one wall: the plane cues
    there came tilted 0.82 deg across the strip (4 cm high at the far wall), and its eight floor lines,
    all along the strip, spread only 0.24 m across it -- under the fixed 0.3 m, so the snap kept the
    tilt and set the height only (the far walls' lifted feet stood 4-7 cm in front of them). Lines
    spread as far as the plane cues the floor came from level it; where the plane cues spread
    farther, the tilt stays theirs (one direction only, as before)."""
    ys = [0.25, 0.38, 0.52, 0.64, 0.65, 0.78, 0.90, 1.04]  # the room's floor lines, along x
    seg = np.array([[[2.2 + 0.2 * k, y, 0.0], [4.5 + 0.1 * k, y, 0.0]] for k, y in enumerate(ys)])
    seg[:, :, 2] += 0.002 * np.array([1, -1, 0, 1, -1, 0, 1, -1])[:, None]  # mm-accurate
    t = np.radians(0.82)
    normal = np.array([0.0, -np.sin(t), np.cos(t)])
    strip = np.diag([1.15, 0.20, 0.01]) ** 2  # the cues' spread: x 1.15 m, y 0.20 m (std)
    wide = np.diag([1.15, 1.0, 0.01]) ** 2
    tilt = lambda f: np.degrees(np.arccos(min(1.0, f.normal[2])))  # noqa: E731
    for floor_cov, level in ((strip, True), (wide, False), (None, False)):
        tilted = Floor(normal, float(normal @ [0.0, 0.65, 0.0]), 100, floor_cov)
        snapped, n = snap_iterated(tilted, seg)
        assert n == 8 and abs(snapped.height - (snapped.normal @ [0.0, 0.65, 0.0])) < 0.003
        if level:
            assert tilt(snapped) < 0.2 and abs((snapped.height - snapped.normal[1] * 3.6) / snapped.normal[2]) < 0.01
            assert np.array_equal(snapped.cue_cov, floor_cov)
        else:
            assert np.allclose(snapped.normal, normal)  # the plane cues' tilt, the lines' height
    one, n = snap_to_lines(Floor(normal, 0.0, 100, strip), seg[:1])  # one line: no spread, no plane
    assert n == 1 and np.allclose(one.normal, normal)


def test_strip_width_is_the_cues_smaller_in_plane_spread():
    t = np.radians(0.82)
    normal = np.array([0.0, -np.sin(t), np.cos(t)])
    strip = Floor(normal, 0.0, 100, np.diag([1.15, 0.20, 0.01]) ** 2)
    assert strip_width(strip) == pytest.approx(0.2, abs=0.01)
    assert strip_width(Floor(normal, 0.0, 100, np.diag([1.15, 1.0, 0.01]) ** 2)) > 0.9
    assert strip_width(Floor(normal, 0.0, 100)) is None


def test_a_table_top_above_a_textured_floor_is_no_floor():
    """A textured floor has SfM points, not plane cues: the lowest horizontal plane cues are a table
    top 0.75 m up (found on a held-out 24-view room: its cues went 27 cm off). The SfM points and line
    samples under it, outside its footprint, say so: the floor is their lowest layer; where they form
    no layer there is no floor; what lies under the table itself (its legs) says nothing."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    Q = Rotation.from_euler("xyz", [10, -5, 20], degrees=True).as_matrix()
    cams = [camera(k, (x, 0.5, 1.5), (x, 4.0, 0.0), Q) for k, x in enumerate(np.linspace(1, 4, 8))]
    xyz, n = room_plane_cues(rng, Q, n_floor=0)  # no plane cue on the floor: the table is the lowest
    table, why = find_floor(xyz, n, cams, FloorLineConfig())
    assert table is not None and abs(table.height - 0.75) < 0.01, why
    sfm = np.c_[rng.uniform(0, 5, 400), rng.uniform(0, 4, 400), rng.normal(0, 0.003, 400)]  # the wood floor
    legs = np.c_[rng.uniform(1, 2, 100), rng.uniform(1, 2, 100), rng.uniform(0, 0.75, 100)]
    above = np.c_[rng.uniform(0, 5, 300), rng.uniform(0, 4, 300), rng.uniform(0.8, 2.5, 300)]
    floor, why = find_floor(xyz, n, cams, FloorLineConfig(), np.r_[sfm, legs, above] @ Q.T)
    assert floor is not None, why
    assert np.degrees(np.arccos(min(1.0, floor.normal @ Q[:, 2]))) < 0.3 and abs(floor.height) < 0.005
    strip = sfm * [1, 0.03, 1]  # seen along one wall only (std 3.5 cm): its tilt is the table's, no matter
    floor, why = find_floor(xyz, n, cams, FloorLineConfig(), np.r_[strip, above] @ Q.T)
    assert floor is not None and abs(floor.height) < 0.005 and strip_width(floor) < 0.05, why
    boxes = np.c_[rng.uniform(2.5, 5, 150), rng.uniform(0, 4, 150), rng.uniform(0.0, 0.6, 150)]  # no layer
    none, why = find_floor(xyz, n, cams, FloorLineConfig(), np.r_[boxes, legs, above] @ Q.T)
    assert none is None and "under the lowest horizontal plane cues (0.75 m below the lowest camera: a table?)" in why
    kept, _ = find_floor(xyz, n, cams, FloorLineConfig(), np.r_[legs, above] @ Q.T)  # only its legs under it
    assert kept is not None and abs(kept.height - table.height) < 1e-12


def test_reflections_under_a_glossy_floor_leave_it_the_floor():
    """A glossy floor's reflections are triangulated below it: scattered, or a mirrored table top in a
    layer 0.75 m under it. They lie under the floor's own footprint and do not make it a table."""
    rng = np.random.default_rng(6)
    cams = [camera(k, (x, 0.5, 1.5), (x, 4.0, 0.0)) for k, x in enumerate(np.linspace(1, 4, 8))]
    xyz, n = room_plane_cues(rng, np.eye(3), n_floor=1500)
    scattered = np.c_[rng.uniform(0.5, 4.5, 150), rng.uniform(0.5, 3.5, 150), rng.uniform(-2.5, -0.1, 150)]
    mirrored = np.c_[rng.uniform(1, 2, 200), rng.uniform(1, 2, 200), rng.normal(-0.75, 0.003, 200)]
    on_it = np.c_[rng.uniform(0, 5, 300), rng.uniform(0, 4, 300), rng.normal(0, 0.003, 300)]
    for below in (scattered, mirrored):
        floor, why = find_floor(xyz, n, cams, FloorLineConfig(), np.r_[below, on_it])
        assert floor is not None and abs(floor.height) < 0.005 and floor.normal[2] > np.cos(np.radians(0.3)), why


def test_a_floor_seen_in_a_thin_strip_is_not_found():
    """Two held-out 24-view rooms saw their bare floor only along one wall, a strip 7 cm wide: its cell
    medians lie in one row and the plane through them tilted 9 and 15 degrees. Such a floor is not found
    (the plain cues follow); a plane through cells in a row is never tilted more than 2 degrees."""
    from geocues.floor import _level_fit

    rng = np.random.default_rng(4)
    cams = [camera(k, (2.5, 2.0, 1.5), (2.5 + np.cos(a), 2 + np.sin(a), 1.0))
            for k, a in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False))]
    m = 300
    strip = np.c_[rng.uniform(0.5, 2.5, m), rng.uniform(0.0, 0.07, m), np.zeros(m)]
    strip[:, 2] += np.where(strip[:, 0] < 1.0, 0.004, 0.0) * (strip[:, 1] / 0.07)  # a bump: a tilt across
    normals = np.tile([0.0, 0.0, 1.0], (m, 1))
    floor, why = find_floor(strip, normals, cams, FloorLineConfig())
    assert floor is None and "strip 0.07 m wide" in why and "tilt" in why, why
    wide = np.c_[rng.uniform(0.5, 2.5, m), rng.uniform(0.0, 1.0, m), np.zeros(m)]
    assert find_floor(wide, normals, cams, FloorLineConfig())[0] is not None
    k = np.arange(6)  # six cells in a row along x, their points 10 cm apart across it and 1 cm apart in height
    row = np.c_[k * 0.25 + 0.1, 0.05 + 0.1 * (k % 2), 0.01 * (k % 2)].repeat(10, axis=0)  # a plane 5.7 deg
    normal, height = _level_fit(row, np.array([0.0, 0.0, 1.0]), band=0.05)
    assert np.array_equal(normal, [0.0, 0.0, 1.0]) and 0.0 <= height <= 0.01
    normal, _ = _level_fit(row, np.array([0.0, 0.0, 1.0]), band=0.05, max_tilt_deg=6.0)
    assert 5.6 < np.degrees(np.arccos(normal[2])) < 5.8  # what it fits without the bound
