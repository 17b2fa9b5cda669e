"""Per-type adaptive density control (splat/strategy.py, splat/densify_ops.py; IndoorGS §4.2)."""

from __future__ import annotations

import math

import pytest
import torch

from geocues.types import CueType
from splat.densify_ops import (duplicate, flat_normal, free_split_offsets, near_any, remove,
                               reset_opacities, split, tangent_clone_means, tangent_split_offsets)
from splat.projection import quat_to_rotmat
from splat.strategy import IndoorStrategy, IndoorStrategyConfig, Schedule, budget_mask

SFM, LINE, PLANE = int(CueType.SFM), int(CueType.LINE), int(CueType.PLANE)


def make_params(n: int, k: int = 3, seed: int = 0) -> torch.nn.ParameterDict:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
        "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g)),
        "scales": torch.nn.Parameter(torch.log(torch.rand(n, 3, generator=g) * 0.01 + 0.001)),
        "opacities": torch.nn.Parameter(torch.full((n,), 2.0)),
        "sh0": torch.nn.Parameter(torch.randn(n, 1, 3, generator=g)),
        "shN": torch.nn.Parameter(torch.randn(n, k, 3, generator=g)),
    })


def make_optimizers(params) -> dict[str, torch.optim.Adam]:
    return {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}


def adam_step(params, optimizers, fill: float) -> None:
    """One optimizer step with every gradient set to ``fill`` (0: creates the moments, moves nothing)."""
    for p in params.values():
        p.grad = torch.full_like(p, fill)
    for opt in optimizers.values():
        opt.step()


def row_ids(params, optimizers):
    """Give each row a distinctive value in means[:, 0] and in both Adam moments (row i -> i + 1)."""
    n = params["means"].shape[0]
    adam_step(params, optimizers, 1.0)
    ids = torch.arange(1, n + 1, dtype=torch.float32)
    with torch.no_grad():
        params["means"][:, 0] = ids
    for key, opt in optimizers.items():
        st = opt.state[params[key]]
        shape = (n,) + (1,) * (params[key].dim() - 1)
        st["exp_avg"] = ids.reshape(shape).expand_as(params[key]).clone()
        st["exp_avg_sq"] = 10 * ids.reshape(shape).expand_as(params[key]).clone()
    for p in params.values():
        p.grad = None


def moments(params, optimizers, key="sh0"):
    st = optimizers[key].state[params[key]]
    return st["exp_avg"].reshape(len(params[key]), -1)[:, 0], st["exp_avg_sq"].reshape(len(params[key]), -1)[:, 0]


def assert_aligned(params, optimizers, state):
    n = params["means"].shape[0]
    for key, p in params.items():
        assert p.shape[0] == n, key
        assert optimizers[key].param_groups[0]["params"][0] is p, key
        st = optimizers[key].state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape, key
    for key, v in state.items():
        if isinstance(v, torch.Tensor):
            assert v.shape[0] == n, key


def steps_ok(params, optimizers):
    """The optimizers still step the (new) parameters."""
    before = {k: p.detach().clone() for k, p in params.items()}
    adam_step(params, optimizers, 1.0)
    for k, p in params.items():
        assert not torch.equal(before[k], p.detach()), k
        assert torch.isfinite(p).all(), k


