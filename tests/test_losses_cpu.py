"""The fused C++ loss terms (SSIM of L_rgb, L_nc) against their torch oracles (values and gradients)."""

import shutil

import pytest
import torch

from evaluation.image_metrics import ssim_map
from splat.losses_cpu import fused_available, ssim_mean

# No compiler: nothing to test. With one, a failed build must fail here, not skip.
pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler")


def test_the_fused_kernels_are_built():
    assert fused_available()


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


RGB_HARD = ["identical", "constant", "black", "saturated"]


def rgb_hard_case(case: str):
    """Flat images (zero variance: B2 = C2 only), identical pairs (S = 1), all-black (B1 = C1), saturated."""
    a, b = _pair(24, 24)
    if case == "identical":
        return a, a.clone()
    if case == "constant":
        return torch.full_like(a, 0.5), torch.full_like(a, 0.3)
    if case == "black":
        return torch.zeros_like(a), torch.zeros_like(a)
    return torch.ones_like(a), torch.zeros_like(a)


@pytest.mark.parametrize("case", RGB_HARD)
def test_hard_cases_stay_finite(case):
    a, b = rgb_hard_case(case)
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


# ---- L_nc ----------------------------------------------------------------------------------------

from splat.losses import depth_normal_consistency_loss  # noqa: E402


def _nc_case(h=23, w=31, dtype=torch.float64, seed=0, holes=True, zero_normals=True):
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    depth = 2.0 + 0.02 * xx + 0.01 * yy + 0.05 * torch.sin(xx / 3) * torch.cos(yy / 4)
    if holes:  # zero depth (no surface) and a discontinuity
        depth[5:8, 10:14] = 0.0
        depth[:, 20:] += 0.7
    normal = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g, dtype=dtype), dim=-1)
    if zero_normals:
        normal[0:3, 0:5] = 0.0  # undefined rendered normals (the mask switches there: not for gradcheck)
    valid = torch.rand(h, w, generator=g) > 0.2
    K = torch.tensor([[40.0, 0, w / 2 + 0.3], [0, 42.0, h / 2 - 0.2], [0, 0, 1]], dtype=dtype)
    return normal, depth, K, valid


def _nc_grads(fused, normal, depth, K, valid, detach=False):
    n = normal.clone().requires_grad_(True)
    d = depth.clone().requires_grad_(True)
    value = depth_normal_consistency_loss(n, d, K, valid, detach, fused=fused)
    value.backward()
    return value.detach(), n.grad, d.grad


@pytest.mark.parametrize("detach", [False, True])
@pytest.mark.parametrize("size", [(23, 31), (3, 3), (2, 9), (40, 17)])
def test_nc_matches_the_torch_oracle_in_float64(size, detach):
    """Holes, a depth jump, undefined normals, masked pixels; images with no interior pixel."""
    case = _nc_case(*size)
    v0, gn0, gd0 = _nc_grads(False, *case, detach=detach)
    v1, gn1, gd1 = _nc_grads(True, *case, detach=detach)
    assert torch.allclose(v1, v0, rtol=1e-12, atol=1e-14)
    assert torch.allclose(gn1, gn0, rtol=1e-10, atol=1e-14)
    if detach:
        assert gd1 is None or not gd1.abs().any()
    else:
        assert torch.allclose(gd1, gd0, rtol=1e-9, atol=1e-13)


def test_nc_gradcheck():
    normal, depth, K, valid = _nc_case(9, 11, holes=False, zero_normals=False)
    n = normal.clone().requires_grad_(True)
    d = depth.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: depth_normal_consistency_loss(a, b, K, valid), (n, d))


def test_nc_float32_within_rounding_of_float64():
    """In float32 the fused kernel is as close to the float64 result as torch's float32 is."""
    normal, depth, K, valid = _nc_case(120, 160, holes=True, seed=4)
    ref = _nc_grads(False, normal, depth, K, valid)
    low = normal.float(), depth.float(), K.float(), valid

    def errors(fused):
        got = _nc_grads(fused, *low)
        return [float((g.double() - r).abs().max() / max(float(r.abs().max()), 1e-30)) for g, r in zip(got, ref)]

    fused, torch32 = errors(True), errors(False)
    assert all(f <= 2 * t + 1e-7 for f, t in zip(fused, torch32)), (fused, torch32)
    assert max(fused) < 1e-4


NC_HARD = ["no_valid", "zero_depth", "flat_fronto", "near_plane"]


def nc_hard_case(case: str):
    """Nothing valid (0 and a zero gradient), all depth 0, a wall facing the camera, depths at 1e-6 m."""
    normal, depth, K, valid = _nc_case(16, 16, holes=False)
    if case == "no_valid":
        valid = torch.zeros_like(valid)
    elif case == "zero_depth":
        depth = torch.zeros_like(depth)
    elif case == "flat_fronto":
        depth = torch.full_like(depth, 1.5)
    else:
        depth = torch.full_like(depth, 1e-6)
    return normal, depth, K, valid


@pytest.mark.parametrize("case", NC_HARD)
def test_nc_hard_cases_stay_finite(case):
    normal, depth, K, valid = nc_hard_case(case)
    v0, gn0, gd0 = _nc_grads(False, normal, depth, K, valid)
    v1, gn1, gd1 = _nc_grads(True, normal, depth, K, valid)
    assert torch.isfinite(v1) and torch.isfinite(gn1).all() and torch.isfinite(gd1).all()
    assert torch.allclose(v1, v0, atol=1e-12) and torch.allclose(gn1, gn0, atol=1e-12)
    assert torch.allclose(gd1, gd0, rtol=1e-9, atol=1e-9 * max(1.0, float(gd0.abs().max())))


# ---- L_n -----------------------------------------------------------------------------------------

from splat.losses import normal_prior_loss  # noqa: E402


def _np_grads(fused, normal, prior, valid):
    n = normal.clone().requires_grad_(True)
    value = normal_prior_loss(n, prior, valid, fused=fused)
    value.backward()
    return value.detach(), n.grad


def np_case(dtype):
    """Zero (undefined) rendered normals and priors, Inf / NaN prior pixels, masked pixels, and
    components equal to the prior's (sign 0): (normal, prior, valid)."""
    g = torch.Generator().manual_seed(1)
    normal = torch.nn.functional.normalize(torch.randn(30, 40, 3, generator=g, dtype=torch.float64), dim=-1)
    prior = torch.nn.functional.normalize(torch.randn(30, 40, 3, generator=g, dtype=torch.float64), dim=-1)
    normal[:3] = 0.0
    prior[5:7] = 0.0
    prior[8, 3, 1] = float("inf")
    prior[9, 4, 0] = float("nan")
    prior[10, :, 2] = normal[10, :, 2]
    valid = torch.rand(30, 40, generator=g) > 0.3
    return normal.to(dtype), prior.to(dtype), valid


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_normal_prior_matches_the_torch_oracle(dtype):
    normal, prior, valid = np_case(dtype)
    v0, g0 = _np_grads(False, normal, prior, valid)
    v1, g1 = _np_grads(True, normal, prior, valid)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert torch.isfinite(v1) and torch.isfinite(g1).all()
    assert abs(float(v1) - float(v0)) < tol
    assert torch.allclose(g1, g0, atol=tol)


def test_normal_prior_with_nothing_valid_is_zero_with_zero_gradient():
    normal = torch.nn.functional.normalize(torch.randn(8, 8, 3, dtype=torch.float64), dim=-1)
    v, grad = _np_grads(True, normal, normal.flip(0), torch.zeros(8, 8, dtype=torch.bool))
    assert float(v) == 0.0 and not grad.abs().any()
