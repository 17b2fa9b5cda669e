"""Property-based fuzzing of the rasterizer: projection, both compositing backends, render().

Properties (docs/testing.md, "Fuzzing"); inputs from tests/fuzz_strategies.py:
- quaternion -> rotation: orthonormal and independent of the quaternion's scale (float32);
- projection: finite values and gradients, opacities in [0, 1], radii >= 0 (float32, both
  backends); the C++ projection equals the torch one in float64 (test_project_cpu tolerances);
- compositing: both backends equal a float64 numpy implementation of the per-pixel rule of
  splat/composite.py (values, n_contrib, median exactly); float32 within the oracle's first-order
  float32 error bound wherever no decision can flip; finite gradients, equal across backends;
- render: finite maps and gradients, alpha in [0, 1], unit normals or zeros (float32); in float64
  the backends agree, and the RaDe-GS depth at a pixel with non-negligible alpha lies within
  [min, max] of the depth planes of the Gaussians blended there, the median depth on the plane of
  the Gaussian where T crosses 0.5.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pytest
import torch
from hypothesis import event, example, given, note
from hypothesis import strategies as st

import fuzz_strategies as fs
from splat.composite import composite, cpu_backend_available
from splat.projection import ProjectionConfig, project_gaussians, quat_to_rotmat
from splat.rasterize import pixel_centres, render

BACKENDS = ["torch"] + (["cpu"] if cpu_backend_available() else [])
PROJ_OUTPUTS = ("means2d", "conics", "depths", "opacities", "colors", "depth_slopes", "normals")
MAPS = ("rgb", "depth", "median_depth", "normal", "alpha")

ALPHA_MIN, ALPHA_MAX, T_MIN = 1.0 / 255.0, 0.99, 1e-4


def random_weights(tensors, seed: int = 7):
    """A fixed random projection per output (float64 draws, cast): one backward covers them all."""
    gen = torch.Generator().manual_seed(seed)
    return [torch.randn(t.shape, generator=gen, dtype=torch.float64).to(t.dtype) for t in tensors]


def bucket(name: str, value: int) -> None:
    """Record a coarse size of ``value`` as a hypothesis event (--hypothesis-show-statistics)."""
    event(f"{name}: " + ("0" if value == 0 else "1-9" if value < 10 else "10+"))


def tmax(t: torch.Tensor) -> float:
    """max |t| as a float, 0 for an empty tensor."""
    return float(t.detach().abs().max()) if t.numel() else 0.0


def assert_grads_close(names, grads, ref_grads, rtol: float):
    """Gradients of two backends agree within rtol of each parameter's largest gradient, plus a
    floor of rtol x 1e-3 x the largest gradient of any parameter: a gradient that is 0 in exact
    arithmetic (d/dquat of an isotropic Gaussian) is 0 in one backend and rounding noise of the
    other parameters' magnitude (1e-14 of it) in the other."""
    pairs = [(n, a, b) for n, a, b in zip(names, grads, ref_grads) if a is not None or b is not None]
    for name, a, b in pairs:
        assert a is not None and b is not None, f"d {name}: None in one backend only"
    top = max([tmax(b) for _, _, b in pairs], default=0.0)
    for name, a, b in pairs:
        torch.testing.assert_close(a, b, rtol=rtol, atol=rtol * (tmax(b) + 1e-3 * top) + 1e-300,
                                   msg=lambda m: f"d {name}: {m}")


def weighted_sum(tensors, weights):
    return sum((t * w).sum() for t, w in zip(tensors, weights))


def assert_unit_or_zero(normals: torch.Tensor, tol: float):
    norms = torch.linalg.vector_norm(normals.detach().double(), dim=-1)
    bad = (norms > tol) & ((norms - 1.0).abs() > tol)
    assert not bool(bad.any()), f"normals neither unit nor zero: {norms[bad][:5].tolist()}"


# --------------------------------------------------------------------------- float64 oracle


class Oracle(NamedTuple):
    """What :func:`composite_oracle` returns (P = H * W pixels, N Gaussians)."""

    features: np.ndarray  # [H, W, C]
    alpha: np.ndarray  # [H, W]
    median: np.ndarray  # [H, W, M]
    n_contrib: np.ndarray  # [H, W]
    weights: np.ndarray  # [P, N] alpha * T of each blended Gaussian, 0 elsewhere
    err_features: np.ndarray  # [H, W] bound on |float32 result - this| of any feature channel
    err_alpha: np.ndarray  # [H, W] the same for alpha
    flip_free: bool  # no decision (skip, stop, median) lies within 3x its float32 error of its threshold