class TestOps:
    def setup_method(self):
        self.params = make_params(5)
        self.opts = make_optimizers(self.params)
        row_ids(self.params, self.opts)
        self.state = {"cue_type": torch.tensor([0, 1, 2, 1, 0]), "count": torch.arange(5.0) * 100,
                      "scene_scale": 1.0}
        self.mask = torch.tensor([False, True, False, True, False])

    def test_duplicate(self):
        old_scales = self.params["scales"].detach().clone()
        target = torch.tensor([[7.0, 7.0, 7.0], [8.0, 8.0, 8.0]])
        assert duplicate(self.params, self.opts, self.state, self.mask, target) == 2
        assert_aligned(self.params, self.opts, self.state)
        torch.testing.assert_close(self.params["means"][:5, 0], torch.arange(1.0, 6.0))
        torch.testing.assert_close(self.params["means"][5:], target)
        torch.testing.assert_close(self.params["scales"][5:], old_scales[[1, 3]])
        m1, m2 = moments(self.params, self.opts)
        torch.testing.assert_close(m1, torch.tensor([1.0, 2, 3, 4, 5, 0, 0]))
        torch.testing.assert_close(m2, torch.tensor([10.0, 20, 30, 40, 50, 0, 0]))
        assert self.state["cue_type"].tolist() == [0, 1, 2, 1, 0, 1, 1]
        assert self.state["count"].tolist() == [0, 100, 200, 300, 400, 100, 300]
        steps_ok(self.params, self.opts)

    def test_split(self):
        old = {k: p.detach().clone() for k, p in self.params.items()}
        offsets = torch.arange(12.0).reshape(2, 2, 3)
        assert split(self.params, self.opts, self.state, self.mask, offsets) == 2
        assert_aligned(self.params, self.opts, self.state)
        # kept rows 0, 2, 4 first, then children of 1, 3 (first children), then second children
        parents = [0, 2, 4, 1, 3, 1, 3]
        torch.testing.assert_close(self.params["sh0"], old["sh0"][parents])
        torch.testing.assert_close(self.params["means"][3:], old["means"][[1, 3, 1, 3]] + offsets.reshape(4, 3))
        torch.testing.assert_close(self.params["scales"][3:], old["scales"][[1, 3, 1, 3]] - math.log(1.6))
        torch.testing.assert_close(self.params["scales"][:3], old["scales"][[0, 2, 4]])
        m1, _ = moments(self.params, self.opts, "means")
        torch.testing.assert_close(m1, torch.tensor([1.0, 3, 5, 0, 0, 0, 0]))
        assert self.state["cue_type"].tolist() == [0, 2, 0, 1, 1, 1, 1]
        assert self.state["count"].tolist() == [0, 200, 400, 100, 300, 100, 300]
        steps_ok(self.params, self.opts)

    def test_remove(self):
        assert remove(self.params, self.opts, self.state, self.mask) == 2
        assert_aligned(self.params, self.opts, self.state)
        torch.testing.assert_close(self.params["means"][:, 0], torch.tensor([1.0, 3, 5]))
        m1, m2 = moments(self.params, self.opts, "shN")
        torch.testing.assert_close(m1, torch.tensor([1.0, 3, 5]))
        torch.testing.assert_close(m2, torch.tensor([10.0, 30, 50]))
        assert self.state["cue_type"].tolist() == [0, 2, 0]
        steps_ok(self.params, self.opts)

    def test_reset_opacities(self):
        with torch.no_grad():
            self.params["opacities"][0] = -8.0
        reset_opacities(self.params, self.opts, 0.01)
        torch.testing.assert_close(torch.sigmoid(self.params["opacities"][1:]), torch.full((4,), 0.01))
        assert float(self.params["opacities"][0].detach()) == -8.0  # already lower: kept
        m1, _ = moments(self.params, self.opts, "opacities")
        assert (m1 == 0).all()
        m1, _ = moments(self.params, self.opts, "means")  # other keys untouched
        assert m1[0] == 1.0
        steps_ok(self.params, self.opts)

    def test_misaligned_state_raises(self):
        self.state["count"] = torch.zeros(4)
        with pytest.raises(ValueError, match="count"):
            remove(self.params, self.opts, self.state, self.mask)


def rotation(seed: int, n: int) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 4, generator=torch.Generator().manual_seed(seed)), dim=-1)


