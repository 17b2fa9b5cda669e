"""Small synthetic scenes for the line-cue tests (not a test module itself).

A box room (z up) whose walls carry painted rectangles and stripes, rendered with Open3D's
RaycastingScene (3 x 3 supersampling, Lambert shading) from a few look-at cameras and written as a
COLMAP scene. Painted edges are exact 3D segments on the walls, so a test can measure triangulated
lines against the mesh. Options build the hard cases: cameras that only translate along x (lines
parallel to the epipolar direction), blank walls (images without lines), flat shading with normal
priors (edges that only the normal maps show).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from geocues.colmap_io import RawImage, write_model

ROOM = np.array([4.0, 3.0, 2.5])
# painted rectangles on the far wall y = ROOM[1]: (x0, x1, z0, z1, albedo)
RECTS = [(0.5, 1.3, 0.9, 1.8, 0.15), (1.7, 2.3, 1.1, 1.6, 0.35), (2.7, 3.5, 0.6, 2.0, 0.25),
         (1.5, 2.5, 0.3, 0.7, 0.55)]
# horizontal stripes (z0, z1) and vertical stripes (x0, x1) on the far wall, for the epipolar case
H_STRIPES = [(0.5, 0.6), (1.2, 1.35), (1.9, 2.0)]
V_STRIPES = [(0.7, 0.8), (1.6, 1.75), (2.6, 2.7), (3.3, 3.45)]


def room_mesh() -> o3d.t.geometry.TriangleMesh:
    """The closed box [0, ROOM] as a triangle mesh (the walls are the only surfaces)."""
    box = o3d.geometry.TriangleMesh.create_box(width=ROOM[0], height=ROOM[1], depth=ROOM[2])
    return o3d.t.geometry.TriangleMesh.from_legacy(box)


def look_at(C: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of an OpenCV camera at C looking at target, world z up."""
    f = target - C
    f = f / np.linalg.norm(f)
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])
    return R, -R @ C


def albedo(P: np.ndarray, pattern: str) -> np.ndarray:
    """Grey albedo [N] of surface points P [N, 3] for a wall pattern: "rects", "stripes", "blank"."""
    a = np.full(len(P), 0.8)
    far = np.abs(P[:, 1] - ROOM[1]) < 1e-4
    x, z = P[:, 0], P[:, 2]
    if pattern == "rects":
        for x0, x1, z0, z1, v in RECTS:
            a[far & (x >= x0) & (x <= x1) & (z >= z0) & (z <= z1)] = v
        floor = np.abs(P[:, 2]) < 1e-4
        a[floor] = np.where((np.floor(P[floor, 0] / 0.5) + np.floor(P[floor, 1] / 0.5)) % 2 == 0, 0.3, 0.6)
    elif pattern == "stripes":
        for z0, z1 in H_STRIPES:
            a[far & (z >= z0) & (z <= z1)] = 0.2
        for x0, x1 in V_STRIPES:
            a[far & (x >= x0) & (x <= x1)] = 0.2
    elif pattern != "blank":
        raise ValueError(f"unknown pattern {pattern!r}")
    return a