EPS32 = 2.0 ** -24  # float32 unit roundoff


def composite_oracle(means2d, conics, opac, feats, depths, radii, width, height, bg=None, medf=None) -> Oracle:
    """The per-pixel rule of splat/composite.py in numpy float64, vectorised over pixels, with a
    first-order bound on the error of the same rule evaluated in float32.

    Error model per blended Gaussian k: the power has absolute error dp = 4 eps (S + |dpower/dmx| |mx|
    + |dpower/dmy| |my|), S = the magnitudes of its three terms (cancellation in needles, rounding
    of the 2D mean far from 0), so alpha has relative error dk = dp + 4 eps; T accumulates
    rho += alpha dk / (1 - alpha) + eps; a feature's weight alpha T has relative error dk + rho.
    A decision can flip in float32 only within (about) that error of its threshold; ``flip_free``
    says none lies within 3x of it.
    """
    m, q, o = (np.asarray(t.detach().double(), np.float64) for t in (means2d, conics, opac))
    f = np.asarray(feats.detach().double(), np.float64)
    z, r = np.asarray(depths.detach().double()), np.asarray(radii, np.float64)
    n, c = f.shape
    medf = np.zeros((n, 0)) if medf is None else np.asarray(medf.detach().double())
    bg = np.zeros(c) if bg is None else np.asarray(bg.detach().double())
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    px, py = xs.ravel(), ys.ravel()
    npix = px.size
    T = np.ones(npix)
    out = np.zeros((npix, c))
    med = np.zeros((npix, medf.shape[1]))
    weights = np.zeros((npix, n))
    done = np.zeros(npix, bool)
    count = np.zeros(npix, np.int64)
    rho = np.zeros(npix)  # relative error bound of T
    err_f = np.zeros(npix)  # absolute error bound of the features
    flip_free = True
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        for g in np.lexsort((np.arange(n), z)):  # ascending depth, ties by index
            if r[g] <= 0:
                continue
            touch = ~done & (np.abs(px - m[g, 0]) <= r[g]) & (np.abs(py - m[g, 1]) <= r[g])
            if not touch.any():
                continue
            dx, dy = m[g, 0] - px, m[g, 1] - py
            power = -0.5 * (q[g, 0] * dx * dx + q[g, 2] * dy * dy) - q[g, 1] * dx * dy
            raw = o[g] * np.exp(np.minimum(power, 0.0))
            alpha = np.minimum(ALPHA_MAX, raw)
            ok = touch & (power <= 0) & (alpha >= ALPHA_MIN)
            test_t = T * (1.0 - alpha)
            stop = ok & (test_t < T_MIN)
            size = 0.5 * np.abs(q[g, 0]) * dx * dx + 0.5 * np.abs(q[g, 2]) * dy * dy + np.abs(q[g, 1] * dx * dy)
            slope = (np.abs(q[g, 0] * dx + q[g, 1] * dy) * abs(m[g, 0]) + np.abs(q[g, 1] * dx + q[g, 2] * dy) * abs(m[g, 1]))
            dp = 4.0 * EPS32 * (size + slope)
            dk = dp + 4.0 * EPS32
            d_test = rho + alpha * dk / (1.0 - alpha) + EPS32
            # alpha >= 1/255  <=>  power >= -log(255 o): compared in log space (raw may underflow to 0)
            log_gap = np.abs(power + np.log(np.maximum(255.0 * o[g], 1e-300))) if o[g] > 0 else np.inf
            near = touch & ((np.abs(power) < 3.0 * dp) & (power != 0) | (power <= 0) & (log_gap <= 3.0 * dk))
            near |= ok & ((np.abs(test_t / T_MIN - 1.0) <= 3.0 * d_test) | (np.abs(T / 0.5 - 1.0) <= 3.0 * rho)
                          | (np.abs(test_t / 0.5 - 1.0) <= 3.0 * d_test))
            flip_free &= not near.any()
            done |= stop
            ok &= ~stop
            w = alpha * T
            out[ok] += f[g] * w[ok, None]
            err_f[ok] += np.abs(f[g]).max(initial=0.0) * w[ok] * (dk[ok] + rho[ok] + 4.0 * EPS32)
            weights[ok, g] = w[ok]
            cross = ok & (T > 0.5) & (test_t <= 0.5)
            med[cross] = medf[g]
            rho = np.where(ok, d_test, rho)
            T = np.where(ok, test_t, T)
            count += ok
    out += T[:, None] * bg
    err_f += T * rho * np.abs(bg).max(initial=0.0) + 4.0 * EPS32 * np.abs(out).max(-1, initial=0.0)
    hw = (height, width)
    return Oracle(out.reshape(*hw, c), (1.0 - T).reshape(hw), med.reshape(*hw, -1), count.reshape(hw), weights,
                  err_f.reshape(hw), (T * rho + EPS32).reshape(hw), bool(flip_free))


