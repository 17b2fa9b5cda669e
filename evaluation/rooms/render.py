"""Ray-cast rendering of a room with Open3D ``RaycastingScene``: images, GT depth and GT normals.

Simulated: procedural albedo (``textures.py``) times direct lighting from point lights plus an
ambient term, with hard ray-cast shadows (optional), S x S supersampling per pixel, sRGB gamma and
8-bit sensor noise (in the writer). Not simulated: global illumination, reflections, specular
highlights, motion blur, lens distortion, vignetting, auto-exposure.

Cameras follow docs/conventions.md: ``x_cam = R x_world + t``, OpenCV axes, COLMAP pixel centres
(pixel (row i, col j) has centre (j + 0.5, i + 0.5)). GT depth and normals are taken with one ray
through each pixel centre, so they are exact for that ray; colours average S x S sub-pixel rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evaluation.rooms.layout import Room
from evaluation.rooms.textures import albedo

LIGHT_SOFTENING = 1.0  # d0 in E = P cos(theta) / (d0^2 + d^2), metres
SHADOW_OFFSET = 1e-4  # metres along the normal before casting a shadow ray


@dataclass
class View:
    """One rendered view. ``image`` is display-referred (sRGB) before sensor noise."""

    image: np.ndarray  # [H, W, 3] float32 in [0, 1]
    depth: np.ndarray  # [H, W] float32 z-depth, metres (0 = no hit)
    normal: np.ndarray  # [H, W, 3] float32 unit, camera frame, facing the camera
    triangle: np.ndarray  # [H, W] int64 triangle id at the pixel centre (-1 = no hit)


def pixel_directions(K: np.ndarray, width: int, height: int, offsets: np.ndarray) -> np.ndarray:
    """Camera-frame ray directions with z = 1 through sub-pixel positions ``(j + ox, i + oy)``
    for each offset pair [S, 2] (0.5, 0.5 = the pixel centre), [H, W, S, 3]."""
    j, i = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x = (j[..., None] + offsets[None, None, :, 0] - K[0, 2]) / K[0, 0]
    y = (i[..., None] + offsets[None, None, :, 1] - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def _cast(scene, origin: np.ndarray, dirs_world: np.ndarray) -> dict[str, np.ndarray]:
    import open3d as o3d

    rays = np.concatenate([np.broadcast_to(origin, dirs_world.shape), dirs_world], axis=-1)
    ans = scene.cast_rays(rays=o3d.core.Tensor(rays.astype(np.float32)))
    return {k: v.numpy() for k, v in ans.items()}


def lambert_shading(room: Room, scene, points: np.ndarray, normals: np.ndarray,
                    shadows: bool = True) -> np.ndarray:
    """Irradiance E = ambient + sum_l P_l max(0, n.l) / (d0^2 + d_l^2) [* visibility_l] at
    ``points`` [N, 3] with unit ``normals`` [N, 3] facing the viewer, [N]."""
    import open3d as o3d

    E = np.full(len(points), room.ambient)
    for pos, power in zip(room.lights, room.light_power):
        L = pos[None, :] - points  # [N, 3]
        d2 = np.einsum("ij,ij->i", L, L)
        cos = np.einsum("ij,ij->i", L, normals) / np.sqrt(d2)
        lit = cos > 0
        contrib = np.where(lit, power * cos / (LIGHT_SOFTENING**2 + d2), 0.0)
        if shadows and lit.any():
            idx = np.flatnonzero(lit)
            o = points[idx] + SHADOW_OFFSET * normals[idx]
            rays = np.concatenate([o, pos[None, :] - o], axis=1).astype(np.float32)
            occ = scene.test_occlusions(rays=o3d.core.Tensor(rays), tnear=0.0, tfar=0.999).numpy()
            contrib[idx[occ]] = 0.0
        E += contrib
    return E


def to_display(radiance: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear radiance -> display values: clip(exposure * x, 0, 1) ** (1 / 2.2)."""
    return np.clip(radiance * exposure, 0.0, 1.0) ** (1.0 / 2.2)


def render_view(room: Room, scene, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int,
                height: int, supersample: int = 2, shadows: bool = True,
                exposure: float = 1.0) -> View:
    """Render one view of ``room`` (``scene`` = ``room.mesh.raycasting_scene()``)."""
    K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"expected K [3, 3], R [3, 3], t [3], got {K.shape}, {R.shape}, {t.shape}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    origin = -R.T @ t  # camera centre, world

    # GT: one ray through each pixel centre (COLMAP convention: offset 0.5)
    d_cam = pixel_directions(K, width, height, np.array([[0.5, 0.5]]))[:, :, 0]  # [H, W, 3]
    hit = _cast(scene, origin, d_cam @ R)  # world dirs = R^T d, row form d @ R
    t_hit = hit["t_hit"]
    valid = np.isfinite(t_hit)
    depth = np.where(valid, t_hit, 0.0).astype(np.float32)  # |d_cam.z| = 1 -> t is z-depth
    n_cam = hit["primitive_normals"] @ R.T  # [H, W, 3]
    flip = np.einsum("hwc,hwc->hw", n_cam, d_cam) > 0
    n_cam = np.where(flip[..., None], -n_cam, n_cam)
    n_cam = np.where(valid[..., None], n_cam, 0.0).astype(np.float32)
    tri = np.where(valid, hit["primitive_ids"].astype(np.int64), -1)

    # colour: S x S sub-pixel rays, shaded in linear light, averaged, then gamma
    s = (np.arange(supersample) + 0.5) / supersample
    offsets = np.stack(np.meshgrid(s, s, indexing="xy"), axis=-1).reshape(-1, 2)  # [S*S, 2]
    dirs = pixel_directions(K, width, height, offsets) @ R  # [H, W, S*S, 3] world
    sub = _cast(scene, origin, dirs)
    ok = np.isfinite(sub["t_hit"]).reshape(-1)
    dirs = dirs.reshape(-1, 3)
    pts = origin[None, :] + sub["t_hit"].reshape(-1, 1)[ok] * dirs[ok]
    nrm = sub["primitive_normals"].reshape(-1, 3)[ok].astype(np.float64)
    nrm = np.where((np.einsum("ij,ij->i", nrm, dirs[ok]) > 0)[:, None], -nrm, nrm)
    tri_sub = sub["primitive_ids"].reshape(-1)[ok].astype(np.int64)
    rad = np.zeros((len(ok), 3))
    rad[ok] = albedo(room.mesh, tri_sub, pts) * lambert_shading(room, scene, pts, nrm, shadows)[:, None]
    rad = rad.reshape(height, width, -1, 3).mean(axis=2)
    image = to_display(rad, exposure).astype(np.float32)
    return View(image=image, depth=depth, normal=n_cam, triangle=tri)


def add_sensor_noise(image: np.ndarray, rng: np.random.Generator, std: float) -> np.ndarray:
    """Gaussian read noise of ``std`` (display units) and 8-bit quantisation -> uint8 [H, W, 3]."""
    noisy = image + (rng.normal(0.0, std, image.shape) if std > 0 else 0.0)
    return np.clip(np.round(noisy * 255.0), 0, 255).astype(np.uint8)