class TestRules:
    def test_flat_normal_is_smallest_axis_facing_camera(self):
        quats = rotation(1, 64)
        log_s = torch.log(torch.rand(64, 3, generator=torch.Generator().manual_seed(2)) + 0.1)
        means = torch.randn(64, 3)
        cam = torch.tensor([0.5, -2.0, 0.3])
        n = flat_normal(quats, log_s, means, cam)
        axes = quat_to_rotmat(quats)[torch.arange(64), :, log_s.argmin(-1)]
        torch.testing.assert_close(n.abs(), axes.abs())  # +- the smallest-scale column
        assert ((n * (means - cam)).sum(-1) <= 0).all()  # angle to the viewing direction > 90 deg
        torch.testing.assert_close(n.norm(dim=-1), torch.ones(64))

    @pytest.mark.parametrize("literal", [True, False])
    @pytest.mark.parametrize("seed", [0, 8, 48])  # 8, 48: float32 normals 1e-6 off unit length
    def test_tangent_clone_is_orthogonal_to_normal(self, literal, seed):
        torch.manual_seed(seed)
        quats, log_s = rotation(3, 32), torch.randn(32, 3) - 3
        means, grads = torch.randn(32, 3), torch.randn(32, 3) * 1e-3
        n = flat_normal(quats, log_s)
        step = None if literal else torch.exp(log_s).amax(-1)
        d = tangent_clone_means(means, grads, n, step) - means
        assert (d * n).sum(-1).abs().max() < 1e-6
        tangent = grads - (grads * n).sum(-1, keepdim=True) * n
        if literal:
            torch.testing.assert_close(d, tangent)
        else:
            torch.testing.assert_close(d.norm(dim=-1), step)
            assert ((d * tangent).sum(-1) > 0).all()  # along the gradient's tangent part (paper sign)

    def test_tangent_split_offsets_stay_in_the_plane_and_follow_scales(self):
        m = 4000
        quats = rotation(4, 1).expand(m, 4)
        log_s = torch.log(torch.tensor([[0.2, 0.05, 0.001]])).expand(m, 3)
        g = torch.Generator().manual_seed(5)
        off = tangent_split_offsets(quats, log_s, generator=g)  # [2, m, 3]
        assert off.shape == (2, m, 3)
        local = off.reshape(-1, 3) @ quat_to_rotmat(quats[:1])[0]  # world -> local: R^T x
        assert local[:, 2].abs().max() < 1e-6  # no component along the smallest axis
        torch.testing.assert_close(local[:, :2].std(0), torch.tensor([0.2, 0.05]), rtol=0.05, atol=0)
        free = free_split_offsets(quats, log_s, generator=g).reshape(-1, 3) @ quat_to_rotmat(quats[:1])[0]
        torch.testing.assert_close(free.std(0), torch.tensor([0.2, 0.05, 0.001]), rtol=0.05, atol=0)

    def test_near_any(self):
        pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0]])
        centres, radii = torch.tensor([[0.0, 0.1, 0], [5.0, 0.5, 0]]), torch.tensor([0.2, 0.4])
        assert near_any(pts, centres, radii, max_elems=2).tolist() == [True, False, False]


# ----------------------------------------------------------------------------------------------
# The strategy

def typed_scene(types: list[int], scale: float = 0.005):
    """One Gaussian per entry of ``types``, 1 m apart, isotropic-in-plane and flat, all visible."""
    n = len(types)
    params = make_params(n)
    with torch.no_grad():
        params["means"].copy_(torch.stack([torch.arange(n) * 1.0, torch.zeros(n), torch.full((n,), 3.0)], -1))
        params["scales"].copy_(torch.log(torch.tensor([scale, scale, scale / 100])).expand(n, 3))
    optimizers = make_optimizers(params)
    adam_step(params, optimizers, 0.0)
    return params, optimizers


def fake_step(strategy, params, optimizers, state, step, grad2d=0.01, grad3d=(1e-4, 2e-4, 3e-4)):
    """A backward pass's gradients without rendering: every Gaussian visible, pixel grad ``grad2d``."""
    n = params["means"].shape[0]
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.full((n, 2), grad2d)
    params["means"].grad = torch.tensor(grad3d).expand(n, 3).clone()
    info = {"means2d": means2d, "radii": torch.full((n,), 3, dtype=torch.int32), "width": 64, "height": 48,
            "camera_center": torch.zeros(3), "viewmat": torch.eye(4)}
    return strategy.step_post_backward(params, optimizers, state, step, info)


