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
    strategy = IndoorStrategy(IndoorStrategyConfig(total_iters=ITERS, max_gaussians=0))
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



def test_fused_adam_is_torch_adam_through_row_rewrites():
    """`--adam fused` (the default) against torch's default Adam on the same gradients, with rows
    cloned and removed between steps (the moments move with the rows): the same update to rounding."""
    from splat.densify_ops import duplicate, remove

    g = torch.Generator().manual_seed(3)
    base = {"means": torch.randn(500, 3, generator=g), "opacities": torch.randn(500, generator=g),
            "shN": torch.randn(500, 3, 3, generator=g)}
    runs = {}
    for adam in ("fused", "torch"):
        params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.clone()) for k, v in base.items()})
        opts = make_optimizers(params, LearningRates(), 3.0, adam)
        state = {"cue_type": torch.arange(500) % 3}
        gg = torch.Generator().manual_seed(4)
        for step in range(60):
            for p in params.values():  # gradients away from zero: Adam's sign-like step is not decided by rounding
                p.grad = (torch.rand(p.shape, generator=gg) + 0.5) * torch.where(p.detach() > 0, 1.0, -1.0)
            for opt in opts.values():
                opt.step()
            if step == 20:
                duplicate(params, opts, state, torch.arange(len(params["means"])) % 7 == 0)
            if step == 40:
                remove(params, opts, state, torch.arange(len(params["means"])) % 5 == 0)
        runs[adam] = {k: v.detach() for k, v in params.items()}, opts
    (a, oa), (b, ob) = runs["fused"], runs["torch"]
    for k in a:
        assert a[k].shape == b[k].shape and torch.allclose(a[k], b[k], rtol=1e-5, atol=1e-6), k
        sa, sb = oa[k].state[oa[k].param_groups[0]["params"][0]], ob[k].state[ob[k].param_groups[0]["params"][0]]
        assert torch.allclose(sa["exp_avg_sq"], sb["exp_avg_sq"], rtol=1e-5, atol=1e-9), k
        assert float(sa["step"]) == float(sb["step"]) == 60
    with pytest.raises(ValueError, match="adam"):
        make_optimizers(torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(2, 3))}),
                        LearningRates(), 1.0, "sgd")


def _short_run(adam: str, iters: int, kernels: str = "fused", device: str = "cpu") -> tuple[float, dict]:
    truth = surface_gaussians(2000, sh_degree=1, seed=2)
    views = target_views(truth, W, H, device, sh_degree=1)
    g = torch.Generator().manual_seed(0)
    start = {k: v.clone() for k, v in truth.items()}
    start["sh0"] += 0.5 * torch.randn(start["sh0"].shape, generator=g)
    start["means"] += 0.01 * torch.randn(start["means"].shape, generator=g)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.to(device)) for k, v in start.items()})
    optimizers = make_optimizers(params, LearningRates(), 3.0, adam)
    strategy = IndoorStrategy(IndoorStrategyConfig(total_iters=ITERS, max_gaussians=0))
    state = strategy.initialize_state(3.0)
    state["cue_type"] = (torch.arange(len(params["means"])) % 3).to(device)
    cfg = TrainConfig(iters=ITERS, device=device, sh_degree=1, adam=adam)
    loss_cfg = replace(LossConfig(), nc_from_iter=0, kernels=kernels)
    for step in range(iters):
        train_step(params, optimizers, strategy, state, views[step % len(views)], step, 1, cfg, loss_cfg, g)
    counts = torch.bincount(state["cue_type"].cpu(), minlength=3).tolist()
    return psnr(params, views), counts


def test_fused_adam_trains_to_the_same_metrics():
    """A fixed-seed run with each Adam: Adam's near-sign step (eps 1e-15) turns rounding into
    different parameters within a few steps, and refine steps then pick other rows, so the runs
    are compared where the issue states its tolerance: the fit (PSNR within 0.5 dB) and the
    Gaussian count per type (within 3 %)."""
    pa, ca = _short_run("fused", ITERS)
    pb, cb = _short_run("torch", ITERS)
    assert abs(pa - pb) < 0.5, (pa, pb)
    assert all(abs(x - y) <= 0.03 * max(y, 10) for x, y in zip(ca, cb)), (ca, cb)


