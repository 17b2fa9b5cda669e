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


@dataclass
class Camera:
    """One view: K [3, 3] and viewmat [4, 4] (world-to-camera) as float32 tensors, size in pixels."""

    K: Tensor  # [3, 3] float32 intrinsics (fx, fy, cx, cy; zero skew)
    viewmat: Tensor  # [4, 4] float32 world-to-camera, last row (0, 0, 0, 1)
    width: int  # image width in pixels
    height: int  # image height in pixels
    center: Tensor | None = None  # [3] float32 camera centre in world; computed in float64 if None

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3):
            raise ValueError(f"K must have shape (3, 3), got {tuple(self.K.shape)}")
        if tuple(self.viewmat.shape) != (4, 4):
            raise ValueError(f"viewmat must have shape (4, 4), got {tuple(self.viewmat.shape)}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)
        if self.center is None:
            # C = -R^T t in float64: far-from-origin scenes (1e4 m) keep their precision this way.
            vm = self.viewmat.detach().to(torch.float64)
            self.center = (-(vm[:3, :3].T @ vm[:3, 3])).to(self.viewmat.dtype)
        elif tuple(self.center.shape) != (3,):
            raise ValueError(f"center must have shape (3,), got {tuple(self.center.shape)}")

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
        return Camera(K=self.K.to(device), viewmat=self.viewmat.to(device), width=self.width,
                      height=self.height, center=self.center.to(device))

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
        return Camera(K=K, viewmat=self.viewmat, width=round(self.width / factor),
                      height=round(self.height / factor), center=self.center)
