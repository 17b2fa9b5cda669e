"""CUDA compositing backend, wrapped in a torch.autograd.Function.

The kernels (``splat/csrc/composite_cuda.cu``, built by :mod:`splat.cuda_ext` on first import)
implement the per-pixel rule of :mod:`splat.composite` as 3DGS's rasterizer does: (tile, depth)
keys of every (16x16 tile, Gaussian) pair radix-sorted on the GPU, one thread block per tile and
one thread per pixel, Gaussians staged in shared memory 256 at a time, early termination, and an
analytic backward back to front (transmittance recovered by division) that sums each warp's
gradients and adds them per Gaussian with ``atomicAdd``. It has no per-pixel cap on contributors.
Only float32 is supported (float64 CUDA tensors go to the torch backend through
:func:`splat.composite.resolve_backend`); all tensors must be on one CUDA device. Gradients are
not bitwise reproducible from run to run (the order of the atomic additions varies).

Importing this module builds the extension; without a CUDA device or when the build fails it raises
ImportError and :mod:`splat.composite` falls back to torch with a warning.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from splat.contracts import CompositeOut, check_composite_inputs
from splat.cuda_ext import ext as _ext


class _CompositeCUDA(torch.autograd.Function):
    """Autograd wrapper: forward and analytic backward both in CUDA."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, background, median_features, depths, radii,
                width, height):
        (out, alpha, median, n_contrib, final_t, last, median_idx,
         *state) = _ext.forward(means2d, conics, opacities, features, depths, radii, background,
                                median_features, width, height)
        ctx.save_for_backward(features, background, median_features, final_t, last, median_idx, *state)
        ctx.size = (width, height)
        ctx.mark_non_differentiable(n_contrib)
        return out, alpha, median, n_contrib

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out, grad_alpha, grad_median, _grad_n):
        grads = _ext.backward(grad_out.contiguous(), grad_alpha.contiguous(), grad_median.contiguous(),
                              *ctx.saved_tensors, *ctx.size)
        d_means, d_conics, d_opac, d_feat, d_bg, d_medf = grads
        return d_means, d_conics, d_opac, d_feat, d_bg, d_medf, None, None, None, None


def composite(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    depths: Tensor,  # [N]
    radii: Tensor,  # [N] int
    width: int,
    height: int,
    *,
    background: Tensor | None = None,  # [C]
    median_features: Tensor | None = None,  # [N, M]
) -> CompositeOut:
    """Composite with the CUDA kernels; same arguments and result as :func:`splat.composite.composite`."""
    check_composite_inputs(means2d, conics, opacities, features, depths, radii, width, height,
                           background, median_features)
    if features.dtype != torch.float32:
        raise ValueError(f"the cuda backend supports float32 only, got features of dtype {features.dtype}")
    device = features.device
    named = {"means2d": means2d, "conics": conics, "opacities": opacities, "features": features,
             "depths": depths, "radii": radii}
    if background is not None:
        named["background"] = background
    if median_features is not None:
        named["median_features"] = median_features
    for name, tensor in named.items():
        if tensor.device != device or device.type != "cuda":
            raise ValueError(f"{name} must be a CUDA tensor on {device} for the 'cuda' backend, "
                             f"got {tensor.device}")
        if name not in ("depths", "radii") and tensor.dtype != torch.float32:
            raise ValueError(f"{name} must have dtype torch.float32 (as features), got {tensor.dtype}")
    n, c = features.shape
    bg = background if background is not None else features.new_zeros(c)
    med = median_features if median_features is not None else features.new_zeros(n, 0)
    out, alpha, median, n_contrib = _CompositeCUDA.apply(
        means2d.contiguous(), conics.contiguous(), opacities.contiguous(), features.contiguous(),
        bg.contiguous(), med.contiguous(), depths.detach().to(torch.float32).contiguous(),
        radii.detach().to(torch.int32).contiguous(), int(width), int(height))
    return CompositeOut(out, alpha, median if median_features is not None else None, n_contrib)