def setup(types, scale=0.005, **cfg):
    """Strategy (scene scale 10 m), typed_scene(types, scale), optimizers and state with cue_type."""
    strategy = IndoorStrategy(IndoorStrategyConfig(**{"max_gaussians": 0, **cfg}))
    params, optimizers = typed_scene(list(types), scale)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(10.0)
    state["cue_type"] = torch.tensor(list(types))
    return strategy, params, optimizers, state


def run_at(step: int, types=(SFM, LINE, PLANE), scale=0.005, **cfg):
    strategy, params, optimizers, state = setup(types, scale, **cfg)
    counts = fake_step(strategy, params, optimizers, state, step)
    assert_aligned(params, optimizers, state)
    return counts, params, state


class TestSchedule:
    @pytest.mark.parametrize("step,sfm,line", [
        (600, 1, 1), (700, 1, 1), (1000, 0, 1), (3500, 0, 1), (4000, 1, 1), (11_900, 1, 1),
        (12_000, None, None), (20_000, None, None), (650, None, None), (500, None, None)])
    def test_paper_schedule(self, step, sfm, line):
        counts, params, state = run_at(step)
        if sfm is None:
            assert counts == {}
            assert params["means"].shape[0] == 3
            return
        assert counts["cloned_sfm"] == sfm and counts["cloned_line"] == line
        assert counts["cloned_plane"] == counts["split_plane"] == 0  # PLANE never
        assert counts["n"] == 3 + sfm + line
        assert sorted(state["cue_type"].tolist()) == sorted([SFM, LINE, PLANE] + [SFM] * sfm + [LINE])

    @pytest.mark.parametrize("step,sfm,line", [(60, 1, 1), (100, 0, 1), (400, 1, 1), (1200, None, None)])
    def test_schedule_scales_with_total_iters(self, step, sfm, line):
        counts, _, _ = run_at(step, total_iters=3000)
        if sfm is None:
            assert counts == {}
        else:
            assert (counts["cloned_sfm"], counts["cloned_line"]) == (sfm, line)

    def test_schedule_values(self):
        s = Schedule.from_config(IndoorStrategyConfig(total_iters=3000, min_refine_every=1, min_reset_every=1))
        assert (s.start, s.stop, s.every, s.reset_every, s.sfm_pause, s.sfm_resume) == (50, 1200, 10, 300, 70, 350)
        # floors of the short run: refine steps average >= 20 views, no opacity reset shorter than 1000
        s = Schedule.from_config(IndoorStrategyConfig(total_iters=3000))
        assert (s.every, s.reset_every, s.big_prune_from) == (20, 0, 300)
        assert not any(s.is_reset(k) for k in range(3000)) and s.is_refine(60) and not s.is_refine(70)
        s = Schedule.from_config(IndoorStrategyConfig(max_gaussians=0))
        assert (s.every, s.reset_every, s.big_prune_from) == (100, 3000, 3000)

    def test_large_gaussians_split_in_their_plane(self):
        counts, params, state = run_at(4000, types=(SFM, LINE, PLANE), scale=0.5, precedence_sigmas=0.0)
        # grow_scale3d * scene_scale = 0.1 < 0.5: split (the parent is replaced by two children)
        assert counts["split_sfm"] == counts["split_line"] == 1 and counts["cloned_line"] == 0
        assert params["means"].shape[0] == 5
        children = torch.where(state["cue_type"] == LINE)[0]
        offsets = params["means"][children].detach() - torch.tensor([1.0, 0.0, 3.0])
        n = flat_normal(params["quats"][children].detach(), params["scales"][children].detach())
        assert (offsets * n).sum(-1).abs().max() < 1e-5
        torch.testing.assert_close(torch.exp(params["scales"][children]).amax(-1), torch.full((2,), 0.5 / 1.6))

    def test_line_clone_moves_in_the_tangent_plane(self):
        _, params, state = run_at(1000, types=(LINE,))
        assert params["means"].shape[0] == 2
        d = (params["means"][1] - params["means"][0]).detach()
        n = flat_normal(params["quats"][:1].detach(), params["scales"][:1].detach())[0]
        assert abs(float(d @ n)) < 1e-6
        torch.testing.assert_close(d.norm(), torch.tensor(0.005))  # one largest scale (line_clone_step = 1)

    @pytest.mark.parametrize("scale,what", [(0.005, "cloned"), (0.5, "split")])
    def test_plane_tangent_rule_grows_planes_within_their_plane(self, scale, what):
        """plane_rule="tangent" (extension): a PLANE Gaussian is cloned / split like LINE, its new
        centres in its own plane; the paper's rule ("none") leaves it alone."""
        counts, params, _ = run_at(4000, types=(PLANE,), scale=scale)
        assert counts[f"{what}_plane"] == 0 and params["means"].shape[0] == 1
        counts, params, state = run_at(4000, types=(PLANE,), scale=scale, plane_rule="tangent")
        assert counts[f"{what}_plane"] == 1 and params["means"].shape[0] == 2
        assert state["cue_type"].tolist() == [PLANE, PLANE]
        offsets = params["means"].detach() - torch.tensor([0.0, 0.0, 3.0])
        n = flat_normal(params["quats"].detach(), params["scales"].detach())
        assert (offsets * n).sum(-1).abs().max() < 1e-5 and offsets.norm(dim=-1).max() > 1e-4
        with pytest.raises(ValueError, match="plane_rule"):
            IndoorStrategy(IndoorStrategyConfig(plane_rule="free", max_gaussians=0))

    def test_line_takes_precedence_over_nearby_sfm(self):
        strategy, params, optimizers, state = setup((SFM, LINE, SFM))
        with torch.no_grad():
            params["means"][0] = params["means"][1] + torch.tensor([0.0075, 0.0, 0.0])  # 1.5 sigma from the LINE one
        counts = fake_step(strategy, params, optimizers, state, 4000)
        assert counts["deferred_sfm"] == 1 and counts["cloned_sfm"] == 1 and counts["cloned_line"] == 1

    def test_accumulation_in_3dgs_units(self):
        strategy, params, optimizers, state = setup((SFM, LINE))
        for step in (601, 602):  # not refine steps
            assert fake_step(strategy, params, optimizers, state, step, grad2d=0.01) == {}
        # pixel gradient (0.01, 0.01) in NDC units: (0.01 * 64 / 2, 0.01 * 48 / 2), twice
        torch.testing.assert_close(state["grad2d"], torch.full((2,), 2 * math.hypot(0.32, 0.24)))
        torch.testing.assert_close(state["grad3d"], torch.tensor([[2e-4, 4e-4, 6e-4]] * 2))
        assert state["count"].tolist() == [2.0, 2.0]

    def test_budget_keeps_the_highest_gradients(self):
        strategy, params, optimizers, state = setup((SFM, LINE, SFM, LINE), max_gaussians=6)
        n = 4
        means2d = torch.zeros(n, 2, requires_grad=True)
        means2d.grad = torch.tensor([[0.01, 0.0], [0.04, 0.0], [0.03, 0.0], [0.02, 0.0]])
        params["means"].grad = torch.zeros(n, 3)
        info = {"means2d": means2d, "radii": torch.full((n,), 3, dtype=torch.int32), "width": 64,
                "height": 48, "camera_center": torch.zeros(3), "viewmat": torch.eye(4)}
        counts = strategy.step_post_backward(params, optimizers, state, 4000, info)
        assert counts["n"] == 6 and counts["cloned_sfm"] == 1 and counts["cloned_line"] == 1
        # the two highest gradients (rows 1 and 2) were cloned: their copies are appended
        torch.testing.assert_close(params["means"][4:, 0], torch.tensor([1.0, 2.0]), rtol=0, atol=0.05)
        full = budget_mask(torch.ones(3, dtype=torch.bool), torch.rand(3), 0)
        assert not full.any() and budget_mask(torch.ones(3, dtype=torch.bool), torch.rand(3), None).all()

    def test_low_gradient_is_not_densified(self):
        strategy, params, optimizers, state = setup((SFM, LINE))
        counts = fake_step(strategy, params, optimizers, state, 4000, grad2d=1e-6)
        assert counts["cloned_sfm"] == counts["cloned_line"] == 0 and counts["n"] == 2
        assert state["count"].sum() == 0  # accumulators reset after a refine step

    def test_missing_cue_type_raises(self):
        strategy, params, optimizers, state = setup((SFM, LINE))
        state["cue_type"] = None
        with pytest.raises(ValueError, match="cue_type"):
            fake_step(strategy, params, optimizers, state, 600)

    def test_check_sanity(self):
        strategy = IndoorStrategy()
        params, optimizers = typed_scene([SFM])
        strategy.check_sanity(params, optimizers)
        optimizers["means"] = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1, 3))])
        with pytest.raises(ValueError, match="means"):
            strategy.check_sanity(params, optimizers)
        del optimizers["means"]
        with pytest.raises(ValueError, match="same keys"):
            strategy.check_sanity(params, optimizers)