# ------------------------------------------------------------------------------- quaternions


@given(q=fs.unit_quats(), scale=fs.log_uniform(1e-5, 1e15))
def test_quat_to_rotmat_is_a_rotation_for_any_quaternion_scale(q, scale):
    """float32: q and s q give the same orthonormal rotation for s in [1e-5, 1e15] (below, the
    normalisation epsilon blends towards the identity by design; above, |q|^2 overflows)."""
    unit = torch.tensor([q], dtype=torch.float32)
    R1 = quat_to_rotmat(unit)[0].double()
    R2 = quat_to_rotmat(unit * scale)[0].double()
    torch.testing.assert_close(R2, R1, rtol=0, atol=1e-5)
    torch.testing.assert_close(R1 @ R1.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-5)
    assert float(torch.linalg.det(R1)) == pytest.approx(1.0, abs=1e-5)


@given(q=st.tuples(*[st.floats(-1e30, 1e30, allow_nan=False)] * 4))
def test_quat_to_rotmat_is_finite_for_zero_tiny_and_huge_quaternions(q):
    R = quat_to_rotmat(torch.tensor([q], dtype=torch.float32))
    assert torch.isfinite(R).all()


# -------------------------------------------------------------------------------- projection


@given(cam=fs.cameras(), gs=fs.gaussians(max_n=48), antialiased=st.booleans())
# an explicit hard case: every extreme at once on a 4x3 image with a 0.1 px focal length
@example(cam=fs.CameraSpec(4, 3, 0.1, 0.1, 2.0, 1.5), antialiased=False,
         gs=fs.GaussianSpec(("front", "on_near", "straddle"), ("plus40", "minus40", "huge"),
                            ("huge", "zero", "tiny"), ("plus50", "minus50", "normal")))
# property fix: d/dquat of an isotropic Gaussian is 0 in torch, 1.8e-16 in C++ (rounding): the
# gradient tolerance now has a floor relative to the largest gradient (assert_grads_close)
@example(cam=fs.CameraSpec(1, 1, 1.0, 1.0, 0.5, 0.5), antialiased=False,
         gs=fs.GaussianSpec(("front",), ("plus40",), ("random",), ("normal",)))
# regression (fixed in splat/projection.py): a Gaussian whose viewing ray is perpendicular to its
# smallest axis, the other axes 1e7 times larger, has a RaDe-GS plane normal n ~ 1e-13 before
# normalising; rsqrt's backward overflowed float32 there: NaN gradients of slopes and normals (torch)
@example(cam=fs.CameraSpec(1, 1, 1e5, 1e5, 0.5, 0.5, center=(1025.0, 1024.0, 0.0)), antialiased=False,
         gs=fs.GaussianSpec(("front",), ("mixed",), ("zero",), ("normal",), seed=258))
