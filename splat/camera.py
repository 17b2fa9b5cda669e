"""Pinhole camera for the rasterizer: intrinsics, world-to-camera pose, image size (torch).

Conventions (docs/conventions.md): world-to-camera OpenCV axes (x right, y down, z forward),
``x_cam = R @ x_world + t``; COLMAP pixel centres, ``u = fx * x / z + cx`` puts the centre of pixel
(row i, col j) at (j + 0.5, i + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


def check_pinhole(K, world_to_cam, where: str) -> tuple[np.ndarray, np.ndarray]:
    """K [3, 3] a pinhole (finite, fx, fy > 0, zero skew, last row 0 0 1) and world_to_cam [4, 4] a
    rigid transform (finite, last row 0 0 0 1, a proper rotation to 1e-4): the two as float64 arrays,
    else ValueError naming ``where``. The rasterizer and the TSDF read fx, fy, cx, cy and R, t only,
    so anything else would be dropped in silence (a scaled R scales every depth)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"{where}: K must be [3, 3], got shape {K.shape}")
    if not np.isfinite(K).all() or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{where}: K must be finite with fx, fy > 0, got {K.tolist()}")
    if K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"{where}: K must be a pinhole [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                         f"(skew is not rendered), got {K.tolist()}")
    T = np.asarray(world_to_cam, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{where}: world_to_cam must be [4, 4], got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"{where}: world_to_cam has non-finite entries: {T.tolist()}")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"{where}: world_to_cam's last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise ValueError(f"{where}: world_to_cam's rotation is not a rotation (R R^T != I or det < 0)")
    return K, T


def _size(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float, np.floating)) \
            or not np.isfinite(value) or int(value) != value or value <= 0:
        raise ValueError(f"Camera {name} must be a positive whole number of pixels, got {value!r}")
    return int(value)


