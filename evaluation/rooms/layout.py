"""Seedable room layouts: a *textured* living room and a *bare* white room.

A layout is the room shell (floor, ceiling, four walls; normals inward), furniture standing on the
floor or hanging on walls (normals outward, hidden faces such as a bottom on the floor or a back
against a wall left out), their materials and the point lights. Everything is drawn from the
``numpy.random.Generator`` handed in, so a seed fixes the room.

Walls are numbered 0..3: south (y = 0), east (x = W), north (y = D), west (x = 0). Along wall k a
position ``s`` runs in the direction of the wall's texture u axis, from one corner to the other.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np

from evaluation.rooms.geometry import Z_UP, MeshBuilder, RoomMesh

log = logging.getLogger(__name__)

Layout = Literal["textured", "bare"]
LAYOUTS = ("textured", "bare")
WALL_NAMES = ("south", "east", "north", "west")
GAP = 0.01  # metres between furniture and the wall it stands against (no coplanar faces)


@dataclass
class Room:
    """A generated room: geometry, lights and the parameters that made it."""

    layout: str
    size: tuple[float, float, float]  # (W, D, H) metres
    mesh: RoomMesh
    lights: np.ndarray  # [L, 3] point light positions
    light_power: np.ndarray  # [L] intensity (irradiance at 1 m distance, before falloff)
    ambient: float  # ambient term of the shading

    def summary(self) -> dict:
        """JSON-ready description (for scene.json)."""
        return {"layout": self.layout, "size_m": [round(s, 6) for s in self.size],
                "n_triangles": int(len(self.mesh.triangles)),
                "materials": [{"name": m.name, "kind": m.kind, "color": [round(c, 4) for c in m.color]}
                              for m in self.mesh.materials],
                "lights": {"positions": self.lights.round(6).tolist(),
                           "power": self.light_power.round(6).tolist(), "ambient": self.ambient}}


def wall_frame(k: int, W: float, D: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Wall k -> (floor-level start point p0 [3], u direction along the wall [3], inward normal [3],
    length). A point on the wall is ``p0 + s u + z e_z`` for s in [0, length]."""
    n = [np.array([0.0, 1, 0]), np.array([-1.0, 0, 0]), np.array([0.0, -1, 0]), np.array([1.0, 0, 0])][k]
    u = np.cross(Z_UP, n)  # matches the shell quads' u = v x n with v = up
    start = {0: [W, 0, 0], 1: [W, D, 0], 2: [0, D, 0], 3: [0, 0, 0]}[k]
    length = W if k in (0, 2) else D
    return np.asarray(start, dtype=np.float64), u, n, float(length)


def _wall_box(b: MeshBuilder, k: int, W: float, D: float, s0: float, width: float, depth: float,
              z0: float, height: float, mat: int, skip=("bottom", "back"), **kw) -> None:
    """A box against wall k covering s in [s0, s0 + width], z in [z0, z0 + height]; its "front"
    faces the room and its "back" the wall."""
    p0, u, n, _ = wall_frame(k, W, D)
    centre = p0 + u * (s0 + width / 2) + n * (GAP + depth / 2) + Z_UP * (z0 + height / 2)
    b.box(centre, (width, depth, height), mat, axis_x=-u, skip=skip, **kw)  # box y axis = n


def _place_along(rng: np.random.Generator, length: float, widths: list[float],
                 margin: float = 0.25) -> list[float]:
    """Non-overlapping start positions for intervals of ``widths`` along a wall of ``length``,
    in random order with random gaps; raises ValueError if they cannot fit."""
    free = length - 2 * margin - sum(widths)
    if free < 0:
        raise ValueError(f"intervals of total width {sum(widths):.2f} m do not fit on a "
                         f"{length:.2f} m wall")
    order = rng.permutation(len(widths))
    gaps = rng.dirichlet(np.ones(len(widths) + 1)) * free
    starts = [0.0] * len(widths)
    s = margin
    for slot, idx in enumerate(order):
        s += gaps[slot]
        starts[idx] = s
        s += widths[idx]
    return starts


def _shell(b: MeshBuilder, W: float, D: float, H: float, wall_mats: list[int], floor: int,
           ceiling: int) -> None:
    """Floor, ceiling and walls of the room with inward normals."""
    c = np.array([W / 2, D / 2, H / 2])
    b.quad([W / 2, D / 2, 0.0], [1.0, 0, 0], [0, 1.0, 0], W / 2, D / 2, floor, origin=[0.0, 0, 0])
    b.quad([W / 2, D / 2, H], [1.0, 0, 0], [0, -1.0, 0], W / 2, D / 2, ceiling)
    for k in range(4):
        p0, u, n, length = wall_frame(k, W, D)
        centre = p0 + u * length / 2 + Z_UP * H / 2
        b.quad(centre, u, Z_UP, length / 2, H / 2, wall_mats[k], origin=p0)
        assert np.dot(c - centre, n) > 0


