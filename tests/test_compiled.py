"""splat/compiled.py: the loss terms and render maps compiled by torch.compile against their eager
torch code (values and gradients), its fallbacks, and on a GPU the losses and renders that use it.

torch.compile runs on the CPU too (inductor's C++ code), so the compiled graphs are checked here
without a GPU; on one, the CUDA tests below check the Triton path the trainer takes.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch

from splat import compiled
from splat.losses import (LossConfig, _nc_torch, _normal_prior_torch, _rgb_loss_torch, normal_prior_loss,
                          rgb_loss, total_loss)
from splat.rasterize import pixel_maps

CUDA = torch.cuda.is_available()


@pytest.fixture(autouse=True)
def _fresh():
    compiled.reset()
    yield
    compiled.reset()


def _images(h=20, w=28, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(h, w, 3, generator=g)
    gt = torch.rand(h, w, 3, generator=g)
    normal = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g), dim=-1)
    normal[..., 2] = -normal[..., 2].abs()  # facing the camera
    normal[0, :3] = 0.0  # undefined normals
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    depth = 2.0 + 0.02 * xs + 0.01 * ys + 0.01 * torch.rand(h, w, generator=g)  # a tilted plane, roughened
    depth[5:8, 10:14] = 0.0  # holes
    valid = torch.rand(h, w, generator=g) > 0.2
    K = torch.tensor([[30.0, 0.0, w / 2], [0.0, 30.0, h / 2], [0.0, 0.0, 1.0]])
    prior = torch.nn.functional.normalize(normal + 0.2 * torch.randn(h, w, 3, generator=g), dim=-1)
    prior[3] = 0.0
    feats = torch.randn(h, w, 9, generator=g)
    median = torch.randn(h, w, 3, generator=g)
    alpha = torch.rand(h, w, generator=g)
    alpha[0, :5] = 0.0
    out = dict(pred=pred, gt=gt, normal=normal, depth=depth, valid=valid, K=K, prior=prior, feats=feats,
               median=median, alpha=alpha)
    return {k: v.to(device) for k, v in out.items()}


CASES = {
    "rgb": (_rgb_loss_torch, lambda d: (d["pred"], d["gt"], 0.2), (0,)),
    "nc": (_nc_torch, lambda d: (d["normal"], d["depth"], d["K"], d["valid"], False), (0, 1)),
    "nc_detached": (_nc_torch, lambda d: (d["normal"], d["depth"], d["K"], d["valid"], True), (0, 1)),
    "normal_prior": (_normal_prior_torch, lambda d: (d["normal"], d["prior"], d["valid"]), (0,)),
    "pixel_maps": (pixel_maps, lambda d: (d["feats"], d["median"], d["alpha"]), (0, 1, 2)),
}


def _value_and_grads(fn, args, grad_idx, use_compiled):
    args = tuple(a.detach().clone().requires_grad_(i in grad_idx) if torch.is_tensor(a) else a
                 for i, a in enumerate(args))
    out = compiled.call(fn, *args) if use_compiled else fn(*args)
    outs = out if isinstance(out, tuple) else (out,)
    g = torch.Generator().manual_seed(1)
    total = sum((o * torch.rand(o.shape, generator=g).to(o.device)).sum() for o in outs)  # every output counts
    grads = torch.autograd.grad(total, [args[i] for i in grad_idx], allow_unused=True)
    return [o.detach() for o in outs], grads


# torch's inductor links its CPU code with `-L<torch>/lib` unquoted: under a folder whose path has a space
# (`/tmp/ci dir`, `~/My Projects`) nothing compiles and the code runs eagerly with one warning (the
# fallback test below); these comparisons need a compiled graph.
INDUCTOR_CANNOT_LINK = any(c.isspace() for c in str(Path(torch.__file__).parent))


@pytest.mark.skipif(INDUCTOR_CANNOT_LINK, reason="torch inductor cannot link under a path with a space (torch's bug)")
@pytest.mark.parametrize("case", sorted(CASES))
def test_compiled_graph_gives_the_eager_values_and_gradients(case):
    fn, make, grad_idx = CASES[case]
    args = make(_images())
    (y0, g0), (y1, g1) = (_value_and_grads(fn, args, grad_idx, c) for c in (False, True))
    assert fn not in compiled._FAILED, compiled._FAILED.get(fn)
    assert compiled._signature(fn, tuple(a.detach().clone().requires_grad_(i in grad_idx) if torch.is_tensor(a)
                                         else a for i, a in enumerate(args))) in compiled._CHECKED
    for a, b in zip(y1, y0):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(g1, g0):
        if b is None:
            assert a is None or not a.abs().any()
        else:
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    assert any(b is not None and b.abs().sum() > 0 for b in g0)  # the check is not vacuous


def test_a_compiler_that_fails_leaves_the_eager_code_with_one_warning(monkeypatch, caplog):
    calls = []

    def broken(fn, **kw):
        def run(*a):
            calls.append(1)
            raise RuntimeError("no working C compiler\nmore lines")
        return run

    monkeypatch.setattr(torch, "compile", broken)
    d = _images()
    with caplog.at_level(logging.WARNING, logger="splat.compiled"):
        v1 = compiled.call(_rgb_loss_torch, d["pred"], d["gt"], 0.2)
        v2 = compiled.call(_rgb_loss_torch, d["pred"], d["gt"], 0.2)
    assert torch.equal(v1, _rgb_loss_torch(d["pred"], d["gt"], 0.2)) and torch.equal(v1, v2)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "no working C compiler" in warnings[0].getMessage()
    assert "_rgb_loss_torch" in warnings[0].getMessage() and len(calls) == 1  # not tried again


def test_a_compiled_graph_that_disagrees_is_not_used(monkeypatch, caplog):
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: (lambda *a: fn(*a) * 1.01))
    d = _images()
    with caplog.at_level(logging.WARNING, logger="splat.compiled"):
        v = compiled.call(_rgb_loss_torch, d["pred"], d["gt"], 0.2)
    assert torch.equal(v, _rgb_loss_torch(d["pred"], d["gt"], 0.2))
    assert "differs from the eager code" in caplog.text


def test_applies_to_cuda_tensors_only_when_switched_on():
    d = _images()
    assert not compiled.enabled()  # off unless asked for
    compiled.enable(True)
    assert compiled.enabled() and not compiled.applies(d["pred"])
    if CUDA:
        assert compiled.applies(d["pred"].cuda())
        compiled.enable(False)
        assert not compiled.applies(d["pred"].cuda())


def test_cpu_losses_do_not_compile(monkeypatch):
    """On the CPU the fused C++ kernels (or eager torch) run: torch.compile is never asked."""
    monkeypatch.setattr(torch, "compile", lambda *a, **k: pytest.fail("compiled on the CPU"))
    compiled.enable(True)
    d = _images()
    rgb_loss(d["pred"], d["gt"])
    normal_prior_loss(d["normal"], d["prior"], d["valid"])


@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU")
def test_cuda_total_loss_fused_matches_torch_kernels():
    """On a GPU, LossConfig.kernels="fused" (compiled) gives "torch"'s (eager) loss and gradients."""
    d = _images(48, 64, device="cuda")
    out_base = {"rgb": d["pred"], "depth": d["depth"], "normal": d["normal"], "alpha": d["alpha"] + 0.5}
    params = {"scales": torch.randn(10, 3, device="cuda")}
    cue = torch.arange(10, device="cuda") % 3
    res = {}
    compiled.enable(True)
    for kernels in ("torch", "fused"):
        out = {k: v.detach().clone().requires_grad_(k != "alpha") for k, v in out_base.items()}
        cfg = LossConfig(kernels=kernels, nc_from_iter=0)
        loss, terms = total_loss(out, d["gt"], d["K"], params, cue, cfg, step=1, normal_prior=d["prior"])
        loss.backward()
        res[kernels] = (loss.detach(), terms, {k: out[k].grad for k in ("rgb", "depth", "normal")})
    assert set(compiled._COMPILED) >= {_rgb_loss_torch, _nc_torch, _normal_prior_torch} and not compiled._FAILED
    torch.testing.assert_close(res["fused"][0], res["torch"][0], rtol=1e-5, atol=1e-6)
    for k in ("rgb", "depth", "normal"):
        torch.testing.assert_close(res["fused"][2][k], res["torch"][2][k], rtol=1e-4, atol=1e-7)
