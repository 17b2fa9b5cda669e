"""Property-based fuzzing of the training losses (splat/losses.py), the priors they read
(splat/views.py) and one full training step (splat/train.py ``train_step``).

Per term (docs/testing.md, "Fuzzing"): finite; bounded -- L_rgb in [0, 1 + λ_dssim] for colours in
[0, 1], L_d in [0, 2], L_n in [0, 2√3], L_s in [min, max] of the masked Gaussians' smallest scales,
L_nc in [0, 2], L_a in [0, max |depth − anchor|]; zero (or minimal) at the optimum (prediction ==
target, prior an increasing affine map of the depth, normals from the depth itself); finite
gradients; float32 within rounding of float64. Priors carry holes (0, the documented invalid
value), spikes, and NaN / ±Inf pixels: a non-finite prior pixel must act exactly like a 0.
"""

from __future__ import annotations

import math
from dataclasses import replace
from unittest import mock

import numpy as np
import pytest
import torch
from hypothesis import assume, event, example, given, note
from hypothesis import strategies as st

import fuzz_strategies as fs
from splat.losses import (LossConfig, anchored_depth_loss, depth_normal_consistency_loss, depth_pcc_loss,
                          depth_to_normal, flatten_loss, normal_prior_loss, rgb_loss, total_loss)

sizes = st.tuples(st.integers(1, 18), st.integers(1, 24))


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def images(h: int, w: int, seed: int, kind: str) -> torch.Tensor:
    """[H, W, 3] float64 colours in [0, 1]: uniform noise, a constant, or saturated 0/1 pixels."""
    g = gen(seed)
    if kind == "noise":
        return torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    if kind == "constant":
        return torch.full((h, w, 3), float(torch.rand(1, generator=g, dtype=torch.float64)), dtype=torch.float64)
    return (torch.rand(h, w, 3, generator=g, dtype=torch.float64) > 0.5).to(torch.float64)


