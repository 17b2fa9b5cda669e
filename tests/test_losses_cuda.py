"""The fused CUDA loss terms (splat/losses_cuda.py: L_rgb, L_nc, L_n) against their torch oracles
in splat/losses.py, values and gradients, float64 and float32, with the hard cases of
tests/test_losses_cpu.py (images smaller than the window, flat and saturated images, holes, depth
jumps, nothing valid, depths at the near plane, Inf / NaN prior pixels), and the promise that they
never wait for the GPU.

CI has no GPU: every test but the dispatch test and L_s's CPU checks is skipped there; they run on a GPU
machine (bench/gpu_check.sh, bench/gpu_session.sh). On a GPU machine a failed build fails here.
"""

import pytest
import torch
from test_losses_cpu import (NC_HARD, RGB_HARD, _nc_case, _nc_grads, _np_grads, _pair, nc_hard_case, np_case,
                             rgb_hard_case)

from splat import losses_cuda
from splat.losses import (_flatten_masked, _rgb_loss_torch, depth_normal_consistency_loss, flatten_loss,
                          normal_prior_loss, rgb_loss)

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (CI has none)")
DEV = "cuda"


def test_cpu_tensors_never_take_the_cuda_kernels():
    """On the CPU nothing imports the CUDA extension (it builds only on GPU machines)."""
    a, b = _pair(8, 8)
    assert not losses_cuda.applies(a, b)
    assert not losses_cuda.applies()


@needs_cuda
def test_the_kernels_are_built_and_taken():
    a, b = _pair(8, 8)
    assert losses_cuda.applies(a.to(DEV), b.to(DEV))
    assert not losses_cuda.applies(a.to(DEV), b)  # mixed devices
    assert not losses_cuda.applies(a.to(DEV).half(), b.to(DEV).half())


def _rgb(fused, a, b, lam=0.2):
    x = a.clone().requires_grad_(True)
    value = losses_cuda.rgb_loss(x, b, lam) if fused else _rgb_loss_torch(x, b, lam)
    value.backward()
    return value.detach(), x.grad


@needs_cuda
def test_rgb_loss_takes_the_kernels_on_the_gpu_and_the_oracle_when_asked():
    a, b = (t.float().to(DEV) for t in _pair(40, 30))
    assert torch.equal(rgb_loss(a, b, 0.2), losses_cuda.rgb_loss(a, b, 0.2))
    oracle = rgb_loss(a, b, 0.2, fused_ssim=False)
    assert abs(float(oracle) - float(_rgb_loss_torch(a, b, 0.2))) < 1e-7
    assert abs(float(oracle) - float(rgb_loss(a, b, 0.2))) < 1e-5


@needs_cuda
@pytest.mark.parametrize("h, w, c", [(37, 53, 3), (5, 4, 3), (11, 11, 1), (1, 30, 3), (64, 48, 2)])
@pytest.mark.parametrize("lam", [0.2, 0.0, 1.0])
def test_rgb_matches_the_torch_oracle_in_float64(h, w, c, lam):
    a, b = (t.to(DEV) for t in _pair(h, w, c))
    v0, g0 = _rgb(False, a, b, lam)
    v1, g1 = _rgb(True, a, b, lam)
    assert torch.allclose(v1, v0, rtol=0, atol=1e-12)
    assert torch.allclose(g1, g0, rtol=1e-9, atol=1e-14)


@needs_cuda
def test_rgb_float32_within_rounding_of_the_float64_oracle():
    a, b = _pair(240, 320, seed=3)
    want, want_grad = _rgb(False, a.to(DEV), b.to(DEV))
    got, grad = _rgb(True, a.float().to(DEV), b.float().to(DEV))
    assert got.dtype == torch.float32
    assert abs(float(got) - float(want)) < 1e-5
    assert float((grad.double() - want_grad).abs().max() / want_grad.abs().max()) < 1e-4


@needs_cuda
@pytest.mark.parametrize("case", RGB_HARD)
def test_rgb_hard_cases_stay_finite(case):
    a, b = rgb_hard_case(case)
    v0, g0 = _rgb(False, a.to(DEV), b.to(DEV))
    v1, g1 = _rgb(True, a.to(DEV), b.to(DEV))
    assert torch.isfinite(v1) and torch.isfinite(g1).all()
    assert torch.allclose(v1, v0, atol=1e-12) and torch.allclose(g1, g0, atol=1e-12)


def _on(case, dtype=None):
    return tuple(t.to(DEV) if t.dtype == torch.bool or dtype is None else t.to(DEV, dtype) for t in case)


@needs_cuda
@pytest.mark.parametrize("detach", [False, True])
@pytest.mark.parametrize("size", [(23, 31), (3, 3), (2, 9), (40, 17)])
def test_nc_matches_the_torch_oracle_in_float64(size, detach):
    case = _on(_nc_case(*size))
    v0, gn0, gd0 = _nc_grads(False, *case, detach=detach)
    v1, gn1, gd1 = _nc_grads(True, *case, detach=detach)
    assert torch.allclose(v1, v0, rtol=1e-12, atol=1e-14)
    assert torch.allclose(gn1, gn0, rtol=1e-10, atol=1e-14)
    if detach:
        assert gd1 is None or not gd1.abs().any()
    else:
        assert torch.allclose(gd1, gd0, rtol=1e-9, atol=1e-13)


