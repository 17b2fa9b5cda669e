"""Fused C++ projection (``csrc/project_cpu.cpp``): the ``cpu`` backend's projection stage.

:func:`project_gaussians_cpu` returns exactly what :func:`splat.projection.project_gaussians`
returns (the torch code is the reference and the oracle: tests compare values and gradients), but
in one pass over the Gaussians per direction instead of ~150 torch operations on [N]-sized tensors,
whose per-operation cost (allocation, OpenMP wake-up) dominated the CPU iteration. The backward is
analytic, with torch's conventions at non-differentiable points (see the C++ header comment).

Gradients flow to every Gaussian parameter (means, quats, scales, opacities, sh0, shN; to sh0 and
shN alone, without the geometry's chain, when none of the others needs one), not to the camera:
when the camera's tensors require grad, :func:`splat.projection.project_gaussians` uses the torch
path instead.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from splat.camera import Camera
from splat.cpu_ext import ext as _ext
from splat.contracts import Projected, ProjectionConfig


class _ProjectCPU(torch.autograd.Function):
    """Autograd wrapper: forward and analytic backward both in C++."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh0, shN, R, C, K, options):
        outs = _ext.project_forward(means, quats, scales, opacities, sh0, shN, R, C, K, *options)
        radii = outs[3]
        ctx.save_for_backward(means, quats, scales, opacities, sh0, shN, R, C, K, radii)
        ctx.options = options
        ctx.mark_non_differentiable(radii)
        if not any(ctx.needs_input_grad[:4]):  # a frozen geometry: only the colours carry a gradient on
            ctx.mark_non_differentiable(*(t for k, t in enumerate(outs) if k != 5))
        return tuple(outs)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_m2, g_con, g_z, _g_rad, g_op, g_col, g_sl, g_nrm):
        means, quats, scales, opacities, sh0, shN, R, C, K, radii = ctx.saved_tensors
        geometry = any(ctx.needs_input_grad[:4])  # else the colours' chain alone (a frozen geometry)
        grads = _ext.project_backward(
            means, quats, scales, opacities, sh0, shN, R, C, K, radii, g_m2.contiguous(),
            g_con.contiguous(), g_z.contiguous(), g_op.contiguous(), g_col.contiguous(),
            g_sl.contiguous(), g_nrm.contiguous(), *ctx.options, geometry)
        if not geometry:
            grads = (None, None, None, None, *grads[4:])
        return (*grads, None, None, None, None)


def project_gaussians_cpu(params: dict[str, Tensor], camera: Camera, sh_degree: int,
                          config: ProjectionConfig) -> Projected:
    """Project with the C++ kernel; ``params`` already checked (CPU, one float dtype)."""
    means = params["means"]
    dtype = means.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the cpu projection needs float32 or float64 Gaussians, got {dtype}")
    tensors = [params[k] for k in ("means", "quats", "scales", "opacities", "sh0", "shN")]
    for key, t in zip(("means", "quats", "scales", "opacities", "sh0", "shN"), tensors):
        if t.device.type != "cpu" or t.dtype != dtype:
            raise ValueError(f"params[{key!r}] must be a CPU {dtype} tensor (as means), "
                             f"got {t.device} {t.dtype}")
    cam = [camera.R, camera.center, camera.K]
    cam = [t.detach().to(dtype=dtype).contiguous() for t in cam]
    options = (camera.width, camera.height, float(config.near), float(config.far), float(config.eps2d),
               float(config.min_plane_cos), bool(config.antialiased), int(sh_degree))
    m2, conics, depths, radii, opac, colors, slopes, normals = _ProjectCPU.apply(
        *[t.contiguous() for t in tensors], *cam, options)
    return Projected(means2d=m2, conics=conics, depths=depths, radii=radii, opacities=opac,
                     colors=colors, depth_slopes=slopes, normals=normals)