def leaf(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """A fresh leaf copy of ``t`` in ``dtype`` that requires grad (``t`` itself stays untouched)."""
    return t.detach().to(dtype).clone().requires_grad_()


def finite_grad(t: torch.Tensor) -> bool:
    return t.grad is None or bool(torch.isfinite(t.grad).all())


def sanitised(prior: torch.Tensor) -> torch.Tensor:
    """The prior with every non-finite pixel set to 0 (invalid), per pixel (any bad channel)."""
    bad = ~torch.isfinite(prior) if prior.dim() == 2 else ~torch.isfinite(prior).all(-1, keepdim=True)
    return torch.where(bad, torch.zeros_like(prior), prior)


# ------------------------------------------------------------------------------------- L_rgb


@given(hw=sizes, seeds=st.tuples(fs.seeds, fs.seeds), kinds=st.tuples(*[st.sampled_from(("noise", "constant", "binary"))] * 2),
       lam=st.floats(0.0, 1.0))
# property fix: float32 vs float64 within 1e-5 was tighter than float32 SSIM's variance cancellation
@example(hw=(12, 16), seeds=(0, 32382), kinds=("constant", "constant"), lam=1.0)
def test_rgb_loss(hw, seeds, kinds, lam):
    pred64, gt64 = images(*hw, seeds[0], kinds[0]), images(*hw, seeds[1], kinds[1])
    values = {}
    for dtype in (torch.float64, torch.float32):
        pred = leaf(pred64, dtype)
        loss = rgb_loss(pred, gt64.to(dtype), lam)
        loss.backward()
        assert torch.isfinite(loss) and finite_grad(pred)
        values[dtype] = float(loss.detach())
        assert -1e-6 <= values[dtype] <= 1.0 + lam + 1e-6  # L1 in [0, 1], 1 - SSIM in [0, 2]
        assert abs(float(rgb_loss(gt64.to(dtype), gt64.to(dtype), lam))) <= 1e-6  # optimum
    # float32 SSIM: sigma^2 = blur(x^2) - mu^2 cancels to ~2 eps32 = 1.2e-7 absolute, and C2 = 9e-4
    # amplifies that to ~2.7e-4 of 1 - SSIM per pixel (constant images: every pixel alike)
    assert values[torch.float32] == pytest.approx(values[torch.float64], abs=3e-4 * lam + 1e-5)


# --------------------------------------------------------------------------------------- L_d


@given(depth=fs.depth_maps(nan=False), prior=fs.depth_maps(), a=st.floats(1e-3, 1e3), b=st.floats(-10.0, 10.0),
       patch=st.integers(1, 8), n_patches=st.integers(1, 16), seed=fs.seeds)
# regression (fixed in depth_pcc_loss): an Inf prior pixel, invalid, leaked into the patch sums
# through x * 0 = NaN -> NaN loss; and a NaN gradient on a 1x1 image
@example(depth=fs.MapSpec(2, 15), prior=fs.MapSpec(1, 1, infs=1), a=1.0, b=0.0, patch=2, n_patches=1, seed=0)
@example(depth=fs.MapSpec(1, 1), prior=fs.MapSpec(1, 1, infs=1), a=1.0, b=0.0, patch=1, n_patches=1, seed=0)
@example(depth=fs.MapSpec(8, 8), prior=fs.MapSpec(8, 8, nans=1), a=2.0, b=1.0, patch=4, n_patches=4, seed=0)
def test_depth_pcc_loss(depth, prior, a, b, patch, n_patches, seed):
    """[0, 2], finite gradients, 0 when the prior is an increasing affine map of the depth on the
    valid pixels, and invalid prior pixels -- 0, NaN, ±Inf -- change nothing (the PCC "uses only
    the valid pixels of a patch")."""
    d = torch.from_numpy(depth.depth()).double()
    h, w = d.shape
    p = torch.from_numpy(fs.MapSpec(h, w, prior.base_depth, prior.holes, prior.spikes, prior.nans,
                                    prior.infs, prior.seed).depth()).double()
    valid = (p > 0) & torch.isfinite(p) & (d > 0)  # what total_loss passes (prior > 0, rendered > 0)
    event(f"valid pixels: {'none' if not valid.any() else 'all' if valid.all() else 'some'}")
    results = {}
    for dtype in (torch.float64, torch.float32):
        dd = leaf(d, dtype)
        loss = depth_pcc_loss(dd, p.to(dtype), valid, patch, n_patches, gen(seed))
        loss.backward()
        assert torch.isfinite(loss), f"{dtype}: {loss}"
        assert finite_grad(dd), dtype
        assert -1e-6 <= float(loss.detach()) <= 2.0 + 1e-6
        results[dtype] = float(loss.detach())
        # invalid pixels' values are never read: replacing them by 0 gives the same loss
        same = depth_pcc_loss(d.to(dtype), sanitised(p).to(dtype), valid, patch, n_patches, gen(seed))
        assert float(same) == pytest.approx(float(loss.detach()), abs=1e-6)
    # optimum: the prior is a d + b (a > 0) where valid, garbage elsewhere
    affine = torch.where(valid, a * d + b, p)
    opt = depth_pcc_loss(d, affine, valid, patch, n_patches, gen(seed))
    assert float(opt) == pytest.approx(0.0, abs=1e-6)
    assert results[torch.float32] == pytest.approx(results[torch.float64], abs=1e-3)


@pytest.mark.parametrize("scale", [1e-30, 1e-20, 1e12, 1e18, 1e20, 1e30])
def test_depth_pcc_loss_takes_a_prior_of_any_scale(scale):
    """L_d is 0 for a prior that is the depth times any positive factor (its docstring: any scale): in
    float32 vx * vy overflowed from 1e18 (L_d 1, then NaN gradients at 1e20) and vy underflowed at 1e-20
    (every patch 'flat', the term idle). Each patch's prior is rescaled by a power of two (exact)."""
    g = torch.Generator().manual_seed(0)
    depth = (1.0 + torch.rand(32, 32, generator=g)).requires_grad_()
    loss = depth_pcc_loss(depth, depth.detach() * scale, torch.ones(32, 32, dtype=torch.bool), 16, 4,
                          generator=torch.Generator().manual_seed(1))
    loss.backward()
    assert abs(float(loss.detach())) < 1e-6 and torch.isfinite(depth.grad).all()
    anti = depth_pcc_loss(depth.detach(), (3.0 - depth.detach() * 0.5) * scale, torch.ones(32, 32, dtype=torch.bool), 16, 4,
                          generator=torch.Generator().manual_seed(1))
    assert float(anti) == pytest.approx(2.0, abs=1e-5)  # still a correlation: reversed depth is the worst


# --------------------------------------------------------------------------------------- L_n


@given(normal=fs.normal_maps(nan=False), prior=fs.normal_maps(), valid_frac=st.floats(0.0, 1.0), seed=fs.seeds)
# regression (fixed in normal_prior_loss): an Inf prior pixel passed the "not all zero" test -> Inf loss
@example(normal=fs.MapSpec(1, 1), prior=fs.MapSpec(1, 1, infs=1), valid_frac=1.0, seed=0)
def test_normal_prior_loss(normal, prior, valid_frac, seed):
    """[0, 2√3], finite gradients, 0 at prior == normal, non-finite prior pixels act as 0."""
    n = torch.from_numpy(normal.normal()).double()
    h, w, _ = n.shape
    p = torch.from_numpy(fs.MapSpec(h, w, 1.0, prior.holes, prior.spikes, prior.nans, prior.infs,
                                    prior.seed).normal()).double()
    valid = torch.rand(h, w, generator=gen(seed), dtype=torch.float64) < valid_frac
    for dtype in (torch.float64, torch.float32):
        nn_ = leaf(n, dtype)
        loss = normal_prior_loss(nn_, p.to(dtype), valid)
        loss.backward()
        assert torch.isfinite(loss) and finite_grad(nn_)
        assert -1e-6 <= float(loss.detach()) <= 2.0 * math.sqrt(3.0) + 1e-5
        clean = normal_prior_loss(n.to(dtype), sanitised(p).to(dtype), valid)
        assert float(clean) == pytest.approx(float(loss.detach()), abs=1e-6)
        assert float(normal_prior_loss(n.to(dtype), n.to(dtype), valid)) == 0.0


# --------------------------------------------------------------------------------------- L_s


@given(log_scales=st.lists(st.tuples(*[st.floats(-40.0, 40.0)] * 3), max_size=64),
       mask_seed=fs.seeds, frac=st.floats(0.0, 1.0))
def test_flatten_loss(log_scales, mask_seed, frac):
    """Between the smallest and largest masked exp(min log-scale) (0 with an empty mask), finite
    gradients, float32 within 1e-5 relative of float64, and smaller when the scales shrink."""
    s = torch.tensor(log_scales, dtype=torch.float64).reshape(-1, 3)
    mask = torch.rand(len(s), generator=gen(mask_seed), dtype=torch.float64) < frac
    smallest = s.min(1).values.exp()[mask]
    lo, hi = (float(smallest.min()), float(smallest.max())) if mask.any() else (0.0, 0.0)
    for dtype, rel in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        ss = leaf(s, dtype)
        loss = flatten_loss(ss, mask)
        loss.backward()
        assert torch.isfinite(loss) and finite_grad(ss)
        assert lo * (1 - rel) <= float(loss.detach()) <= hi * (1 + rel)
    shrunk = flatten_loss(s - 1.0, mask)
    assert float(shrunk) <= float(flatten_loss(s, mask))


# ------------------------------------------------------------------------- depth -> normal, L_nc


def plane_view(cam: fs.CameraSpec, normal, offset: float):
    """z-depth [H, W] (float64, 0 where the plane is behind or parallel) of the plane n . X = offset
    (camera frame), and the normal facing the camera."""
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    u = np.arange(cam.width) + 0.5
    v = np.arange(cam.height) + 0.5
    rx = ((u[None, :] - cam.cx) / cam.fx) * np.ones((cam.height, 1))
    ry = ((v[:, None] - cam.cy) / cam.fy) * np.ones((1, cam.width))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        z = offset / (n[0] * rx + n[1] * ry + n[2])
    z = np.where(np.isfinite(z) & (z > 0) & (z < 1e4), z, 0.0)
    return z, (n if offset < 0 else -n)  # n . X = offset < 0: n points towards the camera


@given(cam=fs.cameras(min_focal=1.0, max_focal=1e5, far_centre=False),
       normal=fs.directions(),
       offset=st.floats(0.1, 100.0).flatmap(lambda x: st.sampled_from((x, -x))))
# property fixes: the angle error was measured with arccos, which turns a float rounding of the
# cosine (1 - 1e-16 in float64, 1 - 6e-8 in float32) into 1.5e-8 / 3.4e-4 rad; now the chord
@example(cam=fs.CameraSpec(3, 3, 1.0, 1.0, 1.5, 1.5), normal=(0.0, 0.0, 1.0), offset=0.109375)
@example(cam=fs.CameraSpec(3, 8, 1.0, 1.0, 1.5, 4.0), normal=(0.0, 1.0, 0.0), offset=1.0)
def test_depth_to_normal_is_exact_on_planes(cam, normal, offset):
    """float64: the plane's normal (facing the camera) wherever it is defined, within rounding
    amplified by the geometry's conditioning; float32: unit or zero, and within its own rounding
    of the float64 result."""
    z, n_true = plane_view(cam, normal, offset)
    K = torch.tensor(cam.K)
    out64 = depth_to_normal(torch.from_numpy(z), K).numpy()
    out32 = depth_to_normal(torch.from_numpy(z).float(), K.float()).double().numpy()
    has = np.abs(out64).sum(-1) > 0
    event("normals defined: " + ("none" if not has.any() else "some"))
    # conditioning: |X|^2 / |dX_u x dX_v| at each pixel (the cross product of two in-plane
    # differences, each rounded relative to |X|)
    u = np.arange(cam.width) + 0.5
    v = np.arange(cam.height) + 0.5
    X = np.stack([((u[None, :] - cam.cx) / cam.fx) * z, ((v[:, None] - cam.cy) / cam.fy) * z, z], -1)
    cond = np.ones(z.shape)
    if min(z.shape) >= 3:
        dx, dy = X[1:-1, 2:] - X[1:-1, :-2], X[2:, 1:-1] - X[:-2, 1:-1]
        cross = np.linalg.norm(np.cross(dx, dy), axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            cond[1:-1, 1:-1] = np.where(cross > 0, (X[1:-1, 1:-1] ** 2).sum(-1) * 4 / cross, np.inf)
    err = np.linalg.norm(out64 - n_true, axis=-1)  # chord ~ angle (arccos near 1 is ill-conditioned)
    ok = err <= 1e-13 * cond + 1e-9
    assert ok[has].all(), (err[has][~ok[has]][:3], cond[has][~ok[has]][:3])
    norms32 = np.linalg.norm(out32, axis=-1)
    assert ((norms32 == 0) | (np.abs(norms32 - 1) < 1e-5)).all()
    both = has & (norms32 > 0)
    err32 = np.linalg.norm(out32 - n_true, axis=-1)
    good = err32 <= 1e-5 * cond + 1e-4
    assert good[both].all(), (err32[both][~good[both]][:3], cond[both][~good[both]][:3])


@given(cam=fs.cameras(far_centre=False), depth=fs.depth_maps(nan=False, min_side=1), seed=fs.seeds,
       detach=st.booleans())
def test_depth_normal_consistency_loss(cam, depth, seed, detach):
    """[0, 2], finite gradients into normals and depth (holes, spikes, extreme intrinsics), and 0
    when the rendered normals are the depth's own normals."""
    d = torch.from_numpy(fs.MapSpec(cam.height, cam.width, depth.base_depth, depth.holes, depth.spikes,
                                    0, 0, depth.seed).depth()).double()
    K = torch.tensor(cam.K)
    normal = torch.nn.functional.normalize(torch.randn(cam.height, cam.width, 3, generator=gen(seed),
                                                       dtype=torch.float64), dim=-1)
    valid = torch.rand(cam.height, cam.width, generator=gen(seed + 1), dtype=torch.float64) < 0.8
    for dtype in (torch.float64, torch.float32):
        n_leaf = leaf(normal, dtype)
        d_leaf = leaf(d, dtype)
        loss = depth_normal_consistency_loss(n_leaf, d_leaf, K.to(dtype), valid, detach)
        loss.backward()
        assert torch.isfinite(loss) and finite_grad(n_leaf) and finite_grad(d_leaf), dtype
        assert -1e-6 <= float(loss.detach()) <= 2.0 + 1e-6
        own = depth_to_normal(d.to(dtype), K.to(dtype))
        assert abs(float(depth_normal_consistency_loss(own, d.to(dtype), K.to(dtype), valid))) <= 1e-5


# --------------------------------------------------------------------------------------- L_a


@given(depth=fs.depth_maps(nan=False), anchor=fs.depth_maps(), tol=st.floats(0.0, 1.0))
# regression (fixed in anchored_depth_loss): an Inf anchor pixel passed anchor > 0 -> Inf loss
@example(depth=fs.MapSpec(1, 2), anchor=fs.MapSpec(1, 1, infs=1), tol=0.0)
def test_anchored_depth_loss(depth, anchor, tol):
    """In [0, max |depth − anchor|] over the used pixels, finite gradients, 0 at depth == anchor,
    non-finite anchor pixels act as 0 (invalid)."""
    d = torch.from_numpy(depth.depth()).double()
    h, w = d.shape
    a = torch.from_numpy(fs.MapSpec(h, w, anchor.base_depth, anchor.holes, anchor.spikes, anchor.nans,
                                    anchor.infs, anchor.seed).depth()).double()
    valid = d > 0  # total_loss: covered & rendered depth > 0
    used = valid & (sanitised(a) > 0)
    bound = float((d - a).abs()[used].max()) if used.any() else 0.0
    for dtype in (torch.float64, torch.float32):
        dd = leaf(d, dtype)
        loss = anchored_depth_loss(dd, a.to(dtype), valid, tol)
        loss.backward()
        assert torch.isfinite(loss) and finite_grad(dd), dtype
        assert 0.0 <= float(loss.detach()) <= bound * (1 + 1e-6) + 1e-6
        clean = anchored_depth_loss(d.to(dtype), sanitised(a).to(dtype), valid, tol)
        assert float(clean) == pytest.approx(float(loss.detach()), rel=1e-6, abs=1e-6)
    assert float(anchored_depth_loss(d, d, valid, tol)) == 0.0


# ------------------------------------------------------------------------------------ total


@given(cam=fs.cameras(far_centre=False), rendered=fs.depth_maps(nan=False), depth_prior=fs.depth_maps(),
       normal_prior=fs.normal_maps(), anchor=fs.depth_maps(), seed=fs.seeds,
       log_scales=st.lists(st.tuples(*[st.floats(math.log(1e-8), math.log(1e3))] * 3), min_size=1, max_size=32),
       with_priors=st.tuples(st.booleans(), st.booleans(), st.booleans()), p90=st.floats(0.0, 1.0))
# regressions (fixed in total_loss / the terms): an Inf depth prior pixel passed prior > 0 (NaN
# gradient of the depth); an Inf anchor pixel (Inf L_a); a NaN prior pixel leaked into L_d
@example(cam=fs.CameraSpec(1, 1, 1.0, 1.0, 0.5, 0.5), rendered=fs.MapSpec(1, 1), depth_prior=fs.MapSpec(1, 1, infs=1),
         normal_prior=fs.MapSpec(1, 1), anchor=fs.MapSpec(1, 1), seed=0, log_scales=[(0.0, 0.0, 0.0)],
         with_priors=(True, False, False), p90=0.0)
@example(cam=fs.CameraSpec(2, 2, 4.0, 4.0, 1.0, 1.0), rendered=fs.MapSpec(2, 2), depth_prior=fs.MapSpec(2, 2),
         normal_prior=fs.MapSpec(2, 2), anchor=fs.MapSpec(2, 2, infs=1), seed=0, log_scales=[(0.0, 0.0, 0.0)],
         with_priors=(False, False, True), p90=0.0)
@example(cam=fs.CameraSpec(8, 8, 10.0, 10.0, 4.0, 4.0), rendered=fs.MapSpec(8, 8), depth_prior=fs.MapSpec(8, 8, nans=1),
         normal_prior=fs.MapSpec(8, 8, nans=1), anchor=fs.MapSpec(8, 8, nans=1), seed=0, log_scales=[(0.0, 0.0, 0.0)],
         with_priors=(True, True, True), p90=0.0)
def test_total_loss(cam, rendered, depth_prior, normal_prior, anchor, seed, log_scales, with_priors, p90):
    """Every term finite and within its bound, total = Σ λ term, finite gradients into every render
    output and the scales, and non-finite prior pixels act as 0."""
    h, w = cam.height, cam.width
    spec = lambda m: fs.MapSpec(h, w, m.base_depth, m.holes, m.spikes, m.nans, m.infs, m.seed)  # noqa: E731
    g = gen(seed)
    out = {"rgb": torch.rand(h, w, 3, generator=g),
           "depth": torch.from_numpy(spec(rendered).depth()),
           "normal": torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g), dim=-1),
           "alpha": torch.rand(h, w, generator=g)}
    out["normal"] = torch.where(out["alpha"][..., None] > 0.1, out["normal"], torch.zeros_like(out["normal"]))
    out = {k: v.requires_grad_() for k, v in out.items()}
    scales = torch.tensor(log_scales, dtype=torch.float32).requires_grad_()
    cue_type = torch.randint(0, 3, (len(scales),), generator=g)
    priors = dict(depth_prior=torch.from_numpy(spec(depth_prior).depth()) if with_priors[0] else None,
                  normal_prior=torch.from_numpy(spec(normal_prior).normal()) if with_priors[1] else None,
                  depth_anchor=torch.from_numpy(spec(anchor).depth()) if with_priors[2] else None)
    cfg = LossConfig(patch_size=4, n_patches=8, nc_from_iter=0)
    gt = torch.rand(h, w, 3, generator=g)
    K = torch.tensor(cam.K, dtype=torch.float32)
    total, terms = total_loss(out, gt, K, {"scales": scales}, cue_type, cfg, 10, generator=gen(seed),
                              anchor_p90=p90, **priors)
    total.backward()
    assert all(math.isfinite(v) for v in terms.values()), terms
    bounds = {"rgb": 1 + cfg.lambda_dssim, "depth": 2.0, "normal": 2 * math.sqrt(3), "nc": 2.0,
              "flat": 1e3, "anchor": math.inf}
    for key, value in terms.items():
        if key != "total":
            assert -1e-5 <= value <= bounds[key] + 1e-5, (key, value)
    weights = {"rgb": 1.0, "depth": cfg.lambda_depth, "normal": cfg.lambda_normal, "flat": cfg.lambda_flat,
               "nc": cfg.lambda_nc, "anchor": cfg.lambda_anchor}
    expected = sum(weights[k] * v for k, v in terms.items() if k != "total")
    assert terms["total"] == pytest.approx(expected, rel=1e-5, abs=1e-6)
    for key, leaf in (*out.items(), ("scales", scales)):
        assert finite_grad(leaf), f"non-finite gradient of {key}"
    clean = {k: None if v is None else sanitised(v) for k, v in priors.items()}
    _, clean_terms = total_loss({k: v.detach() for k, v in out.items()}, gt, K, {"scales": scales.detach()},
                                cue_type, cfg, 10, generator=gen(seed), anchor_p90=p90, **clean)
    for key in terms:
        assert clean_terms[key] == pytest.approx(terms[key], rel=1e-5, abs=1e-6), key