def _palette(rng: np.random.Generator, n: int, sat=(0.35, 0.85), val=(0.25, 0.85)) -> np.ndarray:
    """n random saturated colours (linear RGB) from HSV draws, [n, 3]."""
    h = rng.uniform(0, 1, n)
    s = rng.uniform(*sat, n)
    v = rng.uniform(*val, n)
    k = (np.array([5.0, 3.0, 1.0])[None] + h[:, None] * 6) % 6
    rgb = v[:, None] - v[:, None] * s[:, None] * np.clip(np.minimum(k, 4 - k), 0, 1)
    return rgb ** 2.2  # to linear


def _poster_params(rng: np.random.Generator, w: float, h: float) -> dict:
    """Random shapes (circles, rectangles, triangles, rings, stripes) in normalised poster coords."""
    n = int(rng.integers(7, 15))
    cols = _palette(rng, n + 1)
    shapes = []
    for i in range(n):
        shapes.append({"type": str(rng.choice(["circle", "rect", "triangle", "ring", "stripes"])),
                       "c": rng.uniform(0.1, 0.9, 2).round(4).tolist(),
                       "r": float(round(rng.uniform(0.06, 0.3), 4)),
                       "angle": float(round(rng.uniform(0, np.pi), 4)),
                       "color": cols[i].round(4).tolist()})
    return {"size": [w, h], "background": cols[n].round(4).tolist(), "shapes": shapes,
            "noise_seed": int(rng.integers(0, 2**31 - 1)), "frame_width": 0.03}


def _light_setup(rng: np.random.Generator, W: float, D: float, H: float, n: int):
    pos = np.stack([rng.uniform(0.25, 0.75, n) * W, rng.uniform(0.25, 0.75, n) * D,
                    np.full(n, H - 0.25)], axis=1)
    power = rng.uniform(1.2, 1.8, n)
    return pos, power


