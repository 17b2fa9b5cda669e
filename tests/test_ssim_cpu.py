"""The fused C++ SSIM of the training loss against its torch oracle (values and gradients)."""

import pytest
import torch

from evaluation.image_metrics import ssim_map
from splat.ssim_cpu import fused_available, ssim_mean

pytestmark = pytest.mark.skipif(not fused_available(), reason="C++ extension not built")


def _pair(h, w, c=3, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, c, generator=g, dtype=dtype)
    b = (a + 0.2 * torch.randn(h, w, c, generator=g, dtype=dtype)).clamp(0, 1)
    return a, b


def _oracle(a, b):
    a = a.detach().clone().requires_grad_(True)
    value = ssim_map(a, b).mean()
    value.backward()
    return value.detach(), a.grad


@pytest.mark.parametrize("h, w, c", [(37, 53, 3), (5, 4, 3), (11, 11, 1), (1, 30, 3), (64, 48, 2)])
def test_value_and_gradient_match_the_torch_oracle_in_float64(h, w, c):
    """Images smaller than the window, one row, other channel counts: the zero padding is the same."""
    a, b = _pair(h, w, c)
    want, want_grad = _oracle(a, b)
    x = a.clone().requires_grad_(True)
    got = ssim_mean(x, b)
    got.backward()
    assert torch.allclose(got, want, rtol=0, atol=1e-13)
    assert torch.allclose(x.grad, want_grad, rtol=1e-10, atol=1e-15)


def test_gradcheck():
    a, b = _pair(9, 12)
    assert torch.autograd.gradcheck(lambda x: ssim_mean(x, b), (a.clone().requires_grad_(True),))


def test_float32_within_rounding_of_the_float64_oracle():
    a, b = _pair(120, 160, dtype=torch.float32, seed=3)
    want, want_grad = _oracle(a.double(), b.double())
    x = a.clone().requires_grad_(True)
    got = ssim_mean(x, b)
    got.backward()
    assert got.dtype == torch.float32
    assert abs(float(got) - float(want)) < 1e-5
    rel = (x.grad.double() - want_grad).abs().max() / want_grad.abs().max()
    assert rel < 1e-4


@pytest.mark.parametrize("case", ["identical", "constant", "black", "saturated"])
def test_hard_cases_stay_finite(case):
    """Flat images (zero variance: B2 = C2 only), identical pairs (S = 1), all-black (B1 = C1)."""
    a, b = _pair(24, 24)
    if case == "identical":
        b = a.clone()
    elif case == "constant":
        a, b = torch.full_like(a, 0.5), torch.full_like(a, 0.3)
    elif case == "black":
        a, b = torch.zeros_like(a), torch.zeros_like(a)
    else:
        a, b = torch.ones_like(a), torch.zeros_like(a)
    want, want_grad = _oracle(a, b)
    x = a.clone().requires_grad_(True)
    got = ssim_mean(x, b)
    got.backward()
    assert torch.isfinite(got) and torch.isfinite(x.grad).all()
    assert torch.allclose(got, want, atol=1e-12) and torch.allclose(x.grad, want_grad, atol=1e-12)


def test_torch_path_when_asked_or_when_gt_needs_a_gradient():
    a, b = _pair(16, 16)
    bg = b.clone().requires_grad_(True)
    value = ssim_mean(a, bg)
    value.backward()
    assert bg.grad is not None  # autograd through the oracle reaches gt
    assert torch.allclose(ssim_mean(a, b, fused=False), ssim_map(a, b).mean())


def test_bad_shapes_name_the_inputs():
    with pytest.raises(ValueError, match="pred"):
        ssim_mean(torch.rand(4, 4, 3), torch.rand(4, 5, 3))
