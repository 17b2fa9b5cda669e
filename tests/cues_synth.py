"""A tiny synthetic room for the cue-stage tests (not a test module itself).

A 4 x 3 x 2.5 m box room (z up) with a textured box on a textured floor and plain walls, rendered
by ray casting at 160 x 120 from a few cameras, written as a COLMAP scene with
``geocues.colmap_io.write_model``. Everything is exact: the test knows the surface, the depth maps
and the 3D edges, so it can measure the cues against them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geocues.colmap_io import RawImage, RawPoints, write_model

ROOM = np.array([4.0, 3.0, 2.5])
BOX_LO, BOX_HI = np.array([2.6, 0.4, 0.0]), np.array([3.2, 1.0, 0.7])
WALL_RGB = {"x0": (0.80, 0.80, 0.82), "x1": (0.85, 0.80, 0.70), "y0": (0.70, 0.78, 0.88),
            "y1": (0.75, 0.86, 0.75), "ceil": (0.92, 0.92, 0.92)}


def _box_faces(lo: np.ndarray, hi: np.ndarray, names: list[str]) -> list[tuple[str, np.ndarray]]:
    """Six quads (4 corners each) of an axis-aligned box, named x0 x1 y0 y1 z0 z1."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    q = {"x0": [(x0, y0, z0), (x0, y1, z0), (x0, y1, z1), (x0, y0, z1)],
         "x1": [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],
         "y0": [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],
         "y1": [(x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1)],
         "z0": [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)],
         "z1": [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]}
    return [(n, np.array(q[k], float)) for k, n in zip(["x0", "x1", "y0", "y1", "z0", "z1"], names)]


def room_mesh() -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(vertices [V, 3], triangles [T, 3], material name per triangle)."""
    faces = _box_faces(np.zeros(3), ROOM, ["x0", "x1", "y0", "y1", "floor", "ceil"])
    faces += [(n, q) for n, q in _box_faces(BOX_LO, BOX_HI, ["box"] * 6) if True]
    faces = [f for f in faces if not (f[0] == "box" and np.allclose(f[1][:, 2], 0.0))]  # no box bottom
    V, T, M = [], [], []
    for name, quad in faces:
        base = len(V)
        V.extend(quad)
        T.extend([(base, base + 1, base + 2), (base, base + 2, base + 3)])
        M.extend([name, name])
    return np.array(V), np.array(T, np.int32), M


def raycasting_scene():
    import open3d as o3d

    V, T, _ = room_mesh()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(T.astype(np.uint32)))
    return scene


def distance_to_surface(points: np.ndarray) -> np.ndarray:
    """Exact distance of ``points`` [N, 3] to the room surface, [N]."""
    import open3d as o3d

    if len(points) == 0:
        return np.zeros(0)
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    return raycasting_scene().compute_distance(q).numpy().astype(np.float64)


def look_at(center: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of an OpenCV camera at ``center`` looking at ``target`` (z up)."""
    f = target - center
    f /= np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    R = np.stack([right, down, f])
    return R, -R @ center


def _hash_noise(p: np.ndarray, cell: float) -> np.ndarray:
    """Deterministic value noise in [0, 1] per ``cell``-sized 3D cell."""
    k = np.floor(p / cell)
    v = np.sin(k[:, 0] * 12.9898 + k[:, 1] * 78.233 + k[:, 2] * 37.719) * 43758.5453
    return v - np.floor(v)


def _smooth_noise(p: np.ndarray, cell: float) -> np.ndarray:
    """:func:`_hash_noise` interpolated trilinearly between the cell corners: continuous, in [0, 1]."""
    k = np.floor(p / cell)
    f = p / cell - k
    out = np.zeros(len(p))
    for corner in np.ndindex(2, 2, 2):
        c = np.array(corner)
        w = np.prod(np.where(c, f, 1 - f), axis=1)
        out += w * _hash_noise((k + c + 0.5) * cell, cell)
    return out