class TestPruneAndReset:
    @pytest.mark.parametrize("step", [1000, 4000])
    def test_low_opacity_pruned_for_every_type(self, step):
        strategy, params, optimizers, state = setup([SFM, LINE, PLANE, SFM, LINE, PLANE])
        with torch.no_grad():
            params["opacities"][:3] = -7.0  # sigmoid < 0.005
        counts = fake_step(strategy, params, optimizers, state, step, grad2d=0.0)
        assert (counts["pruned_sfm"], counts["pruned_line"], counts["pruned_plane"]) == (1, 1, 1)
        assert state["cue_type"].tolist() == [SFM, LINE, PLANE]
        assert_aligned(params, optimizers, state)

    def test_too_large_pruned_after_first_reset_only(self):
        for step, pruned in [(2000, 0), (3100, 1)]:
            counts, params, _ = run_at(step, types=(PLANE,), scale=2.0)  # > 0.1 * scene scale 10
            assert counts["pruned_plane"] == pruned, step

    def test_opacity_reset(self):
        counts, params, _ = run_at(3000, types=(PLANE, PLANE))
        assert counts["opacity_reset"] == 1
        torch.testing.assert_close(torch.sigmoid(params["opacities"]), torch.full((2,), 0.01))
        counts, params, _ = run_at(12_000, types=(PLANE,))
        assert counts == {} and float(params["opacities"][0].detach()) == 2.0  # no reset after the stop


