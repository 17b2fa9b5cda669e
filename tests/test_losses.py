"""splat/losses.py: each IndoorGS §4.3 loss term on analytic inputs, its masks, gradients and total_loss."""

from __future__ import annotations

import math

import pytest
import torch

from evaluation.image_metrics import ssim
from splat.losses import (LossConfig, anchored_depth_loss, depth_normal_consistency_loss, depth_pcc_loss,
                          depth_to_normal, flatten_loss, normal_prior_loss, rgb_loss, sample_patch_grid, total_loss)

DT = torch.float64


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def intrinsics(width: int, height: int, f: float = 50.0, dtype=DT) -> torch.Tensor:
    return torch.tensor([[f, 0, width / 2 - 0.3], [0, 1.1 * f, height / 2 + 0.2], [0, 0, 1]], dtype=dtype)


def plane_depth(normal, offset: float, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """z-depth [H, W] of the plane n . X = offset seen through K (COLMAP pixel centres)."""
    n = torch.tensor(normal, dtype=DT)
    u = torch.arange(width, dtype=DT) + 0.5
    v = torch.arange(height, dtype=DT) + 0.5
    rx = ((u[None, :] - K[0, 2]) / K[0, 0]).expand(height, width)
    ry = ((v[:, None] - K[1, 2]) / K[1, 1]).expand(height, width)
    return offset / (n[0] * rx + n[1] * ry + n[2])


def smooth_depth(h: int, w: int, seed: int = 0, dtype=DT) -> torch.Tensor:
    """A positive, non-planar depth map with texture everywhere (no flat patch)."""
    g = gen(seed)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    return 2.0 + 0.3 * torch.sin(0.37 * xx + 0.11 * yy) + 0.2 * torch.cos(0.23 * yy) + 0.05 * torch.rand(h, w, generator=g, dtype=dtype)


class TestRgbLoss:
    def test_zero_for_identical(self):
        img = torch.rand(20, 24, 3, generator=gen())
        assert float(rgb_loss(img, img.clone())) == pytest.approx(0.0, abs=1e-6)

    def test_matches_l1_and_evaluation_ssim(self):
        a, b = torch.rand(30, 26, 3, generator=gen(1)), torch.rand(30, 26, 3, generator=gen(2))
        expected = 0.8 * float((a - b).abs().mean()) + 0.2 * (1.0 - ssim(a, b))
        assert float(rgb_loss(a, b, 0.2)) == pytest.approx(expected, rel=1e-5)
        assert float(rgb_loss(a, b, 0.0)) == pytest.approx(float((a - b).abs().mean()), rel=1e-6)

    def test_gradcheck(self):
        a = torch.rand(7, 8, 3, generator=gen(3), dtype=DT, requires_grad=True)
        b = torch.rand(7, 8, 3, generator=gen(4), dtype=DT)
        assert torch.autograd.gradcheck(lambda x: rgb_loss(x, b), (a,))

    def test_bad_shape(self):
        with pytest.raises(ValueError, match=r"expected shape \[7, 8, 3\], got \[7, 8, 4\]"):
            rgb_loss(torch.rand(7, 8, 3), torch.rand(7, 8, 4))


class TestPatchGrid:
    @pytest.mark.parametrize("h,w,s,n", [(48, 64, 8, 20), (50, 70, 16, 100), (10, 10, 4, 3)])
    def test_non_overlapping_and_inside(self, h, w, s, n):
        for seed in range(5):
            corners, ph, pw = sample_patch_grid(h, w, s, n, gen(seed))
            assert (ph, pw) == (s, s)
            assert corners.shape[0] == min(n, (h // s) * (w // s))
            count = torch.zeros(h, w, dtype=torch.int64)
            for r, c in corners.tolist():
                assert 0 <= r and r + s <= h and 0 <= c and c + s <= w
                count[r:r + s, c:c + s] += 1
            assert int(count.max()) == 1
            assert int(count.sum()) == corners.shape[0] * s * s

    def test_small_image_is_one_patch(self):
        corners, ph, pw = sample_patch_grid(5, 7, 32, 16, gen())
        assert corners.tolist() == [[0, 0]] and (ph, pw) == (5, 7)

    def test_random(self):
        a = sample_patch_grid(64, 64, 8, 4, gen(0))[0]
        b = sample_patch_grid(64, 64, 8, 4, gen(1))[0]
        assert not torch.equal(a, b)


class TestDepthPcc:
    def test_scale_shift_invariant(self):
        d = smooth_depth(40, 48)
        valid = torch.ones_like(d, dtype=torch.bool)
        for a, b, expected in [(1.0, 0.0, 0.0), (3.7, -1.2, 0.0), (0.01, 5.0, 0.0), (-2.0, 10.0, 2.0)]:
            loss = depth_pcc_loss(d, a * d + b, valid, 8, 12, gen())
            assert float(loss) == pytest.approx(expected, abs=1e-9)

    def test_uncorrelated_is_positive(self):
        d = smooth_depth(40, 48)
        prior = 1.0 + torch.rand(40, 48, generator=gen(7), dtype=DT)
        loss = float(depth_pcc_loss(d, prior, torch.ones_like(d, dtype=torch.bool), 8, 12, gen()))
        assert 0.5 < loss < 1.5

    def test_invalid_pixels_are_ignored(self):
        d = smooth_depth(32, 32)
        prior = 2 * d + 1
        valid = torch.rand(32, 32, generator=gen(5)) > 0.2  # ~80 % valid: every 8x8 patch keeps > half
        prior_bad = torch.where(valid, prior, torch.rand(32, 32, generator=gen(6), dtype=DT) * 100)
        assert float(depth_pcc_loss(d, prior_bad, valid, 8, 16, gen())) == pytest.approx(0.0, abs=1e-9)
        # without the mask, the garbage pixels break the correlation
        assert float(depth_pcc_loss(d, prior_bad, torch.ones_like(valid), 8, 16, gen())) > 0.1

    def test_sparse_patches_are_skipped(self):
        d = smooth_depth(16, 16)
        valid = torch.zeros(16, 16, dtype=torch.bool)
        valid[:8, :8] = True  # the only patch with enough valid pixels is perfectly correlated
        valid[8:, 8:11] = True  # 24 of 64 valid: skipped
        prior = torch.where(valid, d, torch.zeros_like(d))
        prior[8:, 8:11] = torch.rand(8, 3, generator=gen(2), dtype=DT) + 1  # uncorrelated, but skipped
        assert float(depth_pcc_loss(d, prior, valid, 8, 4, gen())) == pytest.approx(0.0, abs=1e-9)

    @pytest.mark.parametrize("case", ["flat_render", "flat_prior", "all_invalid"])
    def test_degenerate_finite(self, case):
        d = smooth_depth(24, 24).clone()
        prior = 1.5 * d + 0.5
        valid = torch.ones(24, 24, dtype=torch.bool)
        if case == "flat_render":
            d = torch.full((24, 24), 2.5, dtype=DT)  # zero variance: PCC undefined in every patch
        elif case == "flat_prior":
            prior = torch.full((24, 24), 1.0, dtype=DT)
        else:
            valid[:] = False
        d.requires_grad_(True)
        loss = depth_pcc_loss(d, prior, valid, 8, 9, gen())
        loss.backward()
        assert float(loss.detach()) == 0.0
        assert loss.requires_grad and torch.isfinite(d.grad).all() and float(d.grad.abs().max()) == 0.0

    def test_partly_flat_render_finite(self):
        """Half the patches flat (skipped), half textured: finite, and only the textured ones count."""
        d = smooth_depth(16, 32)
        d[:, :16] = 3.0
        d.requires_grad_(True)
        prior = torch.rand(16, 32, generator=gen(3), dtype=DT) + 1
        loss = depth_pcc_loss(d, prior, torch.ones(16, 32, dtype=torch.bool), 16, 2, gen())
        loss.backward()
        assert float(loss.detach()) > 0 and torch.isfinite(d.grad).all()
        assert float(d.grad[:, :16].abs().max()) == 0.0 and float(d.grad[:, 16:].abs().max()) > 0

    def test_gradcheck(self):
        d = smooth_depth(10, 12).requires_grad_(True)
        prior = torch.rand(10, 12, generator=gen(9), dtype=DT) + 1
        valid = torch.rand(10, 12, generator=gen(8)) > 0.1
        assert torch.autograd.gradcheck(lambda x: depth_pcc_loss(x, prior, valid, 4, 5, gen(3)), (d,))

    def test_bad_shape(self):
        with pytest.raises(ValueError, match=r"prior: expected shape \[4, 5\], got \[5, 4\]"):
            depth_pcc_loss(torch.rand(4, 5), torch.rand(5, 4), torch.ones(4, 5, dtype=torch.bool), 2, 2)


class TestAnchoredDepth:
    def test_hinge_values(self):
        """Only the part of |depth - anchor| beyond the tolerance counts; invalid anchors (0) and
        masked pixels are left out of the mean."""
        anchor = torch.tensor([[2.0, 2.0, 2.0, 0.0]], dtype=DT)
        depth = torch.tensor([[2.01, 1.8, 2.5, 9.0]], dtype=DT)
        valid = torch.tensor([[True, True, True, True]])
        loss = anchored_depth_loss(depth, anchor, valid, tolerance=0.05)
        assert float(loss) == pytest.approx((0.0 + 0.15 + 0.45) / 3)
        masked = anchored_depth_loss(depth, anchor, torch.tensor([[True, True, False, True]]), 0.05)
        assert float(masked) == pytest.approx(0.15 / 2)

    def test_offset_surface_is_penalised_where_pcc_is_not(self):
        """A surface moved 10 cm along the view has the prior's depth pattern (L_d = 0) but not its
        depth: L_a sees it; within the tolerance it is 0."""
        d = smooth_depth(32, 32)
        valid = torch.ones(32, 32, dtype=torch.bool)
        moved = d - 0.10
        assert float(depth_pcc_loss(moved, d, valid, 8, 8, gen())) == pytest.approx(0.0, abs=1e-9)
        assert float(anchored_depth_loss(moved, d, valid, 0.05)) == pytest.approx(0.05, rel=1e-9)
        assert float(anchored_depth_loss(moved, d, valid, 0.12)) == 0.0

    def test_gradient_pulls_towards_the_anchor_and_is_finite(self):
        anchor = smooth_depth(16, 16)
        depth = (anchor + torch.linspace(-0.3, 0.3, 256, dtype=DT).reshape(16, 16)).requires_grad_()
        valid = torch.ones(16, 16, dtype=torch.bool)
        anchored_depth_loss(depth, anchor, valid, 0.05).backward()
        g, r = depth.grad, (depth - anchor).detach()
        assert torch.isfinite(g).all()
        assert (g[r > 0.06] > 0).all() and (g[r < -0.06] < 0).all() and (g[r.abs() < 0.04] == 0).all()

    def test_empty_and_bad(self):
        depth = torch.ones(4, 4, dtype=DT, requires_grad=True)
        loss = anchored_depth_loss(depth, torch.zeros(4, 4, dtype=DT), torch.ones(4, 4, dtype=torch.bool), 0.0)
        loss.backward()
        assert float(loss.detach()) == 0.0 and torch.isfinite(depth.grad).all()
        with pytest.raises(ValueError, match=r"anchor: expected shape \[4, 4\]"):
            anchored_depth_loss(depth, torch.zeros(3, 4, dtype=DT), torch.ones(4, 4, dtype=torch.bool), 0.0)
        with pytest.raises(ValueError, match="tolerance"):
            anchored_depth_loss(depth, depth.detach(), torch.ones(4, 4, dtype=torch.bool), float("nan"))


class TestNormalPrior:
    def test_values_and_masks(self):
        normal = torch.zeros(2, 2, 3)
        normal[..., 2] = -1.0
        prior = normal.clone()
        prior[0, 0] = torch.tensor([1.0, 0.0, 0.0])  # |(-1, 0, -1)|_1 = 2
        prior[0, 1] = 0.0  # invalid prior: dropped
        valid = torch.ones(2, 2, dtype=torch.bool)
        assert float(normal_prior_loss(normal, prior, valid)) == pytest.approx(2.0 / 3.0)
        valid[1, 1] = False
        assert float(normal_prior_loss(normal, prior, valid)) == pytest.approx(1.0)
        assert float(normal_prior_loss(normal, prior, torch.zeros_like(valid))) == 0.0
        assert float(normal_prior_loss(normal, normal.clone(), valid)) == 0.0

    def test_gradient_only_on_valid(self):
        normal = torch.nn.functional.normalize(torch.randn(4, 4, 3, generator=gen()), dim=-1).requires_grad_(True)
        prior = torch.nn.functional.normalize(torch.randn(4, 4, 3, generator=gen(1)), dim=-1)
        valid = torch.zeros(4, 4, dtype=torch.bool)
        valid[1:3, 1:3] = True
        normal_prior_loss(normal, prior, valid).backward()
        assert float(normal.grad[~valid].abs().max()) == 0.0 and float(normal.grad[valid].abs().min()) > 0

    def test_bad_shape(self):
        with pytest.raises(ValueError, match=r"valid: expected shape \[4, 4\]"):
            normal_prior_loss(torch.rand(4, 4, 3), torch.rand(4, 4, 3), torch.ones(4, 3, dtype=torch.bool))


class TestFlatten:
    def test_smallest_scale_of_masked(self):
        scales = torch.log(torch.tensor([[0.1, 0.02, 0.3], [0.5, 0.5, 0.5], [0.004, 1.0, 1.0]]))
        mask = torch.tensor([True, False, True])
        assert float(flatten_loss(scales, mask)) == pytest.approx((0.02 + 0.004) / 2)

    def test_empty_mask_and_gradient(self):
        scales = torch.log(torch.tensor([[0.1, 0.02, 0.3], [0.5, 0.4, 0.6]])).requires_grad_(True)
        loss = flatten_loss(scales, torch.zeros(2, dtype=torch.bool))
        assert float(loss.detach()) == 0.0 and loss.requires_grad
        flatten_loss(scales, torch.tensor([False, True])).backward()
        expected = torch.zeros(2, 3)
        expected[1, 1] = 0.4  # d exp(s)/ds on the smallest axis of the masked row only
        torch.testing.assert_close(scales.grad, expected)

    def test_bad_shape(self):
        with pytest.raises(ValueError, match=r"mask: expected shape \[3\], got \[2\]"):
            flatten_loss(torch.zeros(3, 3), torch.ones(2, dtype=torch.bool))


PLANE_N = [0.3, -0.25, -0.92]  # faces the camera (n . X < 0 for X in front)


def unit(v) -> torch.Tensor:
    t = torch.tensor(v, dtype=DT)
    return t / t.norm()


class TestDepthToNormal:
    def test_tilted_plane_exact(self):
        w, h = 23, 17
        K = intrinsics(w, h)
        n = unit(PLANE_N)
        depth = plane_depth(n.tolist(), -2.0, K, w, h)
        assert float(depth.min()) > 0
        normals = depth_to_normal(depth, K)
        torch.testing.assert_close(normals[1:-1, 1:-1], n.expand(h - 2, w - 2, 3), atol=1e-5, rtol=0)
        border = torch.ones(h, w, dtype=torch.bool)
        border[1:-1, 1:-1] = False
        assert float(normals[border].abs().max()) == 0.0

    def test_faces_the_camera(self):
        w, h = 16, 12
        K = intrinsics(w, h)
        n_away = -unit(PLANE_N)  # the same plane written with its normal pointing away
        depth = plane_depth(n_away.tolist(), 2.0, K, w, h)
        normals = depth_to_normal(depth, K)
        torch.testing.assert_close(normals[1:-1, 1:-1], (-n_away).expand(h - 2, w - 2, 3), atol=1e-5, rtol=0)
        # fronto-parallel wall: (0, 0, -1)
        flat = depth_to_normal(torch.full((h, w), 3.0, dtype=DT), K)
        torch.testing.assert_close(flat[1:-1, 1:-1], torch.tensor([0, 0, -1.0], dtype=DT).expand(h - 2, w - 2, 3))

    def test_zero_depth(self):
        K = intrinsics(12, 10)
        depth = torch.full((10, 12), 2.0, dtype=DT)
        depth[5, 6] = 0.0
        defined = depth_to_normal(depth, K).abs().sum(-1) > 0
        hole = torch.zeros(10, 12, dtype=torch.bool)
        for r, c in [(5, 6), (4, 6), (6, 6), (5, 5), (5, 7)]:
            hole[r, c] = True
        inner = torch.zeros(10, 12, dtype=torch.bool)
        inner[1:-1, 1:-1] = True
        assert torch.equal(defined, inner & ~hole)
        assert float(depth_to_normal(torch.zeros(10, 12), K.float()).abs().max()) == 0.0

    def test_bad_shape(self):
        with pytest.raises(ValueError, match=r"K: expected shape \[3, 3\], got \[3, 4\]"):
            depth_to_normal(torch.ones(5, 5), torch.ones(3, 4))


class TestDepthNormalConsistency:
    def setup_method(self):
        self.w, self.h = 20, 15
        self.K = intrinsics(self.w, self.h)
        self.n = unit(PLANE_N)
        self.depth = plane_depth(self.n.tolist(), -2.5, self.K, self.w, self.h)
        self.valid = torch.ones(self.h, self.w, dtype=torch.bool)

    def test_zero_on_plane(self):
        normal = self.n.expand(self.h, self.w, 3).clone()
        loss = depth_normal_consistency_loss(normal, self.depth, self.K, self.valid)
        assert float(loss) == pytest.approx(0.0, abs=1e-10)

    def test_positive_otherwise(self):
        angle = 0.4
        tilted = torch.tensor([math.sin(angle), 0.0, -math.cos(angle)], dtype=DT)  # 0.4 rad from (0, 0, -1)
        normal = tilted.expand(self.h, self.w, 3).clone()
        depth = torch.full((self.h, self.w), 2.0, dtype=DT)
        loss = depth_normal_consistency_loss(normal, depth, self.K, self.valid)
        assert float(loss) == pytest.approx(1.0 - math.cos(angle), rel=1e-9)  # border pixels excluded

    def test_step_edge_finite_gradients(self):
        depth = torch.full((self.h, self.w), 1.0, dtype=DT)
        depth[:, self.w // 2:] = 3.0
        depth[2, 3] = 0.0  # a hole too
        depth.requires_grad_(True)
        normal = torch.nn.functional.normalize(torch.randn(self.h, self.w, 3, generator=gen(), dtype=DT), dim=-1)
        normal.requires_grad_(True)
        loss = depth_normal_consistency_loss(normal, depth, self.K, self.valid)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(depth.grad).all() and torch.isfinite(normal.grad).all()
        assert float(depth.grad.abs().max()) > 0 and float(normal.grad.abs().max()) > 0

    def test_detach_depth_normal(self):
        depth = self.depth.clone().requires_grad_(True)
        normal = self.n.expand(self.h, self.w, 3).clone()
        normal[..., 0] += 0.1
        normal.requires_grad_(True)
        depth_normal_consistency_loss(normal, depth, self.K, self.valid, detach_depth_normal=True).backward()
        assert depth.grad is None and float(normal.grad.abs().max()) > 0

    def test_gradcheck(self):
        depth = (smooth_depth(6, 7) + 0.0).requires_grad_(True)
        normal = torch.nn.functional.normalize(torch.randn(6, 7, 3, generator=gen(1), dtype=DT), dim=-1)
        K = intrinsics(7, 6, f=5.0)
        valid = torch.ones(6, 7, dtype=torch.bool)
        assert torch.autograd.gradcheck(lambda d: depth_normal_consistency_loss(normal, d, K, valid), (depth,))


def fake_view(h: int = 24, w: int = 32, n: int = 6):
    """A render-like output of leaf tensors, priors, K, params and cue types."""
    depth = smooth_depth(h, w, dtype=torch.float32)
    out = {
        "rgb": torch.rand(h, w, 3, generator=gen(1)),
        "depth": depth,
        "normal": torch.nn.functional.normalize(torch.randn(h, w, 3, generator=gen(2)), dim=-1),
        "alpha": torch.full((h, w), 0.9),
    }
    out = {k: v.clone().requires_grad_(True) for k, v in out.items()}
    params = {"scales": torch.log(torch.rand(n, 3, generator=gen(3)) * 0.1 + 0.01).requires_grad_(True)}
    cue_type = torch.tensor([0, 1, 2, 1, 0, 2][:n])
    extra = dict(depth_prior=(0.5 * depth + 1.0) * (torch.rand(h, w, generator=gen(4)) + 0.5),
                 normal_prior=torch.nn.functional.normalize(torch.randn(h, w, 3, generator=gen(5)), dim=-1))
    return out, torch.rand(h, w, 3, generator=gen(6)), intrinsics(w, h, dtype=torch.float32), params, cue_type, extra


class TestTotalLoss:
    CFG = dict(patch_size=8, n_patches=6)

    def run(self, step=10_000, with_priors=True, **cfg):
        out, gt, K, params, cue_type, extra = fake_view()
        total, terms = total_loss(out, gt, K, params, cue_type, LossConfig(**{**self.CFG, **cfg}), step,
                                  generator=gen(), **(extra if with_priors else {}))
        return total, terms, out, params

    def test_all_terms(self):
        total, terms, _, _ = self.run()
        assert set(terms) == {"rgb", "depth", "normal", "flat", "nc", "total"}
        cfg = LossConfig()
        expected = (terms["rgb"] + cfg.lambda_depth * terms["depth"] + cfg.lambda_normal * terms["normal"]
                    + cfg.lambda_flat * terms["flat"] + cfg.lambda_nc * terms["nc"])
        assert terms["total"] == pytest.approx(expected, rel=1e-5) and float(total.detach()) == pytest.approx(expected, rel=1e-5)
        assert all(v > 0 for v in terms.values())

    @pytest.mark.parametrize("switch,key", [("use_depth", "depth"), ("use_normal", "normal"),
                                            ("use_flat", "flat"), ("use_nc", "nc")])
    def test_switch_removes_term(self, switch, key):
        full, full_terms, _, _ = self.run()
        total, terms, _, _ = self.run(**{switch: False})
        assert key not in terms and set(terms) == set(full_terms) - {key}
        weight = {"depth": 0.1, "normal": 0.5, "flat": 100.0, "nc": 0.1}[key]
        assert float(total.detach()) == pytest.approx(float(full.detach()) - weight * full_terms[key], rel=1e-5)

    def test_anchor_term_weight_switch_and_alignment_residual(self):
        out, gt, K, params, cue_type, extra = fake_view()
        anchor = (out["depth"].detach() - 0.2).clamp(min=0)
        kw = dict(depth_anchor=anchor, **extra)  # a fresh generator per call: the same PCC patches
        _, off = total_loss(out, gt, K, params, cue_type, LossConfig(lambda_anchor=0.0, **self.CFG), 10_000,
                            generator=gen(), **kw)
        assert "anchor" not in off  # λ_a = 0: the paper's loss
        _, no_anchor = total_loss(out, gt, K, params, cue_type, LossConfig(**self.CFG), 10_000, generator=gen(), **extra)
        assert "anchor" not in no_anchor and no_anchor["total"] == pytest.approx(off["total"], rel=1e-6)
        cfg = LossConfig(lambda_anchor=2.0, **self.CFG)
        _, small = total_loss(out, gt, K, params, cue_type, cfg, 10_000, generator=gen(), anchor_p90=0.01, **kw)
        _, large = total_loss(out, gt, K, params, cue_type, cfg, 10_000, generator=gen(), anchor_p90=0.15, **kw)
        assert small["anchor"] > large["anchor"] > 0  # tolerance max(0.03, 0.5 p90): 0.03 vs 0.075
        assert small["total"] == pytest.approx(off["total"] + 2.0 * small["anchor"], rel=1e-5)

    def test_missing_priors_and_nc_schedule(self):
        _, terms, _, _ = self.run(with_priors=False)
        assert set(terms) == {"rgb", "flat", "nc", "total"}
        _, terms, _, _ = self.run(step=6999)
        assert "nc" not in terms
        _, terms, _, _ = self.run(step=7000)
        assert "nc" in terms

    @pytest.mark.parametrize("only,touched", [
        (None, {"rgb"}), ("use_depth", {"rgb", "depth"}), ("use_normal", {"rgb", "normal"}),
        ("use_flat", {"rgb", "scales"}), ("use_nc", {"rgb", "normal", "depth"})])
    def test_gradients_reach_what_each_term_touches(self, only, touched):
        switches = {s: s == only for s in ("use_depth", "use_normal", "use_flat", "use_nc")}
        total, _, out, params = self.run(**switches)
        total.backward()
        tensors = {**out, "scales": params["scales"]}
        for name, t in tensors.items():
            reached = t.grad is not None and float(t.grad.abs().max()) > 0
            assert reached == (name in touched), name
            if t.grad is not None:
                assert torch.isfinite(t.grad).all(), name

    def test_flat_types(self):
        out, gt, K, params, cue_type, extra = fake_view()
        smallest = params["scales"].detach().min(1).values.exp()
        for types, keep in [((1,), cue_type == 1), ((1, 2), cue_type >= 1), ((), cue_type < 0)]:
            _, terms = total_loss(out, gt, K, params, cue_type, LossConfig(flat_types=types, **self.CFG), 0)
            expected = float(smallest[keep].mean()) if bool(keep.any()) else 0.0
            assert terms["flat"] == pytest.approx(expected, rel=1e-6)

    def test_bad_inputs(self):
        out, gt, K, params, cue_type, extra = fake_view()
        with pytest.raises(ValueError, match=r"cue_type: expected shape \[6\], got \[5\]"):
            total_loss(out, gt, K, params, cue_type[:5], LossConfig(), 0)
        with pytest.raises(ValueError, match=r"depth_prior: expected shape \[24, 32\], got \[24, 31\]"):
            total_loss(out, gt, K, params, cue_type, LossConfig(), 0, depth_prior=extra["depth_prior"][:, :31])
        with pytest.raises(ValueError, match="missing key 'alpha'"):
            total_loss({k: v for k, v in out.items() if k != "alpha"}, gt, K, params, cue_type, LossConfig(), 0)


def test_through_the_renderer():
    """End to end: render a tilted sheet of Gaussians, every term on, gradients reach every parameter."""
    from splat.camera import Camera
    from splat.rasterize import render

    w, h, n_side = 24, 18, 6
    K = torch.tensor([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]])
    cam = Camera(K=K, viewmat=torch.eye(4), width=w, height=h)
    g = torch.linspace(-0.6, 0.6, n_side)
    xx, yy = torch.meshgrid(g, g, indexing="xy")
    means = torch.stack([xx, yy, 2.0 + 0.4 * xx + 0.2 * yy], -1).reshape(-1, 3)
    n = means.shape[0]
    params = {
        "means": means,
        "quats": torch.nn.functional.normalize(torch.tensor([[1.0, 0.1, -0.2, 0.05]]).repeat(n, 1), dim=-1),
        "scales": torch.log(torch.tensor([0.15, 0.12, 0.02])).repeat(n, 1),
        "opacities": torch.full((n,), 2.0),
        "sh0": torch.rand(n, 1, 3, generator=gen()),
        "shN": torch.zeros(n, 0, 3),
    }
    params = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    out = render(params, cam, backend="torch")
    assert float((out["alpha"] > 0.5).float().mean()) > 0.5
    cue_type = torch.arange(n) % 3
    depth_prior = (out["depth"].detach() * 0.8 + 0.3) * (1 + 0.1 * torch.rand(h, w, generator=gen(1)))
    normal_prior = torch.tensor([0.0, 0.0, -1.0]).expand(h, w, 3)
    cfg = LossConfig(patch_size=6, n_patches=6)
    total, terms = total_loss(out, torch.rand(h, w, 3, generator=gen(2)), K, params, cue_type, cfg, 10_000,
                              depth_prior=depth_prior, normal_prior=normal_prior, generator=gen())
    assert set(terms) == {"rgb", "depth", "normal", "flat", "nc", "total"}
    total.backward()
    for name in ("means", "quats", "scales", "opacities", "sh0"):
        grad = params[name].grad
        assert grad is not None and torch.isfinite(grad).all() and float(grad.abs().max()) > 0, name