def render(K: np.ndarray, R: np.ndarray, t: np.ndarray, w: int, h: int, plain_floor: bool = False,
           framed_walls: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb [H, W, 3] float32, z-depth [H, W] float32, material index [H, W]); ``plain_floor``: an
    untextured floor (weak texture, like the walls); ``framed_walls``: a textured band 0.6 m wide
    along every wall's edges around its plain middle."""
    import open3d as o3d

    _, _, mats = room_mesh()
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays_c = np.stack([(j - K[0, 2]) / K[0, 0], (i - K[1, 2]) / K[1, 1], np.ones_like(j)], -1).reshape(-1, 3)
    origin = -R.T @ t
    d = rays_c @ R  # world directions with camera z = 1, so t_hit is the z-depth
    rays = np.concatenate([np.broadcast_to(origin, d.shape), d], axis=1).astype(np.float32)
    ans = raycasting_scene().cast_rays(o3d.core.Tensor(rays))
    z = ans["t_hit"].numpy().astype(np.float64)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    nrm = ans["primitive_normals"].numpy().astype(np.float64)
    hit = np.isfinite(z)
    P = origin + d * np.where(hit, z, 0.0)[:, None]
    names = np.array(mats + ["none"])
    name = names[np.where(hit, prim, len(mats))]
    col = np.zeros((len(z), 3))
    for key, rgb in WALL_RGB.items():
        col[name == key] = rgb
    if framed_walls:
        walls = np.isin(name, list(WALL_RGB))
        margin = np.minimum(np.minimum(P, ROOM - P), 1e9)  # distance to each pair of walls
        inner = np.sort(margin, axis=1)[:, 1] > 0.6  # the smallest is the wall the point lies on
        band = walls & ~inner
        col[band] *= (0.4 + 0.6 * _smooth_noise(P[band], 0.05))[:, None]
    tex = _hash_noise(P, 0.04)
    checker = ((np.floor(P[:, 0] / 0.25) + np.floor(P[:, 1] / 0.25)) % 2)
    floor = name == "floor"
    col[floor] = (0.6 if plain_floor else (0.35 + 0.25 * checker[floor] + 0.3 * tex[floor])[:, None]) \
        * np.array([0.9, 0.7, 0.5])
    box = name == "box"
    col[box] = (0.2 + 0.6 * _hash_noise(P[box], 0.03))[:, None] * np.array([0.5, 0.6, 0.9])
    light = np.array([2.0, 1.5, 2.4])
    ldir = light - P
    ldir /= np.maximum(np.linalg.norm(ldir, axis=1, keepdims=True), 1e-9)
    shade = 0.75 + 0.25 * np.abs(np.sum(nrm * ldir, axis=1))
    rgb = np.clip(col * shade[:, None], 0, 1).reshape(h, w, 3).astype(np.float32)
    depth = np.where(hit, z, 0.0).reshape(h, w).astype(np.float32)
    mat_id = np.where(hit, prim // 2, -1).reshape(h, w)
    return rgb, depth, mat_id


def room_edges() -> np.ndarray:
    """3D segments [L, 2, 3] along the room's and the box's visible edges."""
    c = np.array([[x, y, z] for x in (0, ROOM[0]) for y in (0, ROOM[1]) for z in (0, ROOM[2])], float)
    segs = []
    for a in range(8):
        for b in range(a + 1, 8):
            if np.sum(np.abs(c[a] - c[b]) > 0) == 1:
                segs.append((c[a], c[b]))
    lo, hi = BOX_LO, BOX_HI
    bc = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for a in range(8):
        for b in range(a + 1, 8):
            if np.sum(np.abs(bc[a] - bc[b]) > 0) == 1 and not (bc[a][2] == 0 and bc[b][2] == 0):
                segs.append((bc[a], bc[b]))
    return np.array(segs)


def fake_line_cues(cams: list, step: float = 0.05, drop: tuple[int, ...] = ()):
    """A LineCues made of the exact room edges (``drop``: camera indices that see no line)."""
    from geocues.lines import LineCues

    segs = room_edges()
    pts, pl = [], []
    views = []
    for li, (a, b) in enumerate(segs):
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
        s = np.linspace(0, 1, n)[:, None]
        pts.append(a + s * (b - a))
        pl.append(np.full(n, li))
        mid = 0.5 * (a + b)
        v = [c.index for c in cams if c.index not in drop and c.project(mid[None])[1][0] > 0]
        views.append(np.array(v, np.int64))
    P = np.concatenate(pts)
    L = len(segs)
    return LineCues(segs, np.array([len(v) for v in views], np.int64), views,
                    np.full((L, 3), 0.5, np.float32), P, np.full((len(P), 3), 0.5, np.float32),
                    np.concatenate(pl).astype(np.int64), np.zeros((len(P), 3), np.float32))


def make_room_scene(root: Path, n_views: int = 6, w: int = 160, h: int = 120,
                    priors: str = "all", n_sfm: int = 300, n_outliers: int = 30,
                    prior_scale: float = 0.5, prior_shift: float = 0.3, seed: int = 0,
                    plain_floor: bool = False, pitch: tuple[float, ...] = (-0.35,),
                    framed_walls: bool = False, poses: list | None = None) -> Path:
    """Write the synthetic room scene to ``root`` and return it.

    priors: "all", "none" or "some" (every other image) -- simulated depth priors
    prior = prior_scale * z + prior_shift (+ 2 mm noise), labelled simulated in scene.json.
    n_sfm: SfM points on the textured floor and box (3 mm noise) plus ``n_outliers`` in the air.
    plain_floor: an untextured floor (it gets plane cues, as in the bare rooms).
    framed_walls: walls textured along their edges, plain in their middle (see :func:`render`).
    poses: (centre, target) per view instead of the ring of ``n_views`` views looking out.
    pitch: view k looks along (cos yaw, sin yaw, pitch[k % len(pitch)]) (the default looks down at
    the floor; a positive one sees the ceiling).
    """
    import json

    import cv2

    rng = np.random.default_rng(seed)
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    K = np.array([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]]) * np.array([[w / 160], [w / 160], [1]])
    images = []
    for k in range(n_views if poses is None else len(poses)):
        if poses is None:
            yaw = 2 * np.pi * k / n_views
            c = np.array([2.0, 1.5, 1.4]) + 0.3 * np.array([np.cos(yaw + 1), np.sin(yaw + 1), 0])
            target = c + np.array([np.cos(yaw), np.sin(yaw), pitch[k % len(pitch)]])
        else:
            c, target = (np.asarray(v, float) for v in poses[k])
        R, t = look_at(c, target)
        rgb, depth, _ = render(K, R, t, w, h, plain_floor, framed_walls)
        name = f"{k:05d}.png"
        cv2.imwrite(str(root / "images" / name), (rgb[:, :, ::-1] * 255 + 0.5).astype(np.uint8))
        images.append(RawImage(k + 1, 1, name, "PINHOLE", w, h, K, R, t))
        if priors == "all" or (priors == "some" and k % 2 == 0):
            (root / "priors" / "depth").mkdir(parents=True, exist_ok=True)
            prior = prior_scale * depth + prior_shift + rng.normal(0, 0.002, depth.shape)
            np.save(root / "priors" / "depth" / f"{k:05d}.npy",
                    np.where(depth > 0, prior, 0).astype(np.float32))
    # SfM points: on the floor (away from the box) and on the box's top and sides
    n_floor = n_sfm // 2
    fl = np.column_stack([rng.uniform(0.1, 3.9, n_floor), rng.uniform(0.1, 2.9, n_floor), np.zeros(n_floor)])
    fl = fl[~np.all((fl[:, :2] > BOX_LO[:2]) & (fl[:, :2] < BOX_HI[:2]), axis=1)]
    nb = n_sfm - len(fl)
    bx = np.column_stack([rng.uniform(BOX_LO[0], BOX_HI[0], nb), rng.uniform(BOX_LO[1], BOX_HI[1], nb),
                          np.full(nb, BOX_HI[2])])
    side = rng.random(nb) < 0.5
    bx[side, 0] = BOX_LO[0]
    bx[side, 2] = rng.uniform(0.05, 0.65, side.sum())
    xyz = np.concatenate([fl, bx]) + rng.normal(0, 0.003, (n_sfm, 3)) if n_sfm else np.zeros((0, 3))
    if n_outliers and n_sfm:
        xyz = np.concatenate([xyz, rng.uniform([0.5, 0.5, 0.5], [3.5, 2.5, 2.0], (n_outliers, 3))])
    n = len(xyz)
    pts = RawPoints(np.arange(1, n + 1, dtype=np.int64), xyz, np.full((n, 3), 128, np.uint8),
                    np.full(n, 0.5), np.full(n, 3, np.int32), [np.zeros(0, np.int64)] * n)
    write_model(root / "sparse" / "0", images, pts if n else None)
    if priors != "none":
        (root / "scene.json").write_text(json.dumps({"priors": {"depth": "simulated: affine of exact depth"}}))
    return root


class ExactAlignment:
    """A stand-in for a cue alignment (geocues.depth_align.DepthAlignment) of a prior that is
    already metric: ``apply`` returns it as it is."""

    residual_p90_m = 0.01

    def apply(self, d: np.ndarray) -> np.ndarray:
        return d