def test_render_backward_refine_smoke():
    """A real render + backward, then a refine step: counts come back, rows aligned, no NaN."""
    from splat.bench import bench_camera, surface_gaussians
    from splat.rasterize import render

    torch.manual_seed(0)
    init = surface_gaussians(150, sh_degree=1, seed=0)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in init.items()})
    optimizers = make_optimizers(params)
    # these Gaussians are 0.3-1.9 m wide: with precedence on, LINE ones would defer every SFM one
    strategy = IndoorStrategy(IndoorStrategyConfig(grow_grad2d=1e-9, total_iters=3000, precedence_sigmas=0.0, max_gaussians=0))
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(5.0)
    state["cue_type"] = torch.arange(150) % 3
    cam = bench_camera(48, 36)
    for step in (59, 60):  # accumulate once, then refine at 60 (scaled schedule: every 10 from 50)
        out = render(params, cam, sh_degree=1, backend="torch")
        info = {**out, "width": cam.width, "height": cam.height, "camera_center": cam.center,
                "viewmat": cam.viewmat}
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = (out["rgb"] - 0.5).abs().mean() + 0.1 * (out["depth"] - 3.0).abs().mean()
        loss.backward()
        for opt in optimizers.values():
            opt.step()
        counts = strategy.step_post_backward(params, optimizers, state, step, info)
        for opt in optimizers.values():
            opt.zero_grad(set_to_none=True)
    assert out["visible"].any()
    assert counts["cloned_sfm"] + counts["split_sfm"] > 0 and counts["cloned_line"] + counts["split_line"] > 0
    assert counts["cloned_plane"] == counts["split_plane"] == 0
    assert counts["n"] == params["means"].shape[0] > 150
    assert_aligned(params, optimizers, state)
    assert all(torch.isfinite(p).all() for p in params.values())
    out = render(params, cam, sh_degree=1, backend="torch")  # the new Gaussians render and train
    out["rgb"].mean().backward()
    assert torch.isfinite(params["means"].grad).all()


