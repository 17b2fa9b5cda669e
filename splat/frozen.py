"""The training step once the geometry is frozen (`splat train --geometry-until F`, extension).

From step ``round(F * iters)`` the means, scales, rotations and opacities (and any camera
refinement) stop; the colours (sh0, shN) train on. Every geometric loss term (L_d, L_n, L_s, L_nc,
L_a, L_mv) depends on the rendered depth, normals or alpha and on the Gaussians' shapes, never on
their colours, so its gradient on sh0 and shN is zero: the colours' gradient is L_rgb's alone. The
step here takes that alone: the colour composited without the depth and normal channels, L_rgb, a
backward through the colours only (on the CPU the compositing's forward keeps its blend weights and
its backward sums them against d out, with no alpha recomputed; the projection's backward runs the
SH chain alone) and Adam on sh0 and shN. The Gaussians it gives are those of the full step with the
geometry's learning rates at 0, the geometry bit for bit, the colours to float rounding
(tests/test_train_extensions.py compares the two), in less time (bench/train_step_bench.py, the
``frozen`` variant).
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from splat import losses
from splat.losses import LossConfig

GEOMETRY_KEYS = ("means", "scales", "quats", "opacities")
"""The parameters TrainConfig.geometry_until stops: what the rendered depth, normals and alpha (so
the mesh) depend on; the colours (sh0, shN) train on."""

COLOUR_KEYS = ("sh0", "shN")


def detached_view(view):
    """``view`` (splat.views.View) with its camera's tensors detached (a refined camera's corrections
    are frozen with the geometry)."""
    cam = view.camera
    camera = dataclasses.replace(cam, K=cam.K.detach(), viewmat=cam.viewmat.detach(),
                                 center=None if cam.center is None else cam.center.detach())
    return dataclasses.replace(view, camera=camera)


def colour_step(params, optimizers: dict, view, sh_degree: int, loss_cfg: LossConfig, step: int,
                render_fn, guard=None) -> tuple[Tensor, dict, dict]:
    """One iteration with the geometry frozen: L_rgb on ``view``, Adam on the colours.

    ``render_fn(params, view, maps=False)`` renders (the trainer's render_view, its background and
    backend); ``guard`` (splat.guard.NumericsGuard or None) checks the loss and gradients as in
    splat.train.train_step. Returns (loss, terms, density) as train_step does; density is empty, or
    holds the guard's report."""
    frozen = {k: (v.detach() if k in GEOMETRY_KEYS else v) for k, v in params.items()}
    out = render_fn(frozen, detached_view(view), sh_degree, maps=False)
    loss = losses.rgb_loss(out["rgb"], view.rgb, loss_cfg.lambda_dssim, loss_cfg.kernels == "fused")
    loss.backward()
    value = float(loss.detach())
    terms = {"rgb": value, "total": value}
    colour_opts = [optimizers[k] for k in COLOUR_KEYS if k in optimizers]
    if guard is not None:
        event = guard.check_step(step, terms["total"], terms, params)
        if event is not None:
            for opt in colour_opts:
                opt.zero_grad(set_to_none=True)
            return loss.detach(), terms, {"guard": event}
    for opt in colour_opts:
        opt.step()
        opt.zero_grad(set_to_none=True)
    return loss.detach(), terms, {}
