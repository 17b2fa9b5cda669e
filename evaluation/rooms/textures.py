"""Procedural albedo of the benchmark rooms: a function of the 2D surface position.

Each triangle has a texture frame (``geometry.py``): a hit point X on it has surface coordinates
``u = (X - o) . e_u``, ``v = (X - o) . e_v`` in metres, and its material's *kind* maps (u, v) to a
linear-RGB albedo. Noise is value noise on a seeded 256 x 256 lattice (bilinear, smoothstep), summed
over octaves (fBm); cell patterns (planks, wallpaper motifs, labels) use an integer hash. Everything
is a pure function of (u, v) and the material's parameters, so every view sees the same texture.

Simulated here: albedo only (paint, wallpaper, wood planks, wood grain, rug, posters, fabric,
cardboard, books, plastic). Not simulated: specularity, normal/bump maps, transparency.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

from evaluation.rooms.geometry import Material, RoomMesh

_TABLE = 256  # value-noise lattice period (cells)


@lru_cache(maxsize=256)
def _lattice(seed: int) -> np.ndarray:
    """Seeded lattice of uniform values in [-1, 1], [256, 256] float32."""
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (_TABLE, _TABLE)).astype(np.float32)


def hash2(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Integer cell coordinates -> uniform values in [0, 1) (deterministic hash), same shape."""
    s = (int(seed) * 2654435761) & 0xFFFFFFFF
    h = (np.asarray(ix, np.int64) * 374761393 + np.asarray(iy, np.int64) * 668265263 + s) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h.astype(np.float64) / 4294967296.0


def value_noise(u: np.ndarray, v: np.ndarray, freq: float, seed: int) -> np.ndarray:
    """Smooth value noise in [-1, 1] at ``freq`` cells per metre, [N]."""
    x, y = u * freq, v * freq
    ix, iy = np.floor(x), np.floor(y)
    fx, fy = x - ix, y - iy
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)  # smoothstep
    ix, iy = ix.astype(np.int64) & (_TABLE - 1), iy.astype(np.int64) & (_TABLE - 1)
    jx, jy = (ix + 1) & (_TABLE - 1), (iy + 1) & (_TABLE - 1)
    t = _lattice(int(seed))
    a = t[ix, iy] + (t[jx, iy] - t[ix, iy]) * fx
    b = t[ix, jy] + (t[jx, jy] - t[ix, jy]) * fx
    return a + (b - a) * fy


def fbm(u: np.ndarray, v: np.ndarray, freq: float, seed: int, octaves: int = 4,
        gain: float = 0.5) -> np.ndarray:
    """Fractal sum of value noise (octaves at freq * 2^k, amplitudes gain^k), about [-1, 1], [N]."""
    out = np.zeros_like(u)
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        # offset each octave so lattice cells of different octaves do not line up
        out += amp * value_noise(u + 17.3 * k, v - 9.1 * k, freq * 2.0**k, seed + 101 * k)
        norm += amp
        amp *= gain
    return out / norm


def _col(c) -> np.ndarray:
    return np.asarray(c, dtype=np.float64)[None, :]


# ---------------------------------------------------------------------- material kinds
def paint(u, v, m: Material) -> np.ndarray:
    """Painted surface: base colour with low-frequency blotches (amp) and fine grain (fine)."""
    p, s = m.params, m.params["seed"]
    f = 1.0 + p["amp"] * fbm(u, v, 1.2, s) + p["fine"] * value_noise(u, v, 45.0, s + 7)
    return _col(m.color) * f[:, None]


def wallpaper(u, v, m: Material) -> np.ndarray:
    """Vertical stripes of two shades with a jittered dot motif and faint blotches."""
    s, w = m.params["seed"], m.params["stripe"]
    iu, iv = np.floor(u / w), np.floor(v / w)
    shade = np.where(iu % 2 == 0, 1.0, 0.78)
    cx = (iu + 0.2 + 0.6 * hash2(iu, iv, s)) * w
    cy = (iv + 0.2 + 0.6 * hash2(iu, iv, s + 1)) * w
    dot = (np.hypot(u - cx, v - cy) < 0.22 * w) & (hash2(iu, iv, s + 2) < 0.7)
    out = _col(m.color) * shade[:, None] * (1.0 + 0.05 * fbm(u, v, 2.0, s))[:, None]
    accent = _col(m.color)[:, ::-1] * 0.6
    return np.where(dot[:, None], accent, out)