def test_projection_is_finite_and_backends_agree(cam, gs, antialiased):
    """float32: finite outputs and gradients for both backends, opacities in [0, 1], radii >= 0;
    float64: the C++ projection equals the torch projection (test_project_cpu's tolerances:
    values rtol 1e-11 / atol 1e-12, gradients rtol 1e-9 / atol 1e-9 x max)."""
    cfg = ProjectionConfig(antialiased=antialiased)
    results = {}
    for dtype in (torch.float32, torch.float64):
        camera = cam.build(dtype)
        for backend in BACKENDS:
            leaves = {k: v.requires_grad_() for k, v in gs.build(cam, dtype).items()}
            proj = project_gaussians(leaves, camera, config=cfg, backend=backend)
            outs = [getattr(proj, k) for k in PROJ_OUTPUTS]
            grads = torch.autograd.grad(weighted_sum(outs, random_weights(outs)), list(leaves.values()),
                                        allow_unused=True)
            grads = [torch.zeros_like(v) if g is None else g for g, v in zip(grads, leaves.values())]
            for name, t in zip(PROJ_OUTPUTS, outs):
                assert torch.isfinite(t).all(), f"{backend} {dtype}: non-finite {name}"
            for key, g in zip(leaves, grads):
                assert torch.isfinite(g).all(), f"{backend} {dtype}: non-finite gradient of {key}"
            assert bool((proj.radii >= 0).all())
            assert bool(((proj.opacities >= 0) & (proj.opacities <= 1)).all())
            assert_unit_or_zero(proj.normals[proj.radii > 0], 1e-4)
            results[backend, dtype] = (proj, outs, grads)
    if "cpu" not in BACKENDS:
        return
    (ref, ref_outs, ref_grads), (out, outs, grads) = results["torch", torch.float64], results["cpu", torch.float64]
    assert torch.equal(out.radii, ref.radii)
    for name, a, b in zip(PROJ_OUTPUTS, outs, ref_outs):
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-12, msg=lambda m: f"{name}: {m}")
    assert_grads_close(("means", "quats", "scales", "opacities", "sh0", "shN"), grads, ref_grads, 1e-9)


# ------------------------------------------------------------------------------- compositing


@given(spec=fs.splats2d())
@example(spec=fs.Splat2DSpec(1, 1, (), (), (), (), n_features=3, n_median=1))  # empty scene
# property fix: a needle with opacity 1 (alpha 0.98, 1 / (1 - alpha) = 50) made float32 differ from
# the rule by 1.2e-5 in alpha, over a fixed 1e-5 tolerance; float32 is now held to the oracle's bound
@example(spec=fs.Splat2DSpec(12, 9, ("pixel_centre", "near_edge", "inside", "far") + ("inside",) * 5,
                             ("normal", "needle") + ("normal",) * 7, ("normal", "one") + ("normal",) * 7, ("fit",) * 9,
                             n_features=3, n_median=1, depth_ties=False, seed=3))
def test_composite_matches_float64_oracle(spec):
    """Both backends follow the per-pixel rule (float64: to rounding, n_contrib and median exact;
    float32: finite, alpha in [0, 1], and where no decision lies within its float32 error of a
    threshold, the same decisions and values within the oracle's float32 error bound); gradients
    finite and equal across backends (test_composite_cpu's tolerances)."""
    means, conics, opac, feats, depths, radii, bg, medf = spec.build(torch.float64)
    ref = composite_oracle(means, conics, opac, feats, depths, radii, spec.width, spec.height, bg, medf)
    note(f"float32 error bounds: features {ref.err_features.max(initial=0):.3g}, alpha {ref.err_alpha.max(initial=0):.3g}")
    bucket("blended pairs", int(ref.n_contrib.sum()))
    event("float32 compared to its error bound" if ref.flip_free else "float32 may flip a decision")
    grads = {}
    for dtype in (torch.float64, torch.float32):
        for backend in BACKENDS:
            leaves = [t.to(dtype).requires_grad_() for t in (means, conics, opac, feats, bg, medf)]
            m2, con, op, ft, b, mf = leaves
            out = composite(m2, con, op, ft, depths.to(dtype), radii, spec.width, spec.height, background=b,
                            median_features=mf, backend=backend, max_per_pixel=1024)
            for name, t in (("features", out.features), ("alpha", out.alpha), ("median", out.median)):
                assert torch.isfinite(t).all(), f"{backend} {dtype}: non-finite {name}"
            assert bool(((out.alpha >= 0) & (out.alpha <= 1)).all())
            outs = [out.features, out.alpha, out.median]
            g = torch.autograd.grad(weighted_sum(outs, random_weights(outs)), leaves, allow_unused=True)
            g = [torch.zeros_like(v) if gi is None else gi for gi, v in zip(g, leaves)]
            for name, gi in zip(("means2d", "conics", "opacities", "features", "background", "median"), g):
                assert torch.isfinite(gi).all(), f"{backend} {dtype}: non-finite gradient of {name}"
            if dtype == torch.float64:
                assert np.array_equal(out.n_contrib.numpy(), ref.n_contrib), backend
                np.testing.assert_allclose(out.features.detach().numpy(), ref.features, rtol=1e-12, atol=1e-12)
                np.testing.assert_allclose(out.alpha.detach().numpy(), ref.alpha, rtol=1e-12, atol=1e-12)
                np.testing.assert_array_equal(out.median.detach().numpy(), ref.median)
                grads[backend] = g
            elif ref.flip_free:  # float32 takes the same decisions: within its error bound of the rule
                assert np.array_equal(out.n_contrib.numpy(), ref.n_contrib), backend
                diff_f = np.abs(out.features.detach().double().numpy() - ref.features).max(-1, initial=0.0)
                diff_a = np.abs(out.alpha.detach().double().numpy() - ref.alpha)
                assert (diff_f <= 2.0 * ref.err_features + 1e-6).all(), (backend, diff_f.max(), ref.err_features.max())
                assert (diff_a <= 2.0 * ref.err_alpha + 1e-6).all(), (backend, diff_a.max(), ref.err_alpha.max())
    if "cpu" in grads:
        assert_grads_close(("means2d", "conics", "opacities", "features", "background", "median"),
                           grads["cpu"], grads["torch"], 1e-9)