@pytest.mark.parametrize("key, index, value", [("opacities", 2, float("nan")), ("means", 0, float("nan")),
                                               ("scales", (slice(None), 0), 89.0)])
def test_density_control_leaves_no_non_finite_gaussian(key, index, value):
    """A NaN opacity was cloned and never pruned (sigmoid(NaN) < prune_opa is False), a split of a
    Gaussian whose exp(scale) overflows float32 made non-finite means: the refine step prunes every
    Gaussian with a non-finite parameter (the guard rolled such steps back in training)."""
    from geocues.types import CueType

    types = [int(CueType.SFM), int(CueType.LINE), int(CueType.PLANE)] * 2
    params = make_params(len(types))
    with torch.no_grad():
        params[key][index] = value
    opts = make_optimizers(params)
    adam_step(params, opts, 0.0)
    strategy = IndoorStrategy(IndoorStrategyConfig(max_gaussians=0))
    state = strategy.initialize_state(1.0)
    state["cue_type"] = torch.tensor(types)
    n = len(types)
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.full((n, 2), 1.0)
    params["means"].grad = torch.full((n, 3), 1.0)
    info = {"means2d": means2d, "radii": torch.full((n,), 3, dtype=torch.int32), "width": 64, "height": 48,
            "camera_center": torch.zeros(3)}
    strategy.step_post_backward(params, opts, state, 600, info)
    assert len(params["means"]) > 0
    for name, p in params.items():
        assert torch.isfinite(p.detach()).all(), name


def test_density_control_of_an_empty_model_is_a_no_op():
    """A model pruned to nothing reached its next refine step: the non-finite check's reshape(0, -1)
    raised (review finding); it returns its counts."""
    params = make_params(0)
    opts = make_optimizers(params)
    strategy = IndoorStrategy(IndoorStrategyConfig(max_gaussians=0))
    state = strategy.initialize_state(1.0)
    state["cue_type"] = torch.zeros(0, dtype=torch.long)
    means2d = torch.zeros(0, 2, requires_grad=True)
    means2d.grad = torch.zeros(0, 2)
    params["means"].grad = torch.zeros(0, 3)
    info = {"means2d": means2d, "radii": torch.zeros(0, dtype=torch.int32), "width": 64, "height": 48,
            "camera_center": torch.zeros(3)}
    counts = strategy.step_post_backward(params, opts, state, 600, info)
    assert counts["n"] == 0 and len(params["means"]) == 0


def test_resolve_budget():
    """"auto" is AUTO_BUDGET_PER_PIXEL x the view's pixels, to a thousand, at least AUTO_BUDGET_MIN; a number stays."""
    from splat.strategy import AUTO_BUDGET_MIN, AUTO_BUDGET_PER_PIXEL, resolve_budget

    assert (AUTO_BUDGET_PER_PIXEL, AUTO_BUDGET_MIN) == (2, 100_000)
    assert resolve_budget("auto", 160 * 120) == 100_000 and resolve_budget("auto", 320 * 240) == 154_000
    assert resolve_budget("auto", 640 * 480) == 614_000 and resolve_budget("auto", 1) == 100_000
    assert resolve_budget(0, 160 * 120) == 0 and resolve_budget(150_000, 1) == 150_000
    with pytest.raises(ValueError, match="auto needs a training view"):
        resolve_budget("auto", 0)
    with pytest.raises(ValueError, match="not 'auto'"):  # the strategy counts against a number
        IndoorStrategy(IndoorStrategyConfig())