def make_textured(rng: np.random.Generator) -> Room:
    """Living room: wood floor, rug, painted walls (one wallpapered), posters, sofa, table,
    cabinet, wall shelves with books, cardboard boxes and a cylindrical bin."""
    W, D, H = rng.uniform(4.0, 6.0), rng.uniform(3.0, 5.0), rng.uniform(2.5, 3.0)
    b = MeshBuilder()
    paint = _palette(rng, 1, sat=(0.08, 0.25), val=(0.8, 0.95))[0]
    walls = rng.permutation(4)  # walls[0]: sofa, [1]: cabinet + boxes, [2]: shelves, [3]: wallpaper
    wall_mats = []
    for k in range(4):
        if k == walls[3]:
            wall_mats.append(b.material(f"wall_{WALL_NAMES[k]}", "wallpaper",
                                        _palette(rng, 1, sat=(0.2, 0.5), val=(0.55, 0.8))[0],
                                        stripe=float(rng.uniform(0.08, 0.2)),
                                        seed=int(rng.integers(2**31 - 1))))
        else:
            wall_mats.append(b.material(f"wall_{WALL_NAMES[k]}", "paint", paint, amp=0.05,
                                        fine=0.02, seed=int(rng.integers(2**31 - 1))))
    floor = b.material("floor", "wood_floor", [0.45, 0.28, 0.15], plank_width=float(rng.uniform(0.12, 0.2)),
                       plank_length=float(rng.uniform(0.9, 1.5)), seed=int(rng.integers(2**31 - 1)))
    ceiling = b.material("ceiling", "paint", [0.85, 0.85, 0.83], amp=0.02, fine=0.01,
                         seed=int(rng.integers(2**31 - 1)))
    _shell(b, W, D, H, wall_mats, floor, ceiling)

    wood = b.material("wood", "wood", [0.5, 0.32, 0.18], seed=int(rng.integers(2**31 - 1)))
    dark_wood = b.material("dark_wood", "wood", [0.25, 0.14, 0.08], seed=int(rng.integers(2**31 - 1)))
    fabric = b.material("sofa", "fabric", _palette(rng, 1, sat=(0.3, 0.6), val=(0.3, 0.6))[0],
                        seed=int(rng.integers(2**31 - 1)))
    card = b.material("cardboard", "cardboard", [0.55, 0.38, 0.2], seed=int(rng.integers(2**31 - 1)))

    # rug and table in the middle
    rw, rd = rng.uniform(0.45, 0.6) * W, rng.uniform(0.45, 0.6) * D
    rug = b.material("rug", "rug", _palette(rng, 1)[0], size=[rw, rd],
                     palette=_palette(rng, 4).round(4).tolist(), seed=int(rng.integers(2**31 - 1)))
    rc = np.array([W / 2 + rng.uniform(-0.2, 0.2), D / 2 + rng.uniform(-0.2, 0.2)])
    b.box([rc[0], rc[1], 0.006], (rw, rd, 0.012), rug, skip=("bottom",), obstacle=False)
    tw, td, th = rng.uniform(1.0, 1.4), rng.uniform(0.6, 0.8), rng.uniform(0.7, 0.76)
    b.box([rc[0], rc[1], th - 0.02], (tw, td, 0.04), wood, skip=())
    for sx in (-1, 1):
        for sy in (-1, 1):
            lx, ly = rc[0] + sx * (tw / 2 - 0.06), rc[1] + sy * (td / 2 - 0.06)
            b.box([lx, ly, 0.012 + (th - 0.052) / 2], (0.05, 0.05, th - 0.052), wood)

    # sofa against walls[0]: seat, back, two arms
    k = int(walls[0])
    _, _, _, L = wall_frame(k, W, D)
    sw = min(rng.uniform(1.8, 2.3), L - 1.95)  # 0.95 m from the corners: clear of other furniture
    s0 = _place_along(rng, L, [sw], margin=0.95)[0]
    _wall_box(b, k, W, D, s0 + 0.18, sw - 0.36, 0.85, 0.0, 0.42, fabric,
              skip=("bottom", "back", "left", "right"))
    _wall_box(b, k, W, D, s0 + 0.18, sw - 0.36, 0.2, 0.42, 0.45, fabric)
    for a in (s0, s0 + sw - 0.18):
        _wall_box(b, k, W, D, a, 0.18, 0.85, 0.0, 0.62, fabric)

    # cabinet and stacked boxes against walls[1]
    k = int(walls[1])
    _, _, _, L = wall_frame(k, W, D)
    cw, bw = rng.uniform(0.8, 1.1), rng.uniform(0.4, 0.6)
    s_cab, s_box = _place_along(rng, L, [cw, bw + 0.1], margin=0.3)
    ch = rng.uniform(0.9, 1.2)
    cab_front = b.material("cabinet_doors", "doors", [0.5, 0.32, 0.18], doors=2, width=cw,
                           height=ch, seed=int(rng.integers(2**31 - 1)))
    _wall_box(b, k, W, D, s_cab, cw, 0.45, 0.0, ch, dark_wood, face_mats={"front": cab_front})
    z = 0.0
    for i in range(int(rng.integers(2, 4))):
        h = rng.uniform(0.25, 0.4)
        w = bw * rng.uniform(0.8, 1.0)
        _wall_box(b, k, W, D, s_box + rng.uniform(0, 0.1), w, w * rng.uniform(0.8, 1.1), z, h, card,
                  skip=("bottom",) if i == 0 else ())
        z += h

    # wall shelves with books against walls[2], a poster beside them
    k = int(walls[2])
    _, _, _, L = wall_frame(k, W, D)
    shw = rng.uniform(1.0, 1.4)
    pw, ph = rng.uniform(0.5, 0.8), rng.uniform(0.5, 0.8)
    s_sh, s_po = _place_along(rng, L, [shw, pw], margin=0.3)
    for level, zb in enumerate((1.0, 1.38, 1.76)):
        _wall_box(b, k, W, D, s_sh, shw, 0.25, zb, 0.025, wood, skip=("back",))
        s = s_sh + 0.05
        while s < s_sh + shw - 0.1:
            bwid = rng.uniform(0.025, 0.06)
            if rng.uniform() < 0.15:
                s += bwid + 0.03
                continue
            book = b.material(f"book_{level}_{len(b.materials)}", "book", _palette(rng, 1)[0],
                              seed=int(rng.integers(2**31 - 1)))
            _wall_box(b, k, W, D, s, bwid, rng.uniform(0.15, 0.22), zb + 0.025,
                      rng.uniform(0.18, 0.3), book)
            s += bwid + 0.003
    posters = [(k, s_po, pw, ph, rng.uniform(1.2, 1.5))]

    # posters above the sofa and the cabinet, two on the wallpapered wall
    for kk, zlo in ((int(walls[0]), 1.1), (int(walls[1]), 1.35)):
        _, _, _, L = wall_frame(kk, W, D)
        pw, ph = rng.uniform(0.5, 1.0), rng.uniform(0.4, 0.8)
        posters.append((kk, _place_along(rng, L, [pw], margin=0.4)[0], pw, ph,
                        rng.uniform(zlo, min(zlo + 0.4, H - ph - 0.2))))
    k = int(walls[3])
    _, _, _, L = wall_frame(k, W, D)
    sizes = [(rng.uniform(0.4, 0.8), rng.uniform(0.5, 0.9)) for _ in range(2)]
    for s, (pw, ph) in zip(_place_along(rng, L, [w for w, _ in sizes], margin=0.3), sizes):
        posters.append((k, s, pw, ph, rng.uniform(1.1, min(1.6, H - ph - 0.2))))
    for i, (kk, s, pw, ph, z0) in enumerate(posters):
        mat = b.material(f"poster_{i}", "poster", [0.8, 0.8, 0.8], **_poster_params(rng, pw, ph))
        _wall_box(b, kk, W, D, s, pw, 0.012, z0, ph, mat, skip=("back",), obstacle=False)

    # a cylindrical bin in front of the wallpapered wall, clear of the corners' furniture
    bin_mat = b.material("bin", "plastic", _palette(rng, 1)[0], seed=int(rng.integers(2**31 - 1)))
    p0, u, n, L = wall_frame(k, W, D)
    centre = p0 + u * rng.uniform(1.1, L - 1.1) + n * 0.25
    b.cylinder(centre[:2], 0.0, rng.uniform(0.35, 0.55), 0.16, bin_mat, segments=20)

    lights, power = _light_setup(rng, W, D, H, 2)
    return Room("textured", (W, D, H), b.build(), lights, power, ambient=0.3)


