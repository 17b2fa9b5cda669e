"""SIMULATED monocular depth and normal priors, made from the exact GT of a rendered view.

A monocular network's depth is right up to an unknown per-image affine map and is smooth where the
truth has edges; its normals are rounded at creases and slightly tilted. We simulate exactly these
errors, nothing else, and record every parameter in scene.json (``"priors": {"simulated": true}``).

Depth prior, in this order (all sizes in pixels scale with image width / 640):
  1. edge blur      d1 = G_sigma * d_gt (mask-normalised Gaussian; smooths discontinuities)
  2. warp           d2 = d1 * (1 + a_w * w(x, y)), w a smooth field from a coarse random grid
  3. noise          d3 = d2 * (1 + a_n * n(x, y)), n unit-variance noise blurred by 1 px
  4. affine         d_prior = s * d3 + b, s log-uniform in [s_lo, s_hi], b = f * median(d_gt) * s
so after undoing s and b the error is bounded by the blur at edges, a_w and a_n. The prior stays
positive (s > 0, b >= 0), i.e. affine-invariant depth as from MiDaS-style networks, not disparity.

Normal prior: G_sigma blur per component, plus a smooth tilt field of about ``normal_warp_deg``,
plus blurred per-pixel noise, renormalised and flipped to face the camera. Invalid (0) stays 0.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class PriorConfig:
    """Parameters of the SIMULATED monocular priors (pixel sizes are for 640 px wide images)."""

    depth_scale_min: float = 0.5
    """Smallest per-image scale s of the depth prior (log-uniform draw)."""
    depth_scale_max: float = 2.0
    """Largest per-image scale s of the depth prior."""
    depth_shift_max: float = 0.3
    """Largest per-image shift b as a fraction of s * median GT depth (uniform draw from 0)."""
    depth_edge_blur_px: float = 2.0
    """Gaussian sigma (px at 640 wide) blurring the depth, i.e. its discontinuities."""
    depth_warp: float = 0.04
    """Amplitude of the low-frequency multiplicative depth warp (fraction of depth)."""
    depth_warp_cells: int = 3
    """The warp field is bicubically upsampled from a grid of this many cells across the height."""
    depth_noise: float = 0.005
    """Standard deviation of the multiplicative per-pixel depth noise (fraction of depth)."""
    normal_blur_px: float = 3.0
    """Gaussian sigma (px at 640 wide) blurring the normals (rounds creases)."""
    normal_warp_deg: float = 3.0
    """Typical tilt (degrees) of the low-frequency normal error field."""
    normal_noise: float = 0.03
    """Standard deviation of the per-component normal noise before renormalising."""

    def to_dict(self) -> dict:
        return asdict(self)

    def validate(self) -> None:
        """ValueError naming an impossible setting (a min above its max was numpy's 'high - low < 0')."""
        if not 0 < self.depth_scale_min <= self.depth_scale_max < np.inf:
            raise ValueError(f"--priors.depth-scale-min must be > 0 and <= --priors.depth-scale-max, got "
                             f"{self.depth_scale_min} and {self.depth_scale_max}")
        for name, value in asdict(self).items():
            if name not in ("depth_scale_min", "depth_scale_max") and not 0 <= value < np.inf:
                raise ValueError(f"--priors.{name.replace('_', '-')} must be >= 0 and finite, got {value}")
        if self.depth_warp_cells < 1:
            raise ValueError(f"--priors.depth-warp-cells must be >= 1, got {self.depth_warp_cells}")
        if self.depth_warp >= 1 / 3:  # the warp field is clipped to 3 sigma: 1 - 3 w must stay > 0
            raise ValueError(f"--priors.depth-warp must be under 1/3 (a 3-sigma warp of the depth keeps it positive), "
                             f"got {self.depth_warp}")


def _blur(img: np.ndarray, sigma: float, mask: np.ndarray | None = None) -> np.ndarray:
    """Gaussian blur (reflecting borders); with ``mask`` a mask-normalised blur of valid pixels."""
    import cv2

    if sigma <= 0:
        return img.astype(np.float32)
    img = img.astype(np.float32)
    if mask is None:
        return cv2.GaussianBlur(img, ksize=(0, 0), sigmaX=sigma, borderType=cv2.BORDER_REFLECT)
    m = mask.astype(np.float32)
    num = cv2.GaussianBlur(img * (m if img.ndim == 2 else m[..., None]), ksize=(0, 0), sigmaX=sigma,
                           borderType=cv2.BORDER_REFLECT)
    den = cv2.GaussianBlur(m, ksize=(0, 0), sigmaX=sigma, borderType=cv2.BORDER_REFLECT)
    den = np.maximum(den, 1e-6)
    return num / (den if img.ndim == 2 else den[..., None])


def smooth_field(rng: np.random.Generator, height: int, width: int, cells: int,
                 channels: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Low-frequency field: a (cells+1) x (cells*W/H+1) grid of N(0, 1) values upsampled
    bicubically to [H, W] (or [H, W, C]); returns (field, grid)."""
    import cv2

    gh = cells + 1
    gw = max(2, int(round(cells * width / height)) + 1)
    grid = rng.normal(0.0, 1.0, (gh, gw, channels)).astype(np.float32)
    field = cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
    if field.ndim == 2:
        field = field[..., None]
    return (field[..., 0] if channels == 1 else field), grid


def _correlated_noise(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Unit-variance noise blurred by 1 px (networks do not make independent per-pixel errors)."""
    n = _blur(rng.normal(0.0, 1.0, shape).astype(np.float32), 1.0)
    return n / max(float(n.std()), 1e-6)


def simulate_depth_prior(depth: np.ndarray, rng: np.random.Generator, cfg: PriorConfig
                         ) -> tuple[np.ndarray, dict]:
    """Depth prior [H, W] float32 (0 where GT is invalid) and its per-image parameters.

    ``d_prior = s * (G * d_gt) * (1 + a_w w) * (1 + a_n n) + b`` (see the module docstring)."""
    if depth.ndim != 2:
        raise ValueError(f"depth must be [H, W], got shape {depth.shape}")
    H, W = depth.shape
    px = W / 640.0
    valid = depth > 0
    if not valid.any():
        raise ValueError("the GT depth map has no valid pixel")
    d = _blur(depth, cfg.depth_edge_blur_px * px, valid)
    warp, grid = smooth_field(rng, H, W, cfg.depth_warp_cells)
    d = d * (1.0 + cfg.depth_warp * np.clip(warp, -3, 3))
    d = d * (1.0 + cfg.depth_noise * _correlated_noise(rng, (H, W)))
    s = float(np.exp(rng.uniform(np.log(cfg.depth_scale_min), np.log(cfg.depth_scale_max))))
    b = float(rng.uniform(0.0, cfg.depth_shift_max) * s * np.median(depth[valid]))
    prior = np.where(valid, s * d + b, 0.0).astype(np.float32)
    params = {"scale": round(s, 8), "shift": round(b, 8), "warp_grid": grid[..., 0].round(5).tolist()}
    return prior, params


def simulate_normal_prior(normal: np.ndarray, rays: np.ndarray, rng: np.random.Generator,
                          cfg: PriorConfig) -> tuple[np.ndarray, dict]:
    """Normal prior [H, W, 3] float32 (camera frame, unit, facing the camera; 0 where invalid)
    from GT normals [H, W, 3] and the camera-frame pixel rays [H, W, 3]."""
    if normal.ndim != 3 or normal.shape[2] != 3 or rays.shape != normal.shape:
        raise ValueError(f"normal and rays must both be [H, W, 3], got {normal.shape} and {rays.shape}")
    H, W, _ = normal.shape
    valid = np.linalg.norm(normal, axis=-1) > 0.5
    n = _blur(normal, cfg.normal_blur_px * W / 640.0, valid)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    tilt, grid = smooth_field(rng, H, W, 2, channels=3)
    n = n + np.tan(np.radians(cfg.normal_warp_deg)) * tilt / np.sqrt(3.0)
    n = n + cfg.normal_noise * _correlated_noise(rng, (H, W, 3))
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    facing = np.einsum("hwc,hwc->hw", n, rays) > 0
    n = np.where(facing[..., None], -n, n)
    n = np.where(valid[..., None], n, 0.0).astype(np.float32)
    return n, {"tilt_grid": grid.round(5).tolist()}