# ------------------------------------------------------------------------------------ render


@given(cam=fs.cameras(), gs=fs.gaussians(), backend=st.sampled_from(BACKENDS),
       eps2d=st.sampled_from((0.3, 1e-3, 1e-6)), antialiased=st.booleans())
# regression (fixed in csrc/project_cpu.cpp): the C++ backward of the antialiased opacity computed
# det / Dlp^2, which overflows float32 for a huge Gaussian (log-scale 40) at focal 1e4: NaN d/dmeans
@example(cam=fs.CameraSpec(21, 1, 10000.0, 10000.0, 10.5, 0.5), backend="cpu", eps2d=0.3, antialiased=True,
         gs=fs.GaussianSpec(("front", "front", "far", "front", "front"), ("normal", "plus40", "normal", "normal", "normal"),
                            ("random", "zero", "random", "random", "random"), ("normal",) * 5))
def test_render_float32_is_finite(cam, gs, backend, eps2d, antialiased):
    """Every map and every parameter gradient finite; alpha in [0, 1]; normals unit or zero;
    depth 0 where alpha <= 1e-6 (render's rule); for any low-pass eps2d, with or without the
    antialiased opacity."""
    leaves = {k: v.requires_grad_() for k, v in gs.build(cam).items()}
    out = render(leaves, cam.build(), backend=backend, background=torch.tensor([0.2, 0.3, 0.4]), eps2d=eps2d,
                 antialiased=antialiased)
    bucket("visible Gaussians", int(out["visible"].sum()))
    bucket("pixels with alpha > 0.01", int((out["alpha"] > 0.01).sum()))
    for key in MAPS + ("means2d",):
        assert torch.isfinite(out[key]).all(), f"non-finite {key}"
    alpha = out["alpha"].detach()
    assert float(alpha.min()) >= 0.0 and float(alpha.max()) <= 1.0
    assert_unit_or_zero(out["normal"], 1e-4)
    assert bool((out["depth"][alpha <= 1e-6] == 0).all())
    maps = [out[k] for k in MAPS]
    loss = weighted_sum(maps, random_weights(maps))
    if loss.requires_grad:
        loss.backward()
    for key, leaf in leaves.items():
        assert leaf.grad is None or torch.isfinite(leaf.grad).all(), f"non-finite gradient of {key}"


def plane_depths(proj, centres: np.ndarray) -> np.ndarray:
    """[P, N] depth of every Gaussian's RaDe-GS plane at every pixel centre (float64)."""
    z = proj.depths.detach().double().numpy()
    p = proj.depth_slopes.detach().double().numpy()
    m = proj.means2d.detach().double().numpy()
    return z[None, :] + ((centres[:, None, :] - m[None, :, :]) * p[None, :, :]).sum(-1)


