"""render(): project Gaussians, composite RGB + RaDe-GS depth + normal, return per-pixel maps.

Channels blended per Gaussian (one composite call, any backend):
    [r, g, b,  A, p_x, p_y,  n_x, n_y, n_z]   with   A = z - p . mean2d
so that the blended depth at a pixel centre q is  D(q) = sum_i w_i (A_i + p_i . q)
= A_blend + p_blend . q  exactly (RaDe-GS: each Gaussian's depth is a plane in pixel space).
The median depth uses the (A, p) of the Gaussian where transmittance crosses 0.5.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from splat import compiled
from splat.camera import Camera
from splat.composite import composite, resolve_backend
from splat.projection import ProjectionConfig, check_params, project_gaussians

log = logging.getLogger(__name__)

ALPHA_EPS = 1e-6  # below this accumulated alpha, depth and normal are reported as 0 (invalid)


def pixel_centres(width: int, height: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """[H, W, 2] (x, y) centres of the pixels: (j + 0.5, i + 0.5) (COLMAP convention)."""
    ys = torch.arange(height, device=device, dtype=dtype) + 0.5
    xs = torch.arange(width, device=device, dtype=dtype) + 0.5
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)


def plane_depth(offset: Tensor, slope: Tensor, centres: Tensor) -> Tensor:
    """Per-pixel depth of blended planes: D(q) = A + p . q  (IndoorGS §3.2, RaDe-GS).

    offset [H, W] = blended A = z - p . mean2d, slope [H, W, 2] blended p, centres [H, W, 2].
    """
    return offset + (slope * centres).sum(-1)


def pixel_maps(features: Tensor, median: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Depth, median depth and normal maps from the composited channels (see ``render``).

    features [H, W, 9] (rgb, plane A, p, normal sums), median [H, W, 3] (plane at T = 0.5), alpha
    [H, W]. Returns depth [H, W] (alpha-normalised plane depth, 0 where alpha <= ALPHA_EPS),
    median_depth [H, W] and normal [H, W, 3] (unit, 0 where the blended normal vanishes).
    """
    height, width = alpha.shape
    centres = pixel_centres(width, height, alpha.device, alpha.dtype)
    covered = alpha > ALPHA_EPS
    depth_acc = plane_depth(features[..., 3], features[..., 4:6], centres)
    depth = torch.where(covered, depth_acc / torch.where(covered, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(alpha))
    median_depth = plane_depth(median[..., 0], median[..., 1:3], centres)
    normal_acc = features[..., 6:9]
    norm2 = (normal_acc * normal_acc).sum(-1, keepdim=True)
    normal = torch.where(norm2 > 1e-12, normal_acc * torch.rsqrt(torch.clamp(norm2, min=1e-12)),
                         torch.zeros_like(normal_acc))
    return depth, median_depth, normal


def _background(background, dtype: torch.dtype, device: torch.device) -> Tensor:
    background = torch.as_tensor(background)  # a tuple or an array, as TrainConfig.background is
    if tuple(background.shape) != (3,):
        raise ValueError(f"background must have shape (3,), got {tuple(background.shape)}")
    return background.to(device=device, dtype=dtype)


def render(
    params: dict[str, Tensor],
    camera: Camera,
    *,
    sh_degree: int | None = None,
    backend: str = "auto",
    background: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    antialiased: bool = False,
    max_per_pixel: int = 256,
    maps: bool = True,
) -> dict[str, Tensor]:
    """Render one view of the Gaussians ``params`` (keys means, quats, scales, opacities, sh0, shN).

    ``backend`` picks the projection and compositing code: "torch" (reference, any device), "cpu"
    (C++ kernels, CPU tensors), "cuda" (CUDA projection and compositing kernels, float32 CUDA
    tensors; the projection falls back to torch when the camera requires grad), "auto" ("cpu" for
    CPU tensors, "cuda" for float32 CUDA tensors, when it builds; else "torch").

    Returns a dict (H, W = camera.height, camera.width):
      rgb [H, W, 3]           colour, background [3] (default black) blended behind
      depth [H, W]            expected z-depth in metres, NORMALISED by alpha (sum w d / sum w);
                              0 where alpha < 1e-6
      median_depth [H, W]     z-depth of the Gaussian where transmittance crosses 0.5; 0 if none
      normal [H, W, 3]        unit camera-frame normal facing the camera (blended, then normalised);
                              0 where undefined
      alpha [H, W]            accumulated opacity, 1 - T, in [0, 1]
      means2d [N, 2]          projected means (retain_grad() set when they require grad)
      radii [N] int32, visible [N] bool, n_contrib [H, W] int32

    ``max_per_pixel``: the most Gaussians composited per pixel, front to back, by the torch backend (its
    memory grows with it); the compiled backends composite every Gaussian until transmittance falls
    under 1e-4, so with more than this many translucent Gaussians on a pixel they differ (splat/composite.py).
    ``near``, ``far`` (metres, 0 < near < far): view-space depths outside are culled.

    ``maps=False`` composites the colour alone (3 channels, no median): rgb, alpha, means2d, radii,
    visible and n_contrib, the same values as with the maps; no depth, median_depth nor normal.
    With the Gaussians' geometry detached (``splat train --geometry-until``) its backward is the
    colours' alone.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a splat.camera.Camera, got {type(camera).__name__}")
    if isinstance(max_per_pixel, bool) or not isinstance(max_per_pixel, int) or max_per_pixel < 1:
        raise ValueError(f"max_per_pixel must be an int >= 1, got {max_per_pixel!r}")
    check_params(params)  # before any backend reads them: types, shapes, one dtype and device
    cfg = ProjectionConfig(near=near, far=far, eps2d=eps2d, antialiased=antialiased)
    if "means" in params:
        backend = resolve_backend(backend, params["means"].device, params["means"].dtype)
    if backend == "cuda" and "means" in params:  # fused CUDA projection (torch where it cannot)
        from splat.project_cuda import project_gaussians_cuda  # built with the compositing kernels

        proj = project_gaussians_cuda(params, camera, sh_degree=sh_degree, config=cfg)
    else:
        proj = project_gaussians(params, camera, sh_degree=sh_degree, config=cfg,
                                 backend="cpu" if backend == "cpu" else "torch")
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()  # for densification (accumulated screen-space gradients)
    dtype, device = means2d.dtype, means2d.device
    if not maps:
        bg = torch.zeros(3, dtype=dtype, device=device) if background is None else _background(background, dtype, device)
        out = composite(means2d, proj.conics, proj.opacities, proj.colors, proj.depths, proj.radii,
                        camera.width, camera.height, background=bg, backend=backend, max_per_pixel=max_per_pixel)
        return {"rgb": out.features, "alpha": out.alpha, "means2d": means2d, "radii": proj.radii,
                "visible": proj.radii > 0, "n_contrib": out.n_contrib}
    offset = proj.depths - (proj.depth_slopes * means2d).sum(-1)  # [N] A = z - p . mean2d
    plane = torch.cat([offset[:, None], proj.depth_slopes], -1)  # [N, 3]
    features = torch.cat([proj.colors, plane, proj.normals], -1)  # [N, 9]
    bg = torch.zeros(9, dtype=dtype, device=device)
    if background is not None:
        bg = torch.cat([_background(background, dtype, device), bg[3:]])
    out = composite(means2d, proj.conics, proj.opacities, features, proj.depths, proj.radii,
                    camera.width, camera.height, background=bg, median_features=plane,
                    backend=backend, max_per_pixel=max_per_pixel)
    if backend == "cuda" and compiled.applies(out.alpha):  # one fused kernel, not ~25 (splat/compiled.py)
        depth, median_depth, normal = compiled.call(pixel_maps, out.features, out.median, out.alpha)
    elif backend == "cpu" and out.features.shape[-1] >= 9:  # fused C++ pass (splat/maps_cpu.py)
        from splat.maps_cpu import pixel_maps_cpu

        depth, median_depth, normal = pixel_maps_cpu(out.features, out.median, out.alpha, ALPHA_EPS)
    else:
        depth, median_depth, normal = pixel_maps(out.features, out.median, out.alpha)
    return {
        "rgb": out.features[..., :3],
        "depth": depth,
        "median_depth": median_depth,
        "normal": normal,
        "alpha": out.alpha,
        "means2d": means2d,
        "radii": proj.radii,
        "visible": proj.radii > 0,
        "n_contrib": out.n_contrib,
    }
