"""Which surface points a set of cameras saw: frustum and occlusion tests for mesh evaluation.

The MonoSDF / GO-Surf protocols cull the predicted mesh to the ground-truth cameras' view frusta
(MonoSDF ``cull_mesh.py``) and optionally drop what those cameras cannot see behind other surfaces
(GO-Surf ``frustum_culling.py``, with depth maps rendered from a mesh). Here the test is applied to
*points sampled on the surface* (see ``evaluation.mesh_metrics``), which makes it independent of
the mesh's tessellation (GO-Surf subdivides the mesh to 1.5 cm edges for the same reason), and the
occlusion test casts one exact ray per (point, camera) with Open3D's ``RaycastingScene`` instead of
looking the point up in a rendered depth map.

Conventions (docs/conventions.md): world-to-camera OpenCV cameras, ``x_cam = R @ x_world + t``;
COLMAP pixels, so an image of width W and height H covers ``0 <= u < W, 0 <= v < H``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import open3d as o3d

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraSet:
    """A stack of pinhole cameras (world-to-camera, OpenCV axes, COLMAP pixel convention)."""

    K: np.ndarray  # [C, 3, 3] intrinsics
    R: np.ndarray  # [C, 3, 3] world-to-camera rotations
    t: np.ndarray  # [C, 3] world-to-camera translations
    width: np.ndarray  # [C] image widths in pixels
    height: np.ndarray  # [C] image heights in pixels

    def __post_init__(self) -> None:
        c = len(self.K)
        expected = {"K": (c, 3, 3), "R": (c, 3, 3), "t": (c, 3), "width": (c,), "height": (c,)}
        for name, shape in expected.items():
            actual = np.shape(getattr(self, name))
            if actual != shape:
                raise ValueError(f"CameraSet.{name}: expected shape {shape}, got {actual}")
        if c == 0:
            raise ValueError("CameraSet: no cameras")
        if not (np.all(self.width > 0) and np.all(self.height > 0)):
            raise ValueError("CameraSet: image width and height must be positive")

    def __len__(self) -> int:
        return len(self.K)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in world coordinates, ``-R^T t``."""
        return -np.einsum("cji,cj->ci", self.R, self.t)  # [C, 3]

    @classmethod
    def from_cameras(cls, cameras: Sequence[Any], max_cameras: int = 0) -> "CameraSet":
        """Stack objects with attributes ``K, R, t, width, height`` (e.g. ``geocues.scene.Camera``).

        ``max_cameras > 0`` keeps that many cameras, evenly spread over the sequence.
        """
        cameras = list(cameras)
        if not cameras:
            raise ValueError("no cameras given for culling")
        for i, cam in enumerate(cameras):
            missing = [a for a in ("K", "R", "t", "width", "height") if not hasattr(cam, a)]
            if missing:
                raise ValueError(f"camera {i} ({type(cam).__name__}) lacks attributes {missing}")
        if max_cameras > 0 and len(cameras) > max_cameras:
            keep = np.linspace(0, len(cameras) - 1, max_cameras).round().astype(int)
            cameras = [cameras[i] for i in np.unique(keep)]
        return cls(
            K=np.stack([np.asarray(c.K, dtype=np.float64).reshape(3, 3) for c in cameras]),
            R=np.stack([np.asarray(c.R, dtype=np.float64).reshape(3, 3) for c in cameras]),
            t=np.stack([np.asarray(c.t, dtype=np.float64).reshape(3) for c in cameras]),
            width=np.array([int(c.width) for c in cameras]),
            height=np.array([int(c.height) for c in cameras]),
        )


def in_frustum(points: np.ndarray, cams: CameraSet, index: int, near: float = 1e-4) -> np.ndarray:
    """Points that project inside image ``index`` in front of its camera.

    points: [N, 3] world coordinates in metres. Returns a bool mask [N]. A point is inside when its
    camera-frame depth exceeds ``near`` and its pixel position (COLMAP convention) satisfies
    ``0 <= u < width`` and ``0 <= v < height``.
    """
    x_cam = points @ cams.R[index].T + cams.t[index]  # [N, 3]
    z = x_cam[:, 2]
    front = z > near
    uvw = x_cam @ cams.K[index].T  # [N, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = uvw[:, 0] / z
        v = uvw[:, 1] / z
    return front & (u >= 0) & (u < cams.width[index]) & (v >= 0) & (v < cams.height[index])


def raycasting_scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An Open3D ``RaycastingScene`` holding one triangle mesh (vertices [V, 3], faces [F, 3])."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        vertex_positions=o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        triangle_indices=o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
    )
    return scene


def unoccluded(points: np.ndarray, center: np.ndarray, occluder: o3d.t.geometry.RaycastingScene,
               tolerance: float) -> np.ndarray:
    """Points not hidden from ``center`` by the occluder surface by more than ``tolerance`` metres.

    One ray per point, from the camera centre towards the point (direction = point - centre, so
    the hit parameter is a fraction of the way): the point is visible when the first hit lies no
    closer than ``|point - centre| - tolerance`` along the ray (or there is no hit).
    Returns a bool mask [N].
    """
    d = points - center[None]  # [N, 3]
    length = np.linalg.norm(d, axis=1)  # [N]
    rays = np.concatenate([np.broadcast_to(center, d.shape), d], axis=1).astype(np.float32)  # [N, 6]
    t_hit = occluder.cast_rays(rays=o3d.core.Tensor(rays))["t_hit"].numpy()  # [N], inf = no hit
    return t_hit * length >= length - tolerance


def visible_mask(points: np.ndarray, cams: CameraSet,
                 occluder: o3d.t.geometry.RaycastingScene | None = None,
                 tolerance: float = 0.02) -> np.ndarray:
    """Points seen by at least one camera: inside its frustum and, with an occluder, not hidden.

    points: [N, 3] world coordinates. occluder: a ``RaycastingScene`` of the surface that may hide
    points (the GT mesh, or the points' own mesh), or None for the frustum test only. tolerance:
    how far (metres, along the viewing ray) a point may lie behind the occluder and still count as
    seen. Returns a bool mask [N].
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points: expected shape [N, 3], got {points.shape}")
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    seen = np.zeros(len(points), dtype=bool)
    centers = cams.centers  # [C, 3]
    for i in range(len(cams)):
        todo = np.flatnonzero(~seen)  # points already seen need no further test
        if todo.size == 0:
            break
        inside = in_frustum(points[todo], cams, i)
        cand = todo[inside]
        if cand.size == 0:
            continue
        if occluder is not None:
            cand = cand[unoccluded(points[cand], centers[i], occluder, tolerance)]
        seen[cand] = True
    return seen


def bounds_mask(points: np.ndarray, lower: np.ndarray, upper: np.ndarray, margin: float) -> np.ndarray:
    """Points inside the axis-aligned box ``[lower - margin, upper + margin]`` (bool mask [N])."""
    lo = np.asarray(lower, dtype=np.float64) - margin
    hi = np.asarray(upper, dtype=np.float64) + margin
    return np.all((points >= lo) & (points <= hi), axis=1)
