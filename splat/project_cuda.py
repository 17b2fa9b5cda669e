"""Fused CUDA projection (``csrc/project_cuda.cu``): the ``cuda`` backend's projection stage.

:func:`project_gaussians_cuda` returns what :func:`splat.projection.project_gaussians` returns (the
torch code is the reference and the oracle: tests/test_project_cuda.py compares values and
gradients), computed by one kernel per direction with one thread per Gaussian instead of ~150
small torch operations per direction, whose launches dominated the GPU iteration. The kernels are
the per-Gaussian code of the ``cpu`` backend's ``csrc/project_cpu.cpp`` (same math, culling and
torch's gradient conventions), float32 only; a call makes no host-device copy.

Gradients flow to every Gaussian parameter (means, quats, scales, opacities, sh0, shN), not to the
camera. :func:`project_gaussians_cuda` uses the torch projection instead when the camera's tensors
require grad or the Gaussians are not all float32 tensors on one CUDA device.

Importing this module builds the CUDA extension (:mod:`splat.cuda_ext`, shared with the compositing
kernels); :func:`splat.rasterize.render` imports it only once the ``cuda`` compositing backend has
been resolved, i.e. built.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from splat.camera import Camera
from splat.cuda_ext import ext as _ext
from splat.projection import PARAM_KEYS, Projected, ProjectionConfig, check_params, project_gaussians
from splat.sh import num_sh_bases, sh_degree_of


class _ProjectCUDA(torch.autograd.Function):
    """Autograd wrapper: forward and analytic backward both in CUDA."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh0, shN, R, C, K, options):
        outs = _ext.project_forward(means, quats, scales, opacities, sh0, shN, R, C, K, *options)
        radii = outs[3]
        ctx.save_for_backward(means, quats, scales, opacities, sh0, shN, R, C, K, radii)
        ctx.options = options
        ctx.mark_non_differentiable(radii)
        return tuple(outs)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_m2, g_con, g_z, _g_rad, g_op, g_col, g_sl, g_nrm):
        means, quats, scales, opacities, sh0, shN, R, C, K, radii = ctx.saved_tensors
        grads = _ext.project_backward(
            means, quats, scales, opacities, sh0, shN, R, C, K, radii, g_m2.contiguous(),
            g_con.contiguous(), g_z.contiguous(), g_op.contiguous(), g_col.contiguous(),
            g_sl.contiguous(), g_nrm.contiguous(), *ctx.options)
        return (*grads, None, None, None, None)


def cuda_projection_applies(params: dict[str, Tensor], camera: Camera) -> bool:
    """True when the kernels can project ``params``: all float32 on one CUDA device, camera without grad."""
    device = params["means"].device
    if device.type != "cuda":
        return False
    if any(params[k].dtype != torch.float32 or params[k].device != device for k in PARAM_KEYS):
        return False
    return not any(t is not None and t.requires_grad for t in (camera.K, camera.viewmat, camera.center))


def project_gaussians_cuda(params: dict[str, Tensor], camera: Camera, *, sh_degree: int | None = None,
                           config: ProjectionConfig | None = None) -> Projected:
    """:func:`splat.projection.project_gaussians` with the CUDA kernels (torch where they do not apply)."""
    cfg = config or ProjectionConfig()
    check_params(params)
    if sh_degree is None:
        sh_degree = sh_degree_of(params["shN"])
    elif num_sh_bases(sh_degree) > params["shN"].shape[1] + 1:
        raise ValueError(f"SH degree {sh_degree} needs {num_sh_bases(sh_degree)} coefficients, "
                         f"have {params['shN'].shape[1] + 1}")
    if not cuda_projection_applies(params, camera):
        return project_gaussians(params, camera, sh_degree=sh_degree, config=cfg, backend="torch")
    device = params["means"].device
    cam = [t.detach().to(device=device, dtype=torch.float32).contiguous()
           for t in (camera.R, camera.center, camera.K)]
    options = (int(camera.width), int(camera.height), float(cfg.near), float(cfg.far), float(cfg.eps2d),
               float(cfg.min_plane_cos), bool(cfg.antialiased), int(sh_degree))
    m2, conics, depths, radii, opac, colors, slopes, normals = _ProjectCUDA.apply(
        *[params[k].contiguous() for k in PARAM_KEYS], *cam, options)
    return Projected(means2d=m2, conics=conics, depths=depths, radii=radii, opacities=opac,
                     colors=colors, depth_slopes=slopes, normals=normals)
