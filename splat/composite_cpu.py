"""C++ CPU compositing backend, wrapped in a torch.autograd.Function.

The kernel (``splat/csrc/composite_cpu.cpp``, built by :mod:`splat.cpu_ext` on first import)
implements the per-pixel rule of :mod:`splat.composite` with 16x16 tiles, a global stable depth
sort, early termination, OpenMP over tiles and an analytic backward (back to front, transmittance
recovered by division, as 3DGS ``backward.cu``). When the features need a gradient and none of
means2d, conics, opacities and median_features does (a frozen geometry: ``splat train
--geometry-until``), the forward keeps its blend weights w = alpha T per (Gaussian, pixel) and the
backward is d features = sum of w d out per Gaussian, no alpha recomputed (the weights are the
forward's, so the gradients match the full backward's to float rounding, not bit for bit). The kept
weights live in buffers reused from call to call: a backward whose forward's weights have been
replaced by a later forward's takes the full backward instead. It has no per-pixel cap on contributors. float32
and float64 are supported (the latter for ``gradcheck``); all tensors must be on the CPU. If the
extension cannot be built, importing this module raises ImportError and :mod:`splat.composite`
falls back to torch with a warning.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from splat.contracts import CompositeOut, check_composite_inputs
from splat.cpu_ext import ext as _ext


class _CompositeCPU(torch.autograd.Function):
    """Autograd wrapper: forward and analytic backward both in C++."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, background, median_features, depths, radii,
                width, height):
        # the geometry frozen (no gradient to means2d, conics, opacities, median_features): keep the
        # blend weights, and the backward is a weighted sum of d out per Gaussian, no alpha recomputed
        needs = ctx.needs_input_grad
        store = needs[3] and not (needs[0] or needs[1] or needs[2] or needs[5])
        (out, alpha, median, n_contrib, final_t, last, median_idx,
         *bins, generation) = _ext.forward(means2d, conics, opacities, features, depths, radii, background,
                                           median_features, width, height, store)
        ctx.save_for_backward(means2d, conics, opacities, features, radii, background, median_features,
                              final_t, last, median_idx, *bins)
        ctx.size, ctx.generation = (width, height), int(generation) if store else -1
        ctx.mark_non_differentiable(n_contrib)
        return out, alpha, median, n_contrib

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out, grad_alpha, grad_median, _grad_n):
        saved = ctx.saved_tensors
        if ctx.generation >= 0:  # empty when a later forward has kept its own weights since
            stored = _ext.backward_stored(grad_out.contiguous(), saved[3], saved[7], *saved[10:],
                                          ctx.generation, *ctx.size)
            if stored:
                return None, None, None, stored[0], stored[1], None, None, None, None, None
        grads = _ext.backward(grad_out.contiguous(), grad_alpha.contiguous(), grad_median.contiguous(),
                              *saved, *ctx.size)
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
    """Composite with the C++ kernel; same arguments and result as :func:`splat.composite.composite`."""
    check_composite_inputs(means2d, conics, opacities, features, depths, radii, width, height,
                           background, median_features)
    dtype = features.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"features must be float32 or float64, got {dtype}")
    named = {"means2d": means2d, "conics": conics, "opacities": opacities, "features": features}
    if background is not None:
        named["background"] = background
    if median_features is not None:
        named["median_features"] = median_features
    for name, tensor in named.items():
        if tensor.device.type != "cpu":
            raise ValueError(f"{name} must be a CPU tensor for the 'cpu' backend, got {tensor.device}")
        if tensor.dtype != dtype:
            raise ValueError(f"{name} must have dtype {dtype} (as features), got {tensor.dtype}")
    n, c = features.shape
    bg = background if background is not None else features.new_zeros(c)
    med = median_features if median_features is not None else features.new_zeros(n, 0)
    out, alpha, median, n_contrib = _CompositeCPU.apply(
        means2d.contiguous(), conics.contiguous(), opacities.contiguous(), features.contiguous(),
        bg.contiguous(), med.contiguous(), depths.detach().to(dtype).contiguous(),
        radii.detach().to(torch.int32).contiguous(), int(width), int(height))
    return CompositeOut(out, alpha, median if median_features is not None else None, n_contrib)
