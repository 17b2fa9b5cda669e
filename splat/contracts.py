"""Types and input checks shared by the backend dispatchers (splat/projection.py, splat/composite.py)
and their backends (project_cpu, composite_torch, composite_cpu, the CUDA modules), so that a backend
never imports its dispatcher — gsplat's split of ``_backend``, ``_wrapper`` and ``_torch_impl``.
The dispatchers re-export every name here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from torch import Tensor


@dataclass
class ProjectionConfig:
    """Options of the EWA projection."""

    near: float = 0.01
    """Gaussians with view-space z at or below this (metres) are culled."""
    far: float = 1e10
    """Gaussians with view-space z at or beyond this (metres) are culled."""
    eps2d: float = 0.3
    """Low-pass filter added to the 2D covariance diagonal, in pixels^2 (3DGS)."""
    antialiased: bool = False
    """Scale opacity by sqrt(det(cov2d) / det(cov2d + eps2d I)) (Mip-Splatting / gsplat 'antialiased')."""
    min_plane_cos: float = 0.01
    """Clamp of cos(view ray, plane normal) in the depth-plane slope (edge-on Gaussians)."""

    def __post_init__(self) -> None:
        if not 0 < self.near < self.far:  # a blank image otherwise, with no word
            raise ValueError(f"near and far must satisfy 0 < near < far, got near={self.near}, far={self.far}")
        if not self.eps2d >= 0:
            raise ValueError(f"eps2d must be >= 0, got {self.eps2d}")


class Projected(NamedTuple):
    """Per-Gaussian image-space quantities for one view (N = all Gaussians; culled have radii 0)."""

    means2d: Tensor  # [N, 2] pixel coordinates (COLMAP centres)
    conics: Tensor  # [N, 3] (a, b, c) inverse of the low-passed 2D covariance
    depths: Tensor  # [N] view-space z in metres (1.0 stand-in where culled by depth)
    radii: Tensor  # [N] int32 pixel radius, 0 = culled
    opacities: Tensor  # [N] in (0, 1)
    colors: Tensor  # [N, 3] SH colour for this view
    depth_slopes: Tensor  # [N, 2] d(depth)/d(pixel x, pixel y) of the RaDe-GS depth plane
    normals: Tensor  # [N, 3] unit camera-frame normal facing the camera (0 if undefined)


class CompositeOut(NamedTuple):
    """What a compositing backend returns for one view."""

    features: Tensor  # [H, W, C] blended channels, background included
    alpha: Tensor  # [H, W] 1 - final transmittance, in [0, 1]
    median: Tensor | None  # [H, W, M] median_features of the Gaussian where T crosses 0.5 (0 if none)
    n_contrib: Tensor  # [H, W] int32 number of Gaussians blended at the pixel


def check_composite_inputs(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    background: Tensor | None,
    median_features: Tensor | None,
) -> None:
    """Raise ValueError with expected vs actual shapes when the inputs do not fit the contract."""
    if features.dim() != 2:
        raise ValueError(f"features must be [N, C], got shape {tuple(features.shape)}")
    n, c = features.shape
    expected = {
        "means2d": (means2d, (n, 2)),
        "conics": (conics, (n, 3)),
        "opacities": (opacities, (n,)),
        "depths": (depths, (n,)),
        "radii": (radii, (n,)),
    }
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {tuple(tensor.shape)}")
    if background is not None and tuple(background.shape) != (c,):
        raise ValueError(f"background must have shape ({c},), got {tuple(background.shape)}")
    if median_features is not None and (median_features.dim() != 2 or median_features.shape[0] != n):
        raise ValueError(f"median_features must be [{n}, M], got {tuple(median_features.shape)}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"image size must be positive, got width={width}, height={height}")