# ------------------------------------------------------------------------- priors of a View


class FakeScene:
    """Duck-typed like geocues.scene.Scene for ViewSet: one camera, a black image, given priors."""

    def __init__(self, cam: fs.CameraSpec, depth: np.ndarray, normal: np.ndarray):
        self.cameras = [cam.scene_camera(0)]
        self._depth, self._normal = depth, normal

    def load_image(self, i: int) -> np.ndarray:
        return np.zeros((self.cameras[i].height, self.cameras[i].width, 3), np.float32)

    def depth_prior(self, i: int) -> np.ndarray:
        return self._depth

    def normal_prior(self, i: int) -> np.ndarray:
        return self._normal


@given(cam=fs.cameras(far_centre=False), prior=fs.depth_maps(nan=False), unit=fs.log_uniform(1e-6, 1e6),
       scale=fs.log_uniform(1e-3, 1e3), shift=st.floats(-1.0, 1.0))
# regressions (fixed in splat/views.py): float16 storage turned an anchor of 1e5 m into Inf, and
# lost 0.7 % of a 1e-6 prior (values below float16's normal range; below ~6e-8 they became 0 = invalid)
@example(cam=fs.CameraSpec(1, 1, 1.0, 1.0, 0.5, 0.5), prior=fs.MapSpec(1, 1), unit=100.0, scale=1000.0, shift=0.0)
@example(cam=fs.CameraSpec(1, 1, 1.0, 1.0, 0.5, 0.5), prior=fs.MapSpec(1, 1), unit=0.001, scale=0.001, shift=0.0)
@example(cam=fs.CameraSpec(2, 1, 1.0, 1.0, 1.0, 0.5), prior=fs.MapSpec(1, 2), unit=1e-6, scale=1.0, shift=0.0)
def test_view_priors_keep_valid_pixels_finite_and_valid(cam, prior, unit, scale, shift):
    """A prior as Scene hands it over (finite, 0 = invalid; any units: "any positive scale" for
    L_d) comes out of a View with every valid pixel still valid and finite, within float16's
    relative precision, and so does its cue-aligned anchor."""
    from geocues.depth_align import DepthAlignment
    from splat.views import ViewSet

    spec = fs.MapSpec(cam.height, cam.width, prior.base_depth, prior.holes, prior.spikes, 0, 0, prior.seed)
    d = (spec.depth() * unit).astype(np.float32)
    d[~np.isfinite(d)] = 0.0  # Scene.depth_prior's guarantee
    assume((d > 0).any())
    normal = spec.normal()
    normal[~np.isfinite(normal).all(-1)] = 0.0
    al = DepthAlignment(index=0, ok=True, scale=scale, shift=shift, width=cam.width, height=cam.height)
    with mock.patch("splat.views.tqdm", lambda it, **kw: it):  # no progress bar per example
        view = ViewSet(FakeScene(cam, d, normal), [0], alignments={"00000.png": al})[0]
    for name, got, want in (("depth_prior", view.depth_prior, d), ("depth_anchor", view.depth_anchor, al.apply(d))):
        got = got.double().numpy()
        valid = want > 0
        assert np.isfinite(got).all(), f"{name}: non-finite values {got[~np.isfinite(got)][:3]}"
        assert (got[valid] > 0).all(), f"{name}: valid pixels turned invalid: {want[valid][got[valid] <= 0][:3]}"
        np.testing.assert_allclose(got[valid], want[valid], rtol=1e-3, err_msg=name)
        assert (got[~valid] == 0).all(), name


