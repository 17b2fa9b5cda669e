"""Loss terms fused on a CUDA GPU: L_rgb (L1 + SSIM), L_n and L_nc, values and analytic gradients.

The kernels (``splat/csrc/losses_cuda.cu``, in the extension :mod:`splat.cuda_ext` builds) are the
GPU ports of splat/losses_cpu.py's, and the torch code of splat/losses.py is their oracle
(``rgb_loss``'s 3DGS SSIM: 11 × 11 Gaussian window, σ = 1.5, zero padding;
``normal_prior_loss``; ``depth_normal_consistency_loss``), tested in float64 and float32 on the
GPU (tests/test_losses_cuda.py, skipped without CUDA). Why: on a GPU the torch loss code of one
training step is a few hundred element-wise kernels of microseconds each, launched one by one from
Python (docs/rasterizer.md); here L_rgb is three kernels forward and two backward, L_nc two and
two, L_n two and one. The loss values and pixel counts stay on the device (float64 accumulators),
so no term waits for the GPU. Gradients are not bitwise reproducible from run to run (the per-block
sums are added atomically), as the compositing kernels' are not.

:func:`applies` says whether tensors can take them: float32 or float64 CUDA tensors and an
extension that builds (the first call builds it; a failed build logs one warning and the torch code
runs from then on). splat/losses.py calls them under ``LossConfig.kernels = "fused"`` (the
default); ``"torch"`` keeps the oracle, as on the CPU.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from evaluation.image_metrics import gaussian_window

log = logging.getLogger(__name__)

C1, C2 = 0.01**2, 0.03**2  # data range 1, as splat/losses_cpu.py
_WINDOW = gaussian_window(11, 1.5, dtype=torch.float64)  # a CPU tensor: the kernels take it by value

_EXT: list = []  # [the extension or None], loaded on first use


def _ext():
    if not _EXT:
        try:
            from splat.cuda_ext import ext
        except ImportError as exc:  # splat.composite warns about the failed build too
            log.warning("fused CUDA loss kernels unavailable (%s): torch's loss code is used",
                        str(exc).splitlines()[0])
            ext = None
        _EXT.append(ext)
    return _EXT[0]


def applies(*tensors: Tensor) -> bool:
    """Whether the fused CUDA kernels take these tensors: float32/float64 on one CUDA device, built."""
    if not tensors or any(t.device.type != "cuda" for t in tensors):
        return False
    if any(t.device != tensors[0].device for t in tensors):
        return False
    if any(t.is_floating_point() and t.dtype not in (torch.float32, torch.float64) for t in tensors):
        return False
    return _ext() is not None


def _grad_like(grad: Tensor, like: Tensor) -> Tensor:
    """The upstream gradient as a 0-dim tensor of ``like``'s dtype on its device (no host copy)."""
    return grad.detach().to(device=like.device, dtype=like.dtype).reshape(()).contiguous()


class _RGBLossCUDA(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor, lambda_dssim: float) -> Tensor:
        value, d_mx, d_xx, d_xy = _ext().rgb_loss_forward(pred, gt, _WINDOW, C1, C2, lambda_dssim)
        ctx.save_for_backward(pred, gt, d_mx, d_xx, d_xy)
        ctx.lambda_dssim = lambda_dssim
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        pred, gt, d_mx, d_xx, d_xy = ctx.saved_tensors
        g = _ext().rgb_loss_backward(_grad_like(grad, pred), pred, gt, d_mx, d_xx, d_xy, _WINDOW, ctx.lambda_dssim)
        return g, None, None


def rgb_loss(pred: Tensor, gt: Tensor, lambda_dssim: float) -> Tensor:
    """L_rgb = (1 − λ) L1 + λ (1 − SSIM) of ``pred`` [H, W, C] against ``gt`` (same shape and dtype,
    no gradient) by the CUDA kernels (the caller checks :func:`applies`). A 0-dim tensor on the GPU."""
    if pred.dim() != 3 or pred.shape != gt.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must both be [H, W, C]")
    return _RGBLossCUDA.apply(pred.contiguous(), gt.detach().to(pred.dtype).contiguous(), float(lambda_dssim))


class _NCLossCUDA(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal: Tensor, depth: Tensor, valid: Tensor, K: Tensor, detach_depth: bool) -> Tensor:
        value, acc = _ext().nc_loss_forward(normal, depth, valid, K)
        ctx.save_for_backward(normal, depth, valid, acc, K)
        ctx.detach_depth = detach_depth
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        normal, depth, valid, acc, K = ctx.saved_tensors
        g_n, g_d = _ext().nc_loss_backward(_grad_like(grad, normal), normal, depth, valid, acc, K, ctx.detach_depth)
        return g_n, (None if ctx.detach_depth else g_d), None, None, None


def nc_loss(normal: Tensor, depth: Tensor, K: Tensor, valid: Tensor, detach_depth: bool = False) -> Tensor:
    """L_nc by the CUDA kernels (the caller checks :func:`applies`). normal [H, W, 3], depth [H, W] of
    one dtype, K [3, 3] (the kernels read it on the device: no host copy), valid [H, W] bool. A 0-dim
    tensor; no gradient to K."""
    k = K.detach().to(device=normal.device, dtype=normal.dtype).contiguous()
    return _NCLossCUDA.apply(normal.contiguous(), depth.to(normal.dtype).contiguous(), valid.contiguous(), k,
                             detach_depth)


class _NormalPriorCUDA(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
        value, acc = _ext().normal_prior_loss_forward(normal, prior, valid)
        ctx.save_for_backward(normal, prior, valid, acc)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        normal, prior, valid, acc = ctx.saved_tensors
        return _ext().normal_prior_loss_backward(_grad_like(grad, normal), normal, prior, valid, acc), None, None


def normal_prior_loss(normal: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
    """L_n by the CUDA kernels (the caller checks :func:`applies`); gradient to ``normal`` only."""
    return _NormalPriorCUDA.apply(normal.contiguous(), prior.detach().to(normal.dtype).contiguous(),
                                  valid.contiguous())
