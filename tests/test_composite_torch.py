"""composite_torch against a dumb per-pixel loop of the rule in splat.composite (values and grads)."""

from __future__ import annotations

import pytest
import torch

from splat.composite import CompositeOut, composite
from splat.composite_torch import composite_torch, select_contributors


def loop_composite(means2d, conics, opacities, features, depths, radii, width, height,
                   background=None, median_features=None, max_per_pixel=None):
    """The contract's per-pixel rule, written as literally as possible (scalar autograd ops)."""
    order = sorted((g for g in range(len(depths)) if int(radii[g]) > 0),
                   key=lambda g: (float(depths[g]), g))
    nch = features.shape[1]
    outs, alphas, meds, counts = [], [], [], []
    for i in range(height):
        for j in range(width):
            px, py = j + 0.5, i + 0.5
            t = torch.ones((), dtype=features.dtype)
            acc = torch.zeros(nch, dtype=features.dtype)
            med = None if median_features is None else torch.zeros(median_features.shape[1],
                                                                   dtype=features.dtype)
            n = 0
            for g in order:
                r = float(radii[g])
                dx, dy = means2d[g, 0] - px, means2d[g, 1] - py
                if abs(dx.item()) > r or abs(dy.item()) > r:
                    continue
                a, b, c = conics[g]
                power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
                if power.item() > 0:
                    continue
                alpha = torch.clamp(opacities[g] * torch.exp(power), max=0.99)
                if alpha.item() < 1.0 / 255.0:
                    continue
                test_t = t * (1 - alpha)
                if test_t.item() < 1e-4 or (max_per_pixel is not None and n == max_per_pixel):
                    break
                acc = acc + features[g] * alpha * t
                if med is not None and t.item() > 0.5 and test_t.item() <= 0.5:
                    med = median_features[g]
                t = test_t
                n += 1
            if background is not None:
                acc = acc + t * background
            outs.append(acc)
            alphas.append(1 - t)
            counts.append(n)
            if med is not None:
                meds.append(med)
    return CompositeOut(
        features=torch.stack(outs).reshape(height, width, nch),
        alpha=torch.stack(alphas).reshape(height, width),
        median=None if median_features is None else torch.stack(meds).reshape(height, width, -1),
        n_contrib=torch.tensor(counts, dtype=torch.int32).reshape(height, width),
    )


def random_scene(n, width, height, nch=4, nmed=2, dtype=torch.float64, seed=0, opacity_max=0.95,
                 cluster=False):
    """Random 2D Gaussians over (and a little beyond) the image; leaves requiring grad."""
    gen = torch.Generator().manual_seed(seed)
    span = torch.tensor([width + 4.0, height + 4.0], dtype=dtype)
    means = torch.rand(n, 2, generator=gen, dtype=dtype) * span - 2.0
    if cluster:  # all over the middle of the image
        means = torch.tensor([width / 2, height / 2], dtype=dtype) + torch.randn(n, 2, generator=gen, dtype=dtype)
    lmat = torch.randn(n, 2, 2, generator=gen, dtype=dtype) * 0.8
    cov = lmat @ lmat.transpose(1, 2) + 0.3 * torch.eye(2, dtype=dtype)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    radii = torch.ceil(3 * torch.sqrt(torch.linalg.eigvalsh(cov)[:, 1])).to(torch.int32)
    radii[::7] = 0  # some culled
    opac = 0.02 + torch.rand(n, generator=gen, dtype=dtype) * (opacity_max - 0.02)
    feats = torch.rand(n, nch, generator=gen, dtype=dtype)
    depths = torch.rand(n, generator=gen, dtype=dtype)
    depths[1] = depths[2]  # a tie: broken by index
    bg = torch.rand(nch, generator=gen, dtype=dtype)
    medf = torch.rand(n, nmed, generator=gen, dtype=dtype)
    leaves = [t.clone().requires_grad_() for t in (means, conics, opac, feats, bg, medf)]
    return leaves, depths, radii


def _weighted_loss(out: CompositeOut, w_feat, w_med):
    return (out.features * w_feat).sum() + (out.median * w_med).sum() + (out.alpha ** 2).sum()


@pytest.mark.parametrize("seed,n,opacity_max,cluster", [(0, 25, 0.95, False), (1, 40, 0.99, True),
                                                        (2, 60, 0.5, False)])
def test_matches_loop_values_and_grads(seed, n, opacity_max, cluster):
    width, height = 9, 7
    (means, conics, opac, feats, bg, medf), depths, radii = random_scene(
        n, width, height, seed=seed, opacity_max=opacity_max, cluster=cluster)
    out = composite(means, conics, opac, feats, depths, radii, width, height, background=bg,
                    median_features=medf, backend="torch")
    ref = loop_composite(means, conics, opac, feats, depths, radii, width, height, bg, medf)
    torch.testing.assert_close(out.features, ref.features, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.alpha, ref.alpha, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.median, ref.median, rtol=0, atol=0)
    assert torch.equal(out.n_contrib, ref.n_contrib)
    assert int(ref.n_contrib.max()) > 1
    gen = torch.Generator().manual_seed(seed + 100)
    w_feat = torch.rand(out.features.shape, generator=gen, dtype=torch.float64)
    w_med = torch.rand(out.median.shape, generator=gen, dtype=torch.float64)
    leaves = [means, conics, opac, feats, bg, medf]
    g_out = torch.autograd.grad(_weighted_loss(out, w_feat, w_med), leaves)
    g_ref = torch.autograd.grad(_weighted_loss(ref, w_feat, w_med), leaves)
    for name, a, b in zip(["means2d", "conics", "opacities", "features", "background", "median"],
                          g_out, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12, msg=lambda m: f"{name}: {m}")
        assert torch.isfinite(a).all()