@dataclass
class Camera:
    """One view: K [3, 3] and viewmat [4, 4] (world-to-camera) as float32 tensors, size in pixels.

    Build it with :meth:`from_Rt` (checks K and the pose) or directly from tensors. ``center`` is
    the camera centre the projection uses (kept in float64 precision from ``from_Rt``); a given
    ``center`` must agree with ``viewmat``, so ``dataclasses.replace(cam, viewmat=...)`` needs
    ``center=None`` (recomputed). On the CPU a direct construction checks K and the pose as
    ``from_Rt`` does; tensors on a GPU or requiring grad are not read back (no host sync per step).
    Do not edit ``viewmat`` in place: build a new camera."""

    K: Tensor  # [3, 3] float32 intrinsics (fx, fy, cx, cy; zero skew)
    viewmat: Tensor  # [4, 4] float32 world-to-camera, last row (0, 0, 0, 1)
    width: int  # image width in pixels
    height: int  # image height in pixels
    center: Tensor | None = None  # [3] float32 camera centre in world; computed in float64 if None

    def __post_init__(self) -> None:
        for name in ("K", "viewmat") + (("center",) if self.center is not None else ()):
            if not isinstance(getattr(self, name), Tensor):
                raise TypeError(f"Camera {name} must be a torch.Tensor, got {type(getattr(self, name)).__name__} "
                                f"(Camera.from_Rt takes array-likes)")
        if tuple(self.K.shape) != (3, 3):
            raise ValueError(f"K must have shape (3, 3), got {tuple(self.K.shape)}")
        if tuple(self.viewmat.shape) != (4, 4):
            raise ValueError(f"viewmat must have shape (4, 4), got {tuple(self.viewmat.shape)}")
        self.width, self.height = _size(self.width, "width"), _size(self.height, "height")
        if self.center is not None and tuple(self.center.shape) != (3,):
            raise ValueError(f"center must have shape (3,), got {tuple(self.center.shape)}")
        tensors = (self.K, self.viewmat) + ((self.center,) if self.center is not None else ())
        if all(t.device.type == "cpu" and not t.requires_grad for t in tensors):
            _, T = check_pinhole(self.K.numpy(), self.viewmat.numpy(), "Camera")
            if self.center is not None:  # the projection uses it, not viewmat's t: they must agree
                C = -T[:3, :3].T @ T[:3, 3]
                if np.abs(self.center.numpy().astype(np.float64) - C).max() > 1e-5 * (1.0 + np.abs(T[:3, 3]).max()):
                    raise ValueError(f"Camera center {self.center.tolist()} disagrees with viewmat's "
                                     f"-R^T t = {C.tolist()}: pass center=None to compute it from viewmat")
        if self.center is None:
            # C = -R^T t in float64: far-from-origin scenes (1e4 m) keep their precision this way.
            vm = self.viewmat.detach().to(torch.float64)
            self.center = (-(vm[:3, :3].T @ vm[:3, 3])).to(self.viewmat.dtype)

    @classmethod
    def _derived(cls, K: Tensor, viewmat: Tensor, width: int, height: int, center: Tensor) -> "Camera":
        """A camera made from a checked one (another device or dtype, a smaller image): built without
        its checks again, which the projection would otherwise pay on every render (~70 us)."""
        cam = object.__new__(cls)
        cam.K, cam.viewmat, cam.width, cam.height, cam.center = K, viewmat, int(width), int(height), center
        return cam

    @property
    def R(self) -> Tensor:
        """[3, 3] world-to-camera rotation."""
        return self.viewmat[:3, :3]

    @property
    def t(self) -> Tensor:
        """[3] world-to-camera translation."""
        return self.viewmat[:3, 3]

    @property
    def device(self) -> torch.device:
        return self.viewmat.device

    def to(self, device: torch.device | str) -> "Camera":
        """A copy with every tensor on ``device``."""
        return Camera._derived(self.K.to(device), self.viewmat.to(device), self.width, self.height,
                               self.center.to(device))

    @classmethod
    def from_Rt(cls, K, R, t, width: int, height: int, device: torch.device | str = "cpu") -> "Camera":
        """Build from array-likes K [3, 3], R [3, 3], t [3] (world-to-camera, OpenCV)."""
        K64 = np.asarray(K, dtype=np.float64)
        R64 = np.asarray(R, dtype=np.float64)
        t64 = np.asarray(t, dtype=np.float64).reshape(-1)
        if K64.shape != (3, 3) or R64.shape != (3, 3) or t64.shape != (3,):
            raise ValueError(f"expected K (3, 3), R (3, 3), t (3,), got {K64.shape}, {R64.shape}, {t64.shape}")
        vm = np.eye(4)
        vm[:3, :3], vm[:3, 3] = R64, t64
        check_pinhole(K64, vm, "Camera.from_Rt")
        width, height = _size(width, "width"), _size(height, "height")
        center = -R64.T @ t64
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
        return cls(K=as_t(K64), viewmat=as_t(vm), width=int(width), height=int(height), center=as_t(center))

    @classmethod
    def from_scene_camera(cls, cam, device: torch.device | str = "cpu") -> "Camera":
        """From any object with numpy attributes K (3x3), R (3x3), t (3,), width, height
        (e.g. ``geocues.scene.Camera``)."""
        for name in ("K", "R", "t", "width", "height"):
            if not hasattr(cam, name):
                raise ValueError(f"scene camera {type(cam).__name__} has no attribute {name!r}")
        return cls.from_Rt(cam.K, cam.R, cam.t, cam.width, cam.height, device=device)

    def scaled(self, factor: float) -> "Camera":
        """The same view with an image ``factor`` times smaller (fx, fy, cx, cy divided exactly)."""
        if factor <= 0:
            raise ValueError(f"scale factor must be positive, got {factor}")
        K = self.K.clone()
        K[:2] = K[:2] / factor
        width, height = round(self.width / factor), round(self.height / factor)
        if min(width, height) < 1:
            raise ValueError(f"scale factor {factor} leaves a {self.width}x{self.height} image no pixel")
        return Camera._derived(K, self.viewmat, width, height, self.center)