# --------------------------------------------------------------------------- one training step


@given(cam=fs.cameras(max_width=16, max_height=12, min_focal=1.0, max_focal=1e4),
       gs=fs.gaussians(min_n=1, max_n=16, valid=True), backend=st.sampled_from(("torch", "cpu")),
       step=st.sampled_from((0, 600, 3000, 4000, 11_900)), priors=st.tuples(st.booleans(), st.booleans(), st.booleans()),
       maps=fs.depth_maps(), seed=fs.seeds)
def test_train_step_keeps_parameters_and_adam_moments_finite(cam, gs, backend, step, priors, maps, seed):
    """One full train_step (render, all loss terms, backward, Adam, density control at refine /
    reset steps), WITHOUT the numerics guard, on a fuzzed but valid tiny scene (log-scales within
    log 1e-8..log 1e3, priors with holes and NaN / Inf pixels): the loss and every parameter and
    Adam moment stay finite, and the per-Gaussian state stays aligned."""
    from splat.composite import cpu_backend_available
    from splat.strategy import IndoorStrategy, IndoorStrategyConfig
    from splat.train import LearningRates, TrainConfig, make_optimizers, train_step
    from splat.views import View

    if backend == "cpu" and not cpu_backend_available():
        backend = "torch"
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in gs.build(cam).items()})
    optimizers = make_optimizers(params, LearningRates(), 1.0)
    strategy = IndoorStrategy(IndoorStrategyConfig(max_gaussians=0))  # the paper's 30k schedule: step picks the phase
    state = strategy.initialize_state(1.0)
    g = gen(seed)
    state["cue_type"] = torch.randint(0, 3, (gs.n,), generator=g)
    h, w = cam.height, cam.width
    spec = fs.MapSpec(h, w, maps.base_depth, maps.holes, maps.spikes, maps.nans, maps.infs, maps.seed)
    view = View(index=0, name="fuzz.png", camera=cam.build(), rgb=torch.rand(h, w, 3, generator=g),
                depth_prior=torch.from_numpy(spec.depth()) if priors[0] else None,
                normal_prior=torch.from_numpy(spec.normal()) if priors[1] else None,
                depth_anchor=torch.from_numpy(spec.depth()) if priors[2] else None, anchor_p90=0.05)
    cfg = TrainConfig(iters=30_000, backend=backend, sh_degree=gs.sh_degree)
    loss_cfg = replace(LossConfig(patch_size=4, n_patches=4), nc_from_iter=0)
    loss, terms, density = train_step(params, optimizers, strategy, state, view, step, gs.sh_degree, cfg,
                                      loss_cfg, gen(seed + 1), guard=None)
    event(f"density control: {'ran' if density else 'idle'}")
    assert math.isfinite(float(loss)) and all(math.isfinite(v) for v in terms.values()), terms
    n = params["means"].shape[0]
    for key, p in params.items():
        assert torch.isfinite(p).all(), f"non-finite parameter {key}"
        assert p.shape[0] == n, key
        for name, moment in optimizers[key].state.get(p, {}).items():
            if isinstance(moment, torch.Tensor) and moment.dim() > 0:
                assert torch.isfinite(moment).all(), f"non-finite Adam {name} of {key}"
                assert moment.shape == p.shape, (key, name)
    assert state["cue_type"].shape == (n,)