def render(scene: o3d.t.geometry.RaycastingScene, K: np.ndarray, R: np.ndarray, t: np.ndarray,
           width: int, height: int, pattern: str, shading: bool = True, ss: int = 3):
    """(RGB float32 [H, W, 3], camera-frame normals [H, W, 3] at pixel centres) of one view."""
    C = -R.T @ t
    jj, ii = np.meshgrid(np.arange(width * ss) / ss, np.arange(height * ss) / ss)
    u, v = jj + 0.5 / ss, ii + 0.5 / ss  # sub-pixel sample positions (COLMAP pixels)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d_world = d_cam.reshape(-1, 3) @ R
    rays = np.concatenate([np.broadcast_to(C, d_world.shape), d_world], 1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    th = hit["t_hit"].numpy()
    n = hit["primitive_normals"].numpy().astype(np.float64)
    P = C + th[:, None] * d_world
    shade = np.full(len(P), 1.0)
    if shading:
        light = np.array([0.3, -0.5, 0.8])
        shade = 0.35 + 0.65 * np.abs(n @ (light / np.linalg.norm(light)))
    val = np.where(np.isfinite(th), albedo(P, pattern) * shade, 0.0)
    img = val.reshape(height, ss, width, ss).mean((1, 3))  # box-filtered pixels
    rgb = np.repeat(img[..., None], 3, -1).astype(np.float32)
    nc = (n @ R.T).reshape(height * ss, width * ss, 3)[ss // 2::ss, ss // 2::ss]  # pixel centres
    dc = d_cam[ss // 2::ss, ss // 2::ss]
    nc = np.where(((nc * dc).sum(-1) > 0)[..., None], -nc, nc)  # facing the camera
    return rgb, nc.astype(np.float32)


def camera_path(kind: str, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera centres and look-at targets: "arc" (varied positions looking at the far wall),
    "corner" (an arc looking into a corner of the room), "x_only" (a row along x, all looking
    along +y: pure x translation)."""
    out = []
    for k in range(n):
        s = k / max(n - 1, 1)
        if kind == "arc":
            C = np.array([0.9 + 2.2 * s, 0.5 + 0.5 * np.sin(np.pi * s), 1.2 + 0.4 * np.cos(3 * s)])
            target = np.array([1.2 + 1.6 * s, ROOM[1], 1.1 + 0.2 * np.sin(5 * s)])
        elif kind == "corner":  # looking into the corner x = ROOM[0], y = ROOM[1] from an arc
            a = np.deg2rad(-60 + 75 * s)
            C = np.array([2.6, 1.6, 1.3]) + 1.2 * np.array([np.cos(a), np.sin(a), 0.0]) * [1.0, 0.8, 0]
            C[2] = 1.2 + 0.3 * s
            target = np.array([ROOM[0] - 0.4, ROOM[1] - 0.4, 0.6])
        elif kind == "x_only":
            C = np.array([1.4 + 1.2 * s, 0.8, 1.3])
            target = C + np.array([0.0, 1.0, 0.0])
        else:
            raise ValueError(f"unknown camera path {kind!r}")
        out.append((C, target))
    return out


def make_scene(root: Path, n_views: int = 10, width: int = 320, height: int = 240,
               pattern: str = "rects", path: str = "arc", shading: bool = True,
               normals: bool = False, blank_views: tuple[int, ...] = ()) -> Path:
    """Write a synthetic COLMAP scene into ``root`` (images/, sparse/0/, gt/mesh.ply, and
    priors/normal/*.npy when ``normals``). Views in ``blank_views`` look at a blank wall patch."""
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    mesh = room_mesh()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    f = 0.9 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    images = []
    for k, (C, target) in enumerate(camera_path(path, n_views)):
        R, t = look_at(C, target)
        blank = k in blank_views
        rgb, nrm = render(scene, K, R, t, width, height, "blank" if blank else pattern,
                          shading and not blank)
        name = f"{k:05d}.png"
        cv2.imwrite(str(root / "images" / name), (rgb[:, :, ::-1] * 255).round().astype(np.uint8))
        if normals:
            (root / "priors" / "normal").mkdir(parents=True, exist_ok=True)
            np.save(root / "priors" / "normal" / f"{k:05d}.npy", nrm)
        images.append(RawImage(k + 1, 1, name, "PINHOLE", width, height, K, R, t))
    write_model(root / "sparse" / "0", images)
    (root / "gt").mkdir(exist_ok=True)
    o3d.io.write_triangle_mesh(str(root / "gt" / "mesh.ply"), mesh.to_legacy())
    return root


def distances_to_mesh(points: np.ndarray) -> np.ndarray:
    """Unsigned distances [N] of points [N, 3] to the room's surface."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(room_mesh())
    q = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
    return scene.compute_distance(query_points=q).numpy()