def wood_floor(u, v, m: Material) -> np.ndarray:
    """Planks along u (staggered rows across v), per-plank tone, grain lines and dark joints."""
    p, s = m.params, m.params["seed"]
    pw, pl = p["plank_width"], p["plank_length"]
    row = np.floor(v / pw)
    uu = u + hash2(row, 0, s) * pl  # stagger the joints row by row
    col = np.floor(uu / pl)
    tone = 0.7 + 0.6 * hash2(row, col, s + 1)
    vv = v - row * pw
    shift = 50.0 * hash2(row, col, s + 5)  # each plank its own piece of grain
    grain = np.sin(2 * np.pi * (vv * 60.0 + 1.5 * fbm(uu * 0.3 + shift, vv * 4.0 + shift, 3.0, s + 2)))
    f = tone * (1.0 + 0.12 * grain + 0.05 * value_noise(u, v, 40.0, s + 3))
    joint = (vv < 0.002) | (vv > pw - 0.002) | ((uu - col * pl) < 0.003)
    f = np.where(joint, 0.35, f)
    return _col(m.color) * f[:, None]


def wood(u, v, m: Material) -> np.ndarray:
    """Wood grain running along u: warped low-contrast rings, streaks along the grain, fine noise
    (ring spacing ~8 cm and streaks ~1.7 cm across, coarse enough not to alias at 640 px)."""
    s = m.params["seed"]
    rings = np.sin(2 * np.pi * (v * 12.0 + 1.5 * fbm(u, v, 1.5, s)))
    streaks = value_noise(u * 0.05, v, 60.0, s + 2)  # stretched along u
    f = 0.9 + 0.08 * rings + 0.07 * streaks + 0.04 * value_noise(u, v, 35.0, s + 1)
    return _col(m.color) * f[:, None]


def doors(u, v, m: Material) -> np.ndarray:
    """Cabinet front: wood with door grooves (outline inset 4 cm, split in the middle) and knobs."""
    p = m.params
    out = wood(u, v, m)
    w, n = p["width"], p["doors"]
    dw = w / n
    k = np.clip(np.floor(u / dw), 0, n - 1)
    du = u - k * dw
    groove = (np.abs(du - 0.04) < 0.004) | (np.abs(du - (dw - 0.04)) < 0.004) | (du < 0.004)
    groove |= (np.abs(v - 0.06) < 0.004) & (du > 0.04) & (du < dw - 0.04)
    knob_u = np.where(k % 2 == 0, dw - 0.08, 0.08)
    knob = np.hypot(du - knob_u, v - (p["height"] - 0.15)) < 0.018
    return np.where((groove | knob)[:, None], out * 0.35, out)


def fabric(u, v, m: Material) -> np.ndarray:
    """Upholstery: mottled base colour with fine fibre noise."""
    s = m.params["seed"]
    f = 1.0 + 0.08 * fbm(u, v, 3.0, s) + 0.1 * value_noise(u, v, 50.0, s + 1)
    return _col(m.color) * f[:, None]


def cardboard(u, v, m: Material) -> np.ndarray:
    """Cardboard with blotches, fine fibres and a few dark printed labels on a 0.15 m grid."""
    s = m.params["seed"]
    f = 1.0 + 0.1 * fbm(u, v, 5.0, s) + 0.06 * value_noise(u, v, 60.0, s + 1)
    out = _col(m.color) * f[:, None]
    c = 0.15
    iu, iv = np.floor(u / c), np.floor(v / c)
    du, dv = u / c - iu, v / c - iv
    label = (hash2(iu, iv, s) < 0.3) & (du > 0.2) & (du < 0.8) & (dv > 0.35) & (dv < 0.6)
    return np.where(label[:, None], out * 0.25, out)


def book(u, v, m: Material) -> np.ndarray:
    """Book: cover colour with two light title bands."""
    s = m.params["seed"]
    out = _col(m.color) * (1.0 + 0.06 * value_noise(u, v, 40.0, s))[:, None]
    band = ((v > 0.03) & (v < 0.045)) | ((v > 0.14) & (v < 0.15))
    return np.where(band[:, None], _col([0.75, 0.62, 0.25]), out)


def plastic(u, v, m: Material) -> np.ndarray:
    """Moulded plastic: near-uniform with horizontal ridges every 8 cm."""
    s = m.params["seed"]
    ridge = (v % 0.08) < 0.006
    f = np.where(ridge, 0.6, 1.0) * (1.0 + 0.03 * value_noise(u, v, 30.0, s))
    return _col(m.color) * f[:, None]


def rug(u, v, m: Material) -> np.ndarray:
    """Rug: nested border bands, a diamond checker inside, a central medallion, fibre noise."""
    p, s = m.params, m.params["seed"]
    w, h = p["size"]
    pal = np.asarray(p["palette"], dtype=np.float64)
    d = np.minimum(np.minimum(u, w - u), np.minimum(v, h - v))
    a, b = (u + v) / 0.25, (u - v) / 0.25
    out = np.where(((np.floor(a) + np.floor(b)) % 2 == 0)[:, None], pal[2][None], pal[3][None])
    r = np.hypot(u - w / 2, v - h / 2) / (0.3 * min(w, h))
    out = np.where((r < 1.0)[:, None], np.where((r < 0.6)[:, None], _col(m.color), pal[1][None]), out)
    out = np.where((d < 0.12)[:, None], _col(m.color), out)
    out = np.where((d < 0.08)[:, None], pal[1][None], out)
    out = np.where((d < 0.05)[:, None], pal[0][None], out)
    f = 1.0 + 0.06 * fbm(u, v, 4.0, s) + 0.12 * value_noise(u, v, 70.0, s + 1)
    return out * f[:, None]