@given(cam=fs.cameras(), gs=fs.gaussians(max_n=32))
# property fix: quaternion gradients of huge isotropic Gaussians are rounding noise (1e-14 of the
# scale gradients) that differ between backends; the tolerance floor is relative to the largest gradient
@example(cam=fs.CameraSpec(9, 3, 0.1, 0.1, -18.0, -6.0),
         gs=fs.GaussianSpec(("on_near", "far") + ("front",) * 9 + ("on_near",) + ("front",) * 7 + ("on_near", "front"),
                            ("normal", "huge") + ("normal",) * 18 + ("huge",), ("random",) * 21, ("normal",) * 21,
                            seed=12564983))
def test_render_float64_backends_agree_and_rade_depth_is_a_blend(cam, gs):
    """float64: both backends give the same maps and gradients; where alpha > 1e-3 the depth lies
    within [min, max] of the depth planes of the Gaussians blended at the pixel (the oracle's
    weights), the median depth is the plane of the Gaussian where T crosses 0.5 (0 where none)."""
    camera = cam.build(torch.float64)
    outs, grads = {}, {}
    for backend in BACKENDS:
        leaves = {k: v.requires_grad_() for k, v in gs.build(cam, torch.float64).items()}
        out = render(leaves, camera, backend=backend, max_per_pixel=1024)
        maps = [out[k] for k in MAPS]
        loss = weighted_sum(maps, random_weights(maps))
        grads[backend] = (torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
                          if loss.requires_grad else [None] * len(leaves))
        outs[backend] = out
    out = outs["torch"]
    if "cpu" in outs:
        for k in MAPS:
            a, b = outs["cpu"][k].detach(), out[k].detach()
            scale = max(tmax(b), 1.0)
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * scale, msg=lambda m: f"{k}: {m}")
        # rtol 1e-7, not 1e-9: the C++ backward recovers T by dividing by (1 - alpha) (3DGS), up to 100x
        # per alpha = 0.99 Gaussian, and a projected gradient sums many such terms
        assert_grads_close(list(gs.build(cam, torch.float64)), grads["cpu"], grads["torch"], 1e-7)
    # the RaDe-GS depth against the oracle's blend weights of the same projected Gaussians
    with torch.no_grad():
        proj = project_gaussians(gs.build(cam, torch.float64), camera, backend="torch")
    centres = pixel_centres(cam.width, cam.height, torch.device("cpu"), torch.float64).reshape(-1, 2).numpy()
    planes = plane_depths(proj, centres)  # [P, N]
    feats = torch.zeros(len(proj.depths), 1, dtype=torch.float64)
    medf = torch.arange(len(proj.depths), dtype=torch.float64)[:, None] + 1.0  # 1-based median id
    ref = composite_oracle(proj.means2d, proj.conics, proj.opacities, feats, proj.depths, proj.radii,
                           cam.width, cam.height, None, medf)
    alpha, med, weights = ref.alpha, ref.median, ref.weights
    alpha = alpha.ravel()
    bucket("visible Gaussians", int(out["visible"].sum()))
    bucket("pixels with alpha > 1e-3", int((alpha > 1e-3).sum()))
    depth = out["depth"].detach().numpy().ravel()
    blended = weights > 0
    # render blends A = z - p . mean2d and p, then evaluates A + p . q: its rounding scales with |A|, |p . q|
    offsets = np.abs(proj.depths.numpy() - (proj.depth_slopes.numpy() * proj.means2d.numpy()).sum(-1))  # [N]
    slopes_q = np.abs(proj.depth_slopes.numpy() @ centres.T).T  # [P, N]
    for pix in np.flatnonzero(alpha > 1e-3):
        used = blended[pix]
        d = planes[pix, used]
        scale = offsets[used].max() + slopes_q[pix, used].max() + np.abs(d).max()
        tol = 1e-9 * scale / alpha[pix] + 1e-12
        assert d.min() - tol <= depth[pix] <= d.max() + tol, (pix, depth[pix], d.min(), d.max())
    med_id = med.ravel().astype(np.int64)
    median = out["median_depth"].detach().numpy().ravel()
    has = med_id > 0
    np.testing.assert_array_equal(median[~has], 0.0)
    want = planes[np.flatnonzero(has), med_id[has] - 1]
    np.testing.assert_allclose(median[has], want, rtol=1e-9, atol=1e-9 * max(1.0, float(np.abs(want).max(initial=0))))
