"""splat.train.train_step on the CPU and, where there is one, a CUDA device.

No scene files: the targets are renders of flat Gaussians on a benchmark room's surfaces
(splat.bench.surface_gaussians) from four cameras, and training starts from a perturbed copy
(colours, positions, opacities off). It checks that a few refine intervals of the full step (render,
IndoorGS loss, Adam, per-type density control) fit the targets, keep every tensor finite and keep
the per-Gaussian state aligned with the parameters, on whichever device the tensors live.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from geocues.types import CueType
from splat.bench import surface_gaussians, target_views
from splat.losses import LossConfig
from splat.rasterize import render
from splat.strategy import IndoorStrategy, IndoorStrategyConfig
from splat.train import PAPER_ITERS, LearningRates, TrainConfig, make_optimizers, train_step

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                 reason="no CUDA device"))]
ITERS, W, H = 120, 64, 48


def psnr(params, views: list) -> float:
    with torch.no_grad():
        mse = [float(((render(params, v.camera, sh_degree=1)["rgb"].clamp(0, 1) - v.rgb) ** 2).mean())
               for v in views]
    return float(np.mean([-10 * math.log10(max(m, 1e-12)) for m in mse]))


@pytest.mark.parametrize("device", DEVICES)
def test_train_steps_fit_targets_and_keep_state_aligned(device):
    truth = surface_gaussians(3000, sh_degree=1, seed=1)
    views = target_views(truth, W, H, device, sh_degree=1)
    g = torch.Generator().manual_seed(0)
    start = {k: v.clone() for k, v in truth.items()}
    start["sh0"] += 0.5 * torch.randn(start["sh0"].shape, generator=g)
    start["means"] += 0.01 * torch.randn(start["means"].shape, generator=g)
    start["opacities"] = torch.full_like(start["opacities"], math.log(0.1 / 0.9))
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.to(device)) for k, v in start.items()})
    scale = 3.0
    optimizers = make_optimizers(params, LearningRates(), scale)
    strategy = IndoorStrategy(IndoorStrategyConfig(total_iters=ITERS))
    state = strategy.initialize_state(scale)
    state["cue_type"] = (torch.arange(len(params["means"])) % 3).to(device)  # SFM, LINE, PLANE in turn
    cfg = TrainConfig(iters=ITERS, device=device, sh_degree=1)
    loss_cfg = replace(LossConfig(), nc_from_iter=round(LossConfig().nc_from_iter * ITERS / PAPER_ITERS))
    before = psnr(params, views)

    densities, losses = [], []
    for step in range(ITERS):
        loss, terms, density = train_step(params, optimizers, strategy, state, views[step % len(views)], step,
                                          1, cfg, loss_cfg, g)
        assert math.isfinite(float(loss)) and all(math.isfinite(v) for v in terms.values()), (step, terms)
        losses.append(float(loss))
        if density:
            densities.append(density)
        n = params["means"].shape[0]
        assert state["cue_type"].shape == (n,) and state["cue_type"].device.type == device
        for opt in optimizers.values():
            for p in opt.param_groups[0]["params"]:
                assert p.shape[0] == n and p.device.type == device
    for name, p in params.items():
        assert torch.isfinite(p).all(), name
    after = psnr(params, views)
    assert after > before + 3.0, (before, after)
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:10])
    # refine steps ran, and grew LINE Gaussians (cloned or split) where the fit asked for it
    assert len(densities) >= 2, densities
    grown = sum(d.get(f"{op}_line", 0) for d in densities for op in ("cloned", "split"))
    assert grown > 0, densities
    kinds = torch.bincount(state["cue_type"].cpu(), minlength=3)
    assert kinds[int(CueType.PLANE)] <= 1000  # PLANE is prune-only: never more than at the start