@needs_cuda
def test_nc_float32_within_rounding_of_float64():
    case = _nc_case(120, 160, holes=True, seed=4)
    ref = _nc_grads(False, *_on(case))

    def errors(fused):
        got = _nc_grads(fused, *_on(case, torch.float32))
        return [float((g.double() - r).abs().max() / max(float(r.abs().max()), 1e-30)) for g, r in zip(got, ref)]

    fused, torch32 = errors(True), errors(False)
    assert all(f <= 2 * t + 1e-7 for f, t in zip(fused, torch32)), (fused, torch32)
    assert max(fused) < 1e-4


@needs_cuda
@pytest.mark.parametrize("case", NC_HARD)
def test_nc_hard_cases_stay_finite(case):
    args = _on(nc_hard_case(case))
    v0, gn0, gd0 = _nc_grads(False, *args)
    v1, gn1, gd1 = _nc_grads(True, *args)
    assert torch.isfinite(v1) and torch.isfinite(gn1).all() and torch.isfinite(gd1).all()
    assert torch.allclose(v1, v0, atol=1e-12) and torch.allclose(gn1, gn0, atol=1e-12)
    assert torch.allclose(gd1, gd0, rtol=1e-9, atol=1e-9 * max(1.0, float(gd0.abs().max())))


@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_normal_prior_matches_the_torch_oracle(dtype):
    normal, prior, valid = (t.to(DEV) for t in np_case(dtype))
    v0, g0 = _np_grads(False, normal, prior, valid)
    v1, g1 = _np_grads(True, normal, prior, valid)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert torch.isfinite(v1) and torch.isfinite(g1).all()
    assert abs(float(v1) - float(v0)) < tol
    assert torch.allclose(g1, g0, atol=tol)


@needs_cuda
def test_normal_prior_with_nothing_valid_is_zero_with_zero_gradient():
    normal = torch.nn.functional.normalize(torch.randn(8, 8, 3, dtype=torch.float64), dim=-1).to(DEV)
    v, grad = _np_grads(True, normal, normal.flip(0), torch.zeros(8, 8, dtype=torch.bool, device=DEV))
    assert float(v) == 0.0 and not grad.abs().any()


@needs_cuda
def test_the_fused_terms_never_wait_for_the_gpu():
    """Forward and backward of the three terms and L_s launch without a device-to-host copy."""
    a, b = (t.float().to(DEV) for t in _pair(48, 64))
    normal, depth, K, valid = _on(_nc_case(48, 64), torch.float32)
    scales = torch.randn(500, 3, device=DEV)
    mask = torch.rand(500, device=DEV) > 0.5
    losses_cuda.applies(a)  # builds / loads the extension before the check
    x, n, d, s = (t.clone().requires_grad_(True) for t in (a, normal, depth, scales))
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        total = (rgb_loss(x, b, 0.2) + depth_normal_consistency_loss(n, d, K, valid)
                 + normal_prior_loss(n, normal.flip(0), valid) + flatten_loss(s, mask))
        total.backward()
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert torch.isfinite(total) and all(torch.isfinite(t.grad).all() for t in (x, n, d, s))


# ---- L_s without boolean indexing (the GPU form, checked on the CPU and on the GPU) ----------------

def _flat(fn, scales, mask, dev):
    s = scales.clone().to(dev).requires_grad_(True)
    value = fn(s, mask.to(dev))
    value.backward()
    return value.detach().cpu(), s.grad.cpu()


def _flat_case(case):
    g = torch.Generator().manual_seed(2)
    scales = torch.randn(300, 3, generator=g, dtype=torch.float64)
    mask = torch.rand(300, generator=g) > 0.6
    if case == "none":
        mask[:] = False
    elif case == "huge_unmasked":
        scales[~mask] = 1e4
    return scales, mask


CASES = ["some", "none", "huge_unmasked"]


@pytest.mark.parametrize("case", CASES)
def test_flatten_without_indexing_matches_the_indexed_form(case):
    """The same mean and gradient; an empty mask gives 0; an unmasked log-scale of 1e4 (exp = inf) no NaN."""
    scales, mask = _flat_case(case)
    v0, g0 = _flat(flatten_loss, scales, mask, "cpu")
    v1, g1 = _flat(_flatten_masked, scales, mask, "cpu")
    assert torch.isfinite(v1) and torch.isfinite(g1).all()
    assert torch.allclose(v1, v0, rtol=1e-12, atol=0) and torch.allclose(g1, g0, rtol=1e-12, atol=0)


@needs_cuda
@pytest.mark.parametrize("case", CASES)
def test_flatten_loss_on_the_gpu_matches_the_cpu(case):
    scales, mask = _flat_case(case)
    v0, g0 = _flat(flatten_loss, scales, mask, "cpu")
    v1, g1 = _flat(flatten_loss, scales, mask, DEV)
    assert torch.isfinite(v1) and torch.isfinite(g1).all()
    assert torch.allclose(v1, v0, rtol=1e-12, atol=0) and torch.allclose(g1, g0, rtol=1e-12, atol=0)
