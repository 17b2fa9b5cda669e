"""Loss terms fused on the CPU: SSIM of L_rgb, L_n and L_nc, values and analytic gradients in C++.

``ssim_mean(pred, gt)`` is ``evaluation.image_metrics.ssim_map(pred, gt).mean()`` (11 × 11 Gaussian
window, σ = 1.5, zero padding, as 3DGS), the torch oracle it is tested against in float64
(tests/test_losses_cpu.py). The kernel (``splat/csrc/losses_cpu.cpp``) computes the five local moments
in two passes over the image and keeps the three partial-derivative maps for the backward, which is
three blurs and one multiply-add per pixel — where torch's autograd runs ten convolutions forward,
their transposes backward, and a dozen full-size temporaries. It takes float32 and float64 CPU
tensors; the gradient flows to ``pred`` only. ``fused=False``, a CUDA tensor, a ``gt`` that needs
a gradient, or an extension that failed to build take the torch path.

``nc_loss(normal, depth, K, valid, detach_depth)`` is L_nc of splat/losses.py
(``depth_normal_consistency_loss``, its torch oracle, which calls it where :func:`fused_applies`):
one pass over the pixels forward, and a backward that recomputes each pixel's depth normal and
gathers the gradients of its four neighbours — where autograd keeps a dozen [H, W, 3] temporaries
of ``depth_to_normal`` and runs their backward one by one. ``normal_prior_loss_fused`` is L_n
(``normal_prior_loss``, its oracle): the mask, the L1 sum and its sign gradient in one pass each.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from evaluation.image_metrics import gaussian_window, ssim_map

log = logging.getLogger(__name__)

C1, C2 = 0.01**2, 0.03**2  # data range 1
_WINDOW = gaussian_window(11, 1.5, dtype=torch.float64)

_EXT: list = []  # [the extension or None], loaded on first use


def _ext():
    if not _EXT:
        try:
            from splat.cpu_ext import ext
        except ImportError as exc:  # the rasterizer warns about the failed build too
            log.warning("fused loss kernels unavailable (%s): torch's loss code is used", str(exc).splitlines()[0])
            ext = None
        _EXT.append(ext)
    return _EXT[0]


class _SSIMMeanCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor) -> Tensor:
        mean, d_mx, d_xx, d_xy = _ext().ssim_forward(pred, gt, _WINDOW, C1, C2)
        ctx.save_for_backward(pred, gt, d_mx, d_xx, d_xy)
        return mean

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        pred, gt, d_mx, d_xx, d_xy = ctx.saved_tensors
        return _ext().ssim_backward(grad.detach().to(torch.float64).cpu(), pred, gt, d_mx, d_xx, d_xy, _WINDOW), None


def fused_available() -> bool:
    """Whether the C++ extension (with the fused SSIM) is built and loaded."""
    return _ext() is not None


def ssim_mean(pred: Tensor, gt: Tensor, fused: bool = True) -> Tensor:
    """Mean SSIM of ``pred`` [H, W, C] against ``gt`` (same shape), a 0-dim tensor with a gradient
    to ``pred``; the fused C++ kernel where it applies (see the module), else the torch oracle."""
    if pred.dim() != 3 or pred.shape != gt.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must both be [H, W, C]")
    gt = gt.to(pred.dtype)
    if not fused or gt.requires_grad or not fused_applies(pred):
        return ssim_map(pred, gt).mean()
    return _SSIMMeanCPU.apply(pred.contiguous(), gt.contiguous())


def fused_applies(*tensors: Tensor) -> bool:
    """Whether the fused kernels take these tensors: float32/float64 on the CPU, extension built."""
    return (all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors)
            and _ext() is not None)


class _NCLossCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal: Tensor, depth: Tensor, valid: Tensor, intr: tuple, detach_depth: bool) -> Tensor:
        value, count = _ext().nc_forward(normal, depth, valid, *intr)
        ctx.save_for_backward(normal, depth, valid)
        ctx.intr, ctx.count, ctx.detach_depth = intr, int(count), detach_depth
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        normal, depth, valid = ctx.saved_tensors
        g_n, g_d = _ext().nc_backward(grad.detach().to(torch.float64).cpu(), normal, depth, valid, *ctx.intr,
                                      ctx.count, ctx.detach_depth)
        return g_n, (None if ctx.detach_depth else g_d), None, None, None


def nc_loss(normal: Tensor, depth: Tensor, K: Tensor, valid: Tensor, detach_depth: bool = False) -> Tensor:
    """L_nc by the C++ kernel (see the module; the caller checks :func:`fused_applies`). normal
    [H, W, 3], depth [H, W] of one dtype, K [3, 3], valid [H, W] bool. A 0-dim tensor."""
    k = K.detach().to(torch.float64).cpu()
    intr = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    return _NCLossCPU.apply(normal.contiguous(), depth.to(normal.dtype).contiguous(), valid.contiguous(), intr,
                            detach_depth)


class _NormalPriorCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
        value, count = _ext().normal_prior_forward(normal, prior, valid)
        ctx.save_for_backward(normal, prior, valid)
        ctx.count = int(count)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        normal, prior, valid = ctx.saved_tensors
        return _ext().normal_prior_backward(grad.detach().to(torch.float64).cpu(), normal, prior, valid,
                                            ctx.count), None, None


def normal_prior_loss_fused(normal: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
    """L_n by the C++ kernel (the caller checks :func:`fused_applies`); gradient to ``normal`` only."""
    return _NormalPriorCPU.apply(normal.contiguous(), prior.to(normal.dtype).contiguous(), valid.contiguous())