def test_saturation_stops_pixel():
    """Opaque stacks: T must stop before 1e-4 exactly as the loop does (stop Gaussian excluded)."""
    width, height = 6, 5
    (means, conics, opac, feats, bg, medf), depths, radii = random_scene(
        80, width, height, seed=5, opacity_max=0.99, cluster=True)
    out = composite_torch(means, conics, opac, feats, depths, radii, width, height, background=bg,
                          median_features=medf)
    ref = loop_composite(means, conics, opac, feats, depths, radii, width, height, bg, medf)
    assert float(ref.alpha.max()) > 0.999  # the stop rule is exercised
    torch.testing.assert_close(out.features, ref.features, rtol=1e-10, atol=1e-12)
    assert torch.equal(out.n_contrib, ref.n_contrib)


@pytest.mark.parametrize("cap", [1, 3])
def test_cap_per_pixel(cap):
    width, height = 7, 6
    (means, conics, opac, feats, bg, medf), depths, radii = random_scene(
        50, width, height, seed=3, opacity_max=0.3, cluster=True)
    out = composite_torch(means, conics, opac, feats, depths, radii, width, height, background=bg,
                          median_features=medf, max_per_pixel=cap)
    ref = loop_composite(means, conics, opac, feats, depths, radii, width, height, bg, medf,
                         max_per_pixel=cap)
    assert int(out.n_contrib.max()) == cap
    torch.testing.assert_close(out.features, ref.features, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.median, ref.median, rtol=0, atol=0)


def test_chunked_blending_matches_single_chunk_with_grads():
    """Pixel chunks give the same values and gradients as one chunk."""
    width, height = 20, 16
    (means, conics, opac, feats, bg, medf), depths, radii = random_scene(120, width, height, seed=7)
    leaves = [means, conics, opac, feats, bg, medf]
    outs, grads = [], []
    for pairs in (1 << 20, 40):  # one chunk vs many
        out = composite_torch(means, conics, opac, feats, depths, radii, width, height,
                              background=bg, median_features=medf, max_chunk_pairs=pairs)
        loss = (out.features ** 2).sum() + out.median.sum() + out.alpha.sum()
        outs.append(out)
        grads.append(torch.autograd.grad(loss, leaves))
    torch.testing.assert_close(outs[0].features, outs[1].features, rtol=1e-12, atol=1e-14)
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-13)


def test_selection_rounds_do_not_change_result():
    """Many candidates per bin (several selection rounds) vs one big round: same selection."""
    width, height = 8, 8
    (means, conics, opac, *_), depths, radii = random_scene(300, width, height, seed=11,
                                                           opacity_max=0.1, cluster=True)
    args = (means.detach(), conics.detach(), opac.detach(), depths, radii, width, height, 64)
    sel_a, n_a, pix_a = select_contributors(*args, candidates_per_round=4)
    sel_b, n_b, pix_b = select_contributors(*args, candidates_per_round=512)
    assert int(n_a.max()) == 64  # cap reached: many rounds were needed
    assert torch.equal(sel_a, sel_b) and torch.equal(n_a, n_b) and torch.equal(pix_a, pix_b)
    # every image pixel appears exactly once; cells outside the image are empty
    inside = pix_a < width * height
    assert torch.equal(torch.sort(pix_a[inside]).values, torch.arange(width * height))
    assert int(n_a[~inside].sum()) == 0


def test_float32_close_to_float64_and_background_only():
    width, height = 10, 8
    (means, conics, opac, feats, bg, medf), depths, radii = random_scene(40, width, height, seed=4)
    out64 = composite_torch(means, conics, opac, feats, depths, radii, width, height, background=bg)
    f32 = [t.detach().float() for t in (means, conics, opac, feats, bg)]
    out32 = composite_torch(f32[0], f32[1], f32[2], f32[3], depths.float(), radii, width, height,
                            background=f32[4])
    torch.testing.assert_close(out32.features.double(), out64.features.detach(), rtol=1e-4, atol=1e-5)
    assert out32.median is None and out32.n_contrib.dtype == torch.int32
    empty = composite_torch(f32[0], f32[1], f32[2], f32[3], depths.float(), torch.zeros_like(radii),
                            width, height, background=f32[4])
    torch.testing.assert_close(empty.features, f32[4].expand(height, width, -1))
    assert float(empty.alpha.abs().max()) == 0.0


def test_bad_inputs_raise():
    means = torch.zeros(3, 2)
    ok = dict(conics=torch.ones(3, 3), opacities=torch.ones(3), features=torch.ones(3, 2),
              depths=torch.ones(3), radii=torch.ones(3, dtype=torch.int32))
    with pytest.raises(ValueError, match="conics"):
        composite(means, torch.ones(3, 2), ok["opacities"], ok["features"], ok["depths"], ok["radii"], 4, 4)
    with pytest.raises(ValueError, match="background"):
        composite(means, *ok.values(), 4, 4, background=torch.zeros(3))
    with pytest.raises(ValueError, match="backend"):
        composite(means, *ok.values(), 4, 4, backend="metal")  # "cuda" is a backend now