def poster(u, v, m: Material) -> np.ndarray:
    """Poster: dark frame, background, random shapes in painter's order, paper noise."""
    p, s = m.params, m.params["noise_seed"]
    w, h = p["size"]
    a, b = u / w, v / h  # normalised, [0, 1] on the front face
    out = np.repeat(_col(p["background"]), len(u), axis=0) * (0.85 + 0.3 * a)[:, None]
    for sh in p["shapes"]:
        cx, cy = sh["c"]
        r, th = sh["r"], sh["angle"]
        x, y = (a - cx) * w / min(w, h), (b - cy) * h / min(w, h)
        xr, yr = np.cos(th) * x + np.sin(th) * y, -np.sin(th) * x + np.cos(th) * y
        kind = sh["type"]
        if kind == "circle":
            mask = xr**2 + yr**2 < r**2
        elif kind == "ring":
            rr = np.hypot(xr, yr)
            mask = (rr < r) & (rr > 0.6 * r)
        elif kind == "rect":
            mask = (np.abs(xr) < r) & (np.abs(yr) < 0.6 * r)
        elif kind == "triangle":
            mask = (yr > -0.5 * r) & (yr < r - 1.7 * np.abs(xr))
        else:  # stripes inside a square
            mask = (np.abs(xr) < r) & (np.abs(yr) < r) & ((np.floor(xr / (0.25 * r)) % 2) == 0)
        out = np.where(mask[:, None], _col(sh["color"]), out)
    out = out * (1.0 + 0.08 * fbm(u, v, 8.0, s) + 0.04 * value_noise(u, v, 60.0, s + 1))[:, None]
    fw = p["frame_width"]
    frame = (u < fw) | (u > w - fw) | (v < fw) | (v > h - fw)
    return np.where(frame[:, None], _col([0.04, 0.04, 0.04]), out)


ALBEDO_FUNCTIONS: dict[str, Callable[[np.ndarray, np.ndarray, Material], np.ndarray]] = {
    "paint": paint, "wallpaper": wallpaper, "wood_floor": wood_floor, "wood": wood, "doors": doors,
    "fabric": fabric, "cardboard": cardboard, "book": book, "plastic": plastic, "rug": rug,
    "poster": poster,
}


def surface_coords(mesh: RoomMesh, tri_ids: np.ndarray, points: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Texture coordinates (u, v) in metres of ``points`` [N, 3] lying on triangles ``tri_ids``."""
    fr = mesh.frames[mesh.tri_frame]  # [F, 3, 3]: origin, e_u, e_v per triangle
    # u = X . e_u - o . e_u (one [F, 4] table gathered per hit instead of a [F, 3, 3] one)
    tab_u = np.concatenate([fr[:, 1], -np.einsum("ij,ij->i", fr[:, 0], fr[:, 1])[:, None]], axis=1)
    tab_v = np.concatenate([fr[:, 2], -np.einsum("ij,ij->i", fr[:, 0], fr[:, 2])[:, None]], axis=1)
    a, b = tab_u[tri_ids], tab_v[tri_ids]  # [N, 4]
    u = points[:, 0] * a[:, 0] + points[:, 1] * a[:, 1] + points[:, 2] * a[:, 2] + a[:, 3]
    v = points[:, 0] * b[:, 0] + points[:, 1] * b[:, 1] + points[:, 2] * b[:, 2] + b[:, 3]
    return u, v


def albedo(mesh: RoomMesh, tri_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Linear-RGB albedo in [0, 1] of hit points [N, 3] on triangles [N], [N, 3] float32."""
    tri_ids = np.asarray(tri_ids, dtype=np.int64)
    if points.shape != (len(tri_ids), 3):
        raise ValueError(f"points must be [{len(tri_ids)}, 3], got {points.shape}")
    u, v = surface_coords(mesh, tri_ids, np.asarray(points, dtype=np.float64))
    mats = mesh.tri_material[tri_ids]
    out = np.zeros((len(tri_ids), 3))
    order = np.argsort(mats, kind="stable")
    bounds = np.flatnonzero(np.diff(mats[order])) + 1
    for idx in np.split(order, bounds):
        if len(idx) == 0:
            continue
        m = mesh.materials[int(mats[idx[0]])]
        if m.kind not in ALBEDO_FUNCTIONS:
            raise ValueError(f"material {m.name!r} has unknown kind {m.kind!r}; "
                             f"known: {sorted(ALBEDO_FUNCTIONS)}")
        out[idx] = ALBEDO_FUNCTIONS[m.kind](u[idx], v[idx], m)
    return np.clip(out, 0.0, 1.0).astype(np.float32)
