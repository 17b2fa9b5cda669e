"""IndoorGS per-Gaussian-type adaptive density control (paper §4.2; 3DGS defaults otherwise).

gsplat's pattern: ``IndoorStrategyConfig`` holds thresholds only; the running state is a plain dict
from ``initialize_state()`` handed back each step; the row operations are the free functions of
splat/densify_ops.py. The trainer calls, per iteration,

    strategy.step_pre_backward(params, optimizers, state, step, info)
    loss.backward()
    counts = strategy.step_post_backward(params, optimizers, state, step, info)

Per type (``state["cue_type"]``, geocues.types.CueType):
  SFM (G_M)   3DGS clone / split in (start, sfm_pause] and (sfm_resume, stop); none in between.
  LINE (G_L)  tangent-space clone / split on every refine step in (start, stop).
  PLANE (G_S) never cloned or split (``plane_rule="tangent"``, an extension: as LINE).
A type left out of ``custom_types`` gets plain 3DGS density control instead (the ablation rows).
Every type is pruned (low opacity; too large in world after the first opacity reset) and has its
opacity reset. "G_L takes precedence over G_M": on a refine step the LINE candidates are chosen
first; an SFM candidate within ``precedence_sigmas`` largest-scales of a LINE candidate is left to
the LINE rule (not densified) on that step. docs/density_control.md has the reasoning.

All iteration counts are the paper's for 30,000 iterations and scale with ``total_iters / 30000``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from geocues.extract_checks import flag as cli_flag
from geocues.types import CueType
from splat.densify_ops import (duplicate, flat_normal, free_split_offsets, near_any, remove,
                               reset_opacities, split, tangent_clone_means, tangent_split_offsets)

log = logging.getLogger(__name__)

PAPER_ITERS = 30_000
REQUIRED_KEYS = ("means", "quats", "scales", "opacities")
TYPE_NAMES = {int(t): t.name.lower() for t in CueType}  # 0 -> "sfm", 1 -> "line", 2 -> "plane"


AUTO_BUDGET_PER_PIXEL = 2
AUTO_BUDGET_MIN = 100_000
"""--strategy.max-gaussians auto: AUTO_BUDGET_PER_PIXEL Gaussians per pixel of the largest training view,
at least AUTO_BUDGET_MIN: the benchmark protocols' budgets (100k for rooms at 160x120, 150k for ICL at
320x240), which were as good as larger ones (docs/training.md, "Budget")."""

_HALF_SIZES: dict[tuple, Tensor] = {}


def resolve_budget(max_gaussians: int | str, view_pixels: int) -> int:
    """The Gaussian budget a run trains under: ``max_gaussians`` as given (0 = no limit), or for
    "auto" AUTO_BUDGET_PER_PIXEL x ``view_pixels`` (the largest training view's W x H at the training
    resolution) rounded to a thousand, at least AUTO_BUDGET_MIN."""
    if max_gaussians != "auto":
        return int(max_gaussians)
    if view_pixels <= 0:
        raise ValueError(f"--strategy.max-gaussians auto needs a training view with pixels, got {view_pixels}")
    return max(AUTO_BUDGET_MIN, round(AUTO_BUDGET_PER_PIXEL * view_pixels, -3))


def _half_size(width: int, height: int, device: torch.device) -> Tensor:
    """[W / 2, H / 2] on ``device``, made once per size (a copy to a GPU waits for it each time)."""
    key = (width, height, device)
    if key not in _HALF_SIZES:
        _HALF_SIZES[key] = torch.tensor([width / 2.0, height / 2.0], device=device)
    return _HALF_SIZES[key]


@dataclass
class IndoorStrategyConfig:
    """Thresholds and schedule of the per-type density control (iterations for a 30k run)."""

    total_iters: int = PAPER_ITERS
    """Length of the run; every iteration count below is scaled by total_iters / 30000. `splat train`
    sets it from --iters (giving it there is an error)."""
    refine_start: int = 500
    """Densify / prune only after this iteration (3DGS)."""
    refine_stop: int = 12_000
    """No density control (nor opacity reset) from this iteration on (IndoorGS: 12k)."""
    refine_every: int = 100
    """Densify and prune every this many iterations (3DGS)."""
    reset_every: int = 3000
    """Reset opacities every this many iterations (3DGS)."""
    sfm_pause: int = 700
    """SFM Gaussians stop densifying after this iteration (IndoorGS: free in 500-700)."""
    sfm_resume: int = 3500
    """SFM Gaussians densify again after this iteration (IndoorGS: none in 700-3500)."""
    grow_grad2d: float = 0.0002
    """Mean 2D-mean gradient norm (NDC units, as 3DGS) above which a Gaussian is cloned or split."""
    grow_scale3d: float = 0.01
    """Largest scale, times the scene scale, at or below which a Gaussian is cloned, else split."""
    prune_opa: float = 0.005
    """Gaussians with opacity below this are pruned (every type)."""
    prune_scale3d: float = 0.1
    """After the first opacity reset, Gaussians larger than this times the scene scale are pruned."""
    reset_opacity: float = 0.01
    """Opacities are clamped to this value at each reset (3DGS)."""
    line_clone_step: float = 1.0
    """LINE clone offset along the tangent mean gradient, in parent's largest scales (0 = in place)."""
    line_clone_literal: bool = False
    """Place LINE clones at mu + grad - (n.grad)n with the raw mean gradient (paper verbatim)."""
    min_refine_every: int = 20
    """Floor of the scaled refine period: a refine step averages the gradients of this many views at least."""
    min_reset_every: int = 1000
    """Opacity resets only when the scaled reset period is at least this long (opacities need
    hundreds of steps to recover at the 3DGS learning rate); shorter runs never reset."""
    max_gaussians: int | Literal["auto"] = "auto"
    """Budget: growth stops at this many Gaussians, highest mean gradients first. "auto" (default):
    2 x the pixels of the largest training view, at least 100k (154k at 320x240, 614k at 640x480);
    0 = no limit (3DGS; on a short run growth reached 2.5 M on a 24-view room at 160x120)."""
    precedence_sigmas: float = 2.0
    """SFM candidates within this many largest-scales of a LINE candidate are not densified (0 = off)."""
    plane_rule: Literal["none", "tangent"] = "none"
    """PLANE Gaussians under IndoorGS's rule: "none" (the paper: never cloned or split) or
    "tangent" (extension: LINE's tangent clone / split, so a plane Gaussian grows within its own
    plane and stays flat; for walls that the plane cues cover too thinly). Applies while PLANE is
    in custom_types; PLANE candidates do not defer nearby SFM ones (only LINE candidates do)."""
    custom_types: tuple[str, ...] = ("SFM", "LINE", "PLANE")
    """Types under IndoorGS's own rule (above). A type left out gets plain 3DGS density control:
    clone in place / free split on every refine step in (start, stop) -- the paper's Tab. 3 rows
    "w/o customised ADC" (none listed), "w/o line / SfM / plane ADC" (that one left out)."""

    def validate(self) -> None:
        """Raise ValueError naming (as `splat train` spells it) the first impossible setting: a NaN
        threshold trained to the end and then failed writing report.json, --strategy.reset-opacity 2
        failed at the first reset (step 3000 of 30k) without naming the option."""
        def flag(name: str) -> str:
            return cli_flag(f"strategy.{name}")

        for name in ("refine_start", "refine_stop", "sfm_pause", "sfm_resume", "min_reset_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"{flag(name)} must be >= 0, got {getattr(self, name)}")
        for name in ("refine_every", "reset_every", "min_refine_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{flag(name)} must be >= 1, got {getattr(self, name)}")
        for name in ("grow_grad2d", "grow_scale3d", "prune_scale3d"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{flag(name)} must be a finite number > 0, got {getattr(self, name)}")
        for name in ("line_clone_step", "precedence_sigmas"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{flag(name)} must be a finite number >= 0, got {getattr(self, name)}")
        if not 0 <= self.prune_opa < 1:  # 1 prunes every Gaussian at the first refine step
            raise ValueError(f"{flag('prune_opa')} is an opacity and must be in [0, 1), got {self.prune_opa}")
        if not 0 < self.reset_opacity < 1:
            raise ValueError(f"{flag('reset_opacity')} is an opacity and must be in (0, 1), got {self.reset_opacity}")
        if self.plane_rule not in ("none", "tangent"):
            raise ValueError(f"{flag('plane_rule')} must be 'none' or 'tangent', got {self.plane_rule!r}")
        if bad := [t for t in self.custom_types if t not in CueType.__members__]:
            raise ValueError(f"{flag('custom_types')}: unknown cue types {bad}; choose from {list(CueType.__members__)}")


@dataclass(frozen=True)
class Schedule:
    """The config's iteration counts scaled to the run length (all >= 1 where they are periods)."""

    start: int
    stop: int
    every: int
    reset_every: int  # 0 = no opacity reset
    big_prune_from: int  # too-large Gaussians are pruned after this step (3DGS: the first reset)
    sfm_pause: int
    sfm_resume: int

    @classmethod
    def from_config(cls, cfg: IndoorStrategyConfig) -> "Schedule":
        f = cfg.total_iters / PAPER_ITERS
        return cls(start=round(cfg.refine_start * f), stop=round(cfg.refine_stop * f),
                   every=max(1, cfg.min_refine_every, round(cfg.refine_every * f)),
                   reset_every=reset if (reset := round(cfg.reset_every * f)) >= max(1, cfg.min_reset_every) else 0,
                   big_prune_from=round(cfg.reset_every * f),
                   sfm_pause=round(cfg.sfm_pause * f), sfm_resume=round(cfg.sfm_resume * f))

    def is_refine(self, step: int) -> bool:
        return self.start < step < self.stop and step % self.every == 0

    def sfm_active(self, step: int) -> bool:
        """IndoorGS §4.2: SFM densifies in (start, sfm_pause] and (sfm_resume, stop)."""
        return self.is_refine(step) and (step <= self.sfm_pause or step > self.sfm_resume)

    def is_reset(self, step: int) -> bool:
        return self.reset_every > 0 and 0 < step < self.stop and step % self.reset_every == 0


def budget_mask(candidates: torch.Tensor, score: torch.Tensor, room: int | None) -> torch.Tensor:
    """The candidates [N] bool to grow when only ``room`` more Gaussians fit (None: all of them):
    the ``room`` highest-scoring ones (a clone or a split adds one Gaussian each)."""
    if room is None or int(candidates.sum()) <= room:
        return candidates
    keep = torch.zeros_like(candidates)
    if room > 0:
        idx = torch.where(candidates)[0]
        keep[idx[torch.topk(score[idx], room).indices]] = True
    return keep


class IndoorStrategy:
    """Per-Gaussian-type adaptive density control of IndoorGS (§4.2). See the module docstring."""

    def __init__(self, cfg: IndoorStrategyConfig | None = None) -> None:
        self.cfg = cfg or IndoorStrategyConfig(max_gaussians=0)
        if self.cfg.max_gaussians == "auto":  # the training views' size sets it: splat/train_setup.py
            raise ValueError("IndoorStrategy needs a number of Gaussians as max_gaussians, not 'auto': "
                             "resolve it with resolve_budget(max_gaussians, pixels of the largest training view)")
        if self.cfg.total_iters <= 0:
            raise ValueError(f"total_iters must be positive, got {self.cfg.total_iters}")
        bad = [t for t in self.cfg.custom_types if t not in CueType.__members__]
        if bad:
            raise ValueError(f"strategy.custom_types: unknown cue types {bad}; choose from {list(CueType.__members__)}")
        self._plain = [CueType[t].value for t in CueType.__members__ if t not in self.cfg.custom_types]
        if self.cfg.plane_rule not in ("none", "tangent"):
            raise ValueError(f"strategy.plane_rule must be 'none' or 'tangent', got {self.cfg.plane_rule!r}")
        self.schedule = Schedule.from_config(self.cfg)

    # -- state and checks ------------------------------------------------------------------------
    def initialize_state(self, scene_scale: float) -> dict[str, Any]:
        """Running state: per-Gaussian tensors (created lazily on the params' device) + the scale.

        grad2d [N]  sum over views of |d loss / d means2d| in NDC units (pixel grad * (W/2, H/2))
        grad3d [N, 3] sum over the same views of d loss / d means (world units)
        count [N]   number of views in which the Gaussian was visible since the last refine step
        cue_type [N] int64 CueType, set by the trainer after this call.
        """
        if not scene_scale > 0:
            raise ValueError(f"scene_scale must be positive, got {scene_scale}")
        return {"grad2d": None, "grad3d": None, "count": None, "cue_type": None,
                "scene_scale": float(scene_scale)}

    def check_sanity(self, params, optimizers: dict) -> None:
        """Raise ValueError unless params and optimizers have the same keys, each optimizer one group
        holding exactly its parameter, and the required keys share one N."""
        if set(params.keys()) != set(optimizers.keys()):
            raise ValueError(f"params and optimizers must have the same keys, got {sorted(params.keys())} "
                             f"and {sorted(optimizers.keys())}")
        missing = [k for k in REQUIRED_KEYS if k not in params]
        if missing:
            raise ValueError(f"params miss {missing}; the strategy needs {list(REQUIRED_KEYS)}")
        n = params["means"].shape[0]
        for key, opt in optimizers.items():
            groups = opt.param_groups
            if len(groups) != 1 or len(groups[0]["params"]) != 1 or groups[0]["params"][0] is not params[key]:
                raise ValueError(f"optimizers[{key!r}] must have one param group holding exactly params[{key!r}]")
            if params[key].shape[0] != n:
                raise ValueError(f"params[{key!r}] has {params[key].shape[0]} rows, means has {n}")

    def _check_state(self, params, state: dict) -> Tensor:
        n = params["means"].shape[0]
        cue_type = state.get("cue_type")
        if not isinstance(cue_type, Tensor) or tuple(cue_type.shape) != (n,):
            got = None if not isinstance(cue_type, Tensor) else tuple(cue_type.shape)
            raise ValueError(f"state['cue_type'] must be a tensor of shape ({n},) (set it after "
                             f"initialize_state), got {got}")
        return cue_type

    # -- per-step hooks --------------------------------------------------------------------------
    def step_pre_backward(self, params, optimizers: dict, state: dict, step: int, info: dict) -> None:
        """Keep the 2D means' gradient (render() already calls retain_grad; harmless twice)."""
        if "means2d" not in info:
            raise ValueError("info must hold 'means2d' (the renderer's projected means)")
        if info["means2d"].requires_grad:
            info["means2d"].retain_grad()

    def step_post_backward(self, params, optimizers: dict, state: dict, step: int,
                           info: dict) -> dict[str, int]:
        """Accumulate gradients; on refine steps densify per type and prune; reset opacities.

        Returns the counts of what was done at this step ({} when nothing was scheduled):
        cloned_<type>, split_<type>, pruned_<type> (type = sfm, line, plane), deferred_sfm (SFM
        candidates left to a LINE neighbour), opacity_reset (0/1), n (Gaussians after the step).
        """
        sched = self.schedule
        if step >= sched.stop:
            return {}
        self._check_state(params, state)
        self._update_state(params, state, info)
        counts: dict[str, int] = {}
        if sched.is_refine(step):
            counts.update(self._grow(params, optimizers, state, step, info))
            counts.update(self._prune(params, optimizers, state, step))
            for key in ("grad2d", "grad3d", "count"):
                state[key].zero_()
        if sched.is_reset(step):
            reset_opacities(params, optimizers, self.cfg.reset_opacity)
            counts["opacity_reset"] = 1
        if counts:
            counts["n"] = int(params["means"].shape[0])
            log.debug("step %d density control: %s", step, counts)
        return counts

    def _update_state(self, params, state: dict, info: dict) -> None:
        for key in ("means2d", "radii", "width", "height"):
            if key not in info:
                raise ValueError(f"info must hold {key!r} for density control")
        means2d = info["means2d"]
        n = params["means"].shape[0]
        device = params["means"].device
        if state["count"] is None or state["count"].shape[0] != n:
            if state["count"] is not None:
                raise ValueError(f"state rows ({state['count'].shape[0]}) do not match the {n} Gaussians")
            state["grad2d"] = torch.zeros(n, device=device)
            state["grad3d"] = torch.zeros(n, 3, device=device)
            state["count"] = torch.zeros(n, device=device)
        if means2d.grad is None:
            return  # nothing rendered with gradients (e.g. an evaluation step)
        if tuple(means2d.shape) != (n, 2):
            raise ValueError(f"info['means2d'] must have shape ({n}, 2), got {tuple(means2d.shape)}")
        # Dense updates masked by visibility (no boolean indexing: a gather and a scatter per state
        # tensor cost more than the whole pass); adding 0 leaves the invisible rows bit-identical.
        visible = info["radii"] > 0  # [N]
        scale = _half_size(info["width"], info["height"], means2d.device)
        grad = (means2d.grad.detach().float() * scale).norm(dim=-1)  # [N] pixel units
        state["grad2d"] += torch.where(visible, grad, 0.0)
        means_grad = params["means"].grad
        if means_grad is not None:
            state["grad3d"] += torch.where(visible[:, None], means_grad.detach().float(), 0.0)
        state["count"] += visible.to(state["count"].dtype)

    # -- refine ----------------------------------------------------------------------------------
    @torch.no_grad()
    def _grow(self, params, optimizers: dict, state: dict, step: int, info: dict) -> dict[str, int]:
        cfg, sched = self.cfg, self.schedule
        cue_type = state["cue_type"]
        count = state["count"].clamp_min(1.0)
        high = state["grad2d"] / count > cfg.grow_grad2d  # [N]
        max_scale = torch.exp(params["scales"]).amax(-1)  # [N]
        small = max_scale <= cfg.grow_scale3d * state["scene_scale"]
        custom = self.cfg.custom_types
        is_line = (cue_type == CueType.LINE) & high if "LINE" in custom else torch.zeros_like(high)
        is_sfm = (cue_type == CueType.SFM) & high if ("SFM" in custom and sched.sfm_active(step)) \
            else torch.zeros_like(high)
        # extension: PLANE under the LINE rule (tangent clone / split within its own plane)
        is_plane = (cue_type == CueType.PLANE) & high if ("PLANE" in custom and cfg.plane_rule == "tangent") \
            else torch.zeros_like(high)
        # types under plain 3DGS control: every refine step, clone in place / free split
        is_plain = torch.isin(cue_type, torch.tensor(self._plain, device=cue_type.device)) & high \
            if self._plain else torch.zeros_like(high)
        # G_L takes precedence over G_M: SFM candidates near a LINE candidate are left to it
        deferred = torch.zeros_like(high)
        if cfg.precedence_sigmas > 0 and is_sfm.any() and is_line.any():
            means = params["means"]
            near = near_any(means[is_sfm], means[is_line], cfg.precedence_sigmas * max_scale[is_line])
            deferred[torch.where(is_sfm)[0][near]] = True
            is_sfm &= ~deferred
        grow = budget_mask(is_line | is_sfm | is_plane | is_plain, state["grad2d"] / count,
                           cfg.max_gaussians - params["means"].shape[0] if cfg.max_gaussians > 0 else None)
        clone, splt = grow & small, grow & ~small

        # clone positions: LINE (and PLANE under "tangent") tangent clone (§4.2), SFM in place (3DGS)
        tangent = ((cue_type == CueType.LINE) & ~is_plain) | is_plane  # [N]
        clone_means = params["means"][clone].clone()
        line_rows = tangent[clone]
        if line_rows.any():
            sel = torch.where(clone)[0][line_rows]
            grad3d = state["grad3d"][sel] / count[sel, None]
            normals = flat_normal(params["quats"][sel], params["scales"][sel], params["means"][sel],
                                  info.get("camera_center"))
            step_len = None if cfg.line_clone_literal else cfg.line_clone_step * max_scale[sel]
            clone_means[line_rows] = tangent_clone_means(params["means"][sel], grad3d.to(normals), normals,
                                                         step_len)
        # split offsets: LINE tangent split (§4.2), SFM free split (3DGS)
        sel = torch.where(splt)[0]
        offsets = free_split_offsets(params["quats"][sel], params["scales"][sel])
        line_rows = tangent[sel]
        if line_rows.any():
            offsets[:, line_rows] = tangent_split_offsets(params["quats"][sel[line_rows]],
                                                          params["scales"][sel[line_rows]])

        counts = {}
        for t, name in TYPE_NAMES.items():
            counts[f"cloned_{name}"] = int((clone & (cue_type == t)).sum())
            counts[f"split_{name}"] = int((splt & (cue_type == t)).sum())
        counts["deferred_sfm"] = int(deferred.sum())
        n_clone = duplicate(params, optimizers, state, clone, clone_means)
        split_mask = torch.cat([splt, torch.zeros(n_clone, dtype=torch.bool, device=splt.device)])
        split(params, optimizers, state, split_mask, offsets)  # clones are not split again (3DGS)
        return counts

    @torch.no_grad()
    def _prune(self, params, optimizers: dict, state: dict, step: int) -> dict[str, int]:
        cfg = self.cfg
        prune = torch.sigmoid(params["opacities"]) < cfg.prune_opa
        for value in params.values():  # a non-finite Gaussian (NaN opacity: sigmoid(NaN) < x is False, or a split
            prune |= ~torch.isfinite(value.reshape(value.shape[0], math.prod(value.shape[1:]))).all(-1)  # whose
            # exp(scale) overflowed) goes too; shape[1:] spelled out: an empty model has no -1 to infer
        if step > self.schedule.big_prune_from:
            prune |= torch.exp(params["scales"]).amax(-1) > cfg.prune_scale3d * state["scene_scale"]
        cue_type = state["cue_type"]
        counts = {f"pruned_{name}": int((prune & (cue_type == t)).sum()) for t, name in TYPE_NAMES.items()}
        remove(params, optimizers, state, prune)
        return counts