def make_bare(rng: np.random.Generator) -> Room:
    """Bare room: near-uniform white walls and ceiling, a faintly textured floor, a door, one
    cabinet and one box (hard for SfM)."""
    W, D, H = rng.uniform(4.0, 6.0), rng.uniform(3.0, 5.0), rng.uniform(2.5, 3.0)
    b = MeshBuilder()
    white = b.material("walls", "paint", [0.82, 0.82, 0.8], amp=0.006, fine=0.004,
                       seed=int(rng.integers(2**31 - 1)))
    floor = b.material("floor", "paint", [0.55, 0.53, 0.5], amp=0.03, fine=0.03,
                       seed=int(rng.integers(2**31 - 1)))
    ceiling = b.material("ceiling", "paint", [0.85, 0.85, 0.85], amp=0.004, fine=0.003,
                         seed=int(rng.integers(2**31 - 1)))
    _shell(b, W, D, H, [white] * 4, floor, ceiling)
    walls = rng.permutation(4)
    door = b.material("door", "paint", [0.7, 0.7, 0.68], amp=0.01, fine=0.005,
                      seed=int(rng.integers(2**31 - 1)))
    k = int(walls[0])
    _, _, _, L = wall_frame(k, W, D)
    s = _place_along(rng, L, [0.9], margin=0.4)[0]
    _wall_box(b, k, W, D, s, 0.9, 0.03, 0.0, 2.05, door, obstacle=False)
    _wall_box(b, k, W, D, s + 0.75, 0.1, 0.06, 1.0, 0.03, door, skip=("back",), obstacle=False)
    wood = b.material("wood", "wood", [0.55, 0.4, 0.25], seed=int(rng.integers(2**31 - 1)))
    k = int(walls[1])
    _, _, _, L = wall_frame(k, W, D)
    cw = rng.uniform(0.7, 1.0)
    _wall_box(b, k, W, D, _place_along(rng, L, [cw], margin=0.7)[0], cw, 0.45, 0.0,
              rng.uniform(0.8, 1.1), wood)
    card = b.material("box", "cardboard", [0.6, 0.45, 0.3], seed=int(rng.integers(2**31 - 1)))
    k = int(walls[2])
    _, _, _, L = wall_frame(k, W, D)
    bw = rng.uniform(0.4, 0.6)
    _wall_box(b, k, W, D, _place_along(rng, L, [bw], margin=0.7)[0], bw, bw, 0.0,
              rng.uniform(0.3, 0.5), card)
    lights, power = _light_setup(rng, W, D, H, 2)
    return Room("bare", (W, D, H), b.build(), lights, power, ambient=0.3)


def make_room_geometry(layout: str, rng: np.random.Generator) -> Room:
    """Build the room of the given layout ("textured" or "bare") from ``rng``."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    room = make_textured(rng) if layout == "textured" else make_bare(rng)
    log.info("room %s: %.2f x %.2f x %.2f m, %d triangles, %d materials", layout, *room.size,
             len(room.mesh.triangles), len(room.mesh.materials))
    return room