def test_fused_loss_kernels_train_to_the_same_metrics():
    """The loss's fused C++ SSIM and L_nc (the default) against autograd through torch's, under the
    same tolerance as the fused Adam: the values and gradients agree to float rounding
    (tests/test_losses_cpu.py), which the run amplifies."""
    pa, ca = _short_run("fused", ITERS, kernels="fused")
    pb, cb = _short_run("fused", ITERS, kernels="torch")
    assert abs(pa - pb) < 0.5, (pa, pb)
    assert all(abs(x - y) <= 0.03 * max(y, 10) for x, y in zip(ca, cb)), (ca, cb)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_loss_kernels_give_the_steps_gradients():
    """On a GPU: one step's loss and the gradients of every parameter through the rasterizer, with the
    CUDA loss kernels of splat/losses_cuda.py (the default there) and with torch's loss code, every
    term on (L_rgb, L_d, L_n, L_s, L_nc). Not a training run: on a GPU the compositing backward adds
    with atomics, so two runs of the same code already part (120-step runs of this test's problem
    with torch's loss code alone gave 28.0 / 29.1 / 30.3 dB on an H200)."""
    from splat.losses import total_loss
    from splat.train import render_view

    truth = surface_gaussians(2000, sh_degree=1, seed=2)
    views = target_views(truth, W, H, "cuda", sh_degree=1)
    g = torch.Generator().manual_seed(0)
    start = {k: v.clone() for k, v in truth.items()}
    start["sh0"] += 0.5 * torch.randn(start["sh0"].shape, generator=g)
    start["means"] += 0.01 * torch.randn(start["means"].shape, generator=g)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.to("cuda")) for k, v in start.items()})
    cue_type = (torch.arange(len(params["means"])) % 3).to("cuda")
    cfg = TrainConfig(iters=ITERS, device="cuda", sh_degree=1)
    results = {}
    for kernels in ("fused", "torch"):
        loss_cfg = replace(LossConfig(), nc_from_iter=0, kernels=kernels)
        view = views[1]
        out = render_view(params, view, 1, cfg)
        loss, terms = total_loss(out, view.rgb, view.camera.K, params, cue_type, loss_cfg, 10,
                                 depth_prior=view.depth_prior, normal_prior=view.normal_prior,
                                 generator=torch.Generator().manual_seed(1))
        grads = torch.autograd.grad(loss, list(params.values()))
        results[kernels] = float(loss.detach()), terms, dict(zip(params.keys(), grads))
    (lf, tf, gf), (lt, tt, gt) = results["fused"], results["torch"]
    assert set(tf) == {"rgb", "depth", "normal", "flat", "nc", "total"}, tf
    for key in tf:
        assert abs(tf[key] - tt[key]) <= 1e-5 * max(1.0, abs(tt[key])), (key, tf[key], tt[key])
    for name in gt:
        rel = float((gf[name] - gt[name]).abs().max() / gt[name].abs().max().clamp(min=1e-30))
        assert rel < 1e-3, (name, rel)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_a_cuda_step_waits_for_the_gpu_at_most_three_times():
    """The compositing's pair count, the loss terms' values and one more copy to the host; every
    other wait (images and constants copied from pageable memory, boolean indexing) is gone."""
    import warnings

    truth = surface_gaussians(2000, sh_degree=1, seed=2)
    views = target_views(truth, W, H, "cuda", sh_degree=1)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.to("cuda")) for k, v in truth.items()})
    optimizers = make_optimizers(params, LearningRates(), 3.0)
    strategy = IndoorStrategy(IndoorStrategyConfig(total_iters=ITERS, max_gaussians=0))
    state = strategy.initialize_state(3.0)
    state["cue_type"] = (torch.arange(len(params["means"])) % 3).to("cuda")
    cfg = TrainConfig(iters=ITERS, device="cuda", sh_degree=1)
    loss_cfg = replace(LossConfig(), nc_from_iter=0)
    g = torch.Generator().manual_seed(0)
    train_step(params, optimizers, strategy, state, views[0], 1, 1, cfg, loss_cfg, g)  # warm-up
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            train_step(params, optimizers, strategy, state, views[1], 2, 1, cfg, loss_cfg, g)
        finally:
            torch.cuda.set_sync_debug_mode(0)
    syncs = [str(w.message) for w in caught if "called a synchronizing" in str(w.message)]
    assert 1 <= len(syncs) <= 3, syncs
