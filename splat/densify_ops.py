"""Adaptive density control, free functions: the row operations and the IndoorGS §4.2 rules.

Row operations (gsplat's pattern): ``duplicate``, ``split``, ``remove`` and ``reset_opacities``
rewrite every parameter *and its Adam moments* together and carry every per-Gaussian tensor of the
strategy state along (``cue_type``, gradient accumulators, view counts), so rows stay aligned. New
rows get zero Adam moments; kept rows keep theirs.

The rules, one function each (IndoorGS §4.2; 3DGS where the paper says nothing):
  ``flat_normal``            normal of a flat Gaussian, facing the camera
  ``tangent_clone_means``    LINE clone: mu + grad - (n . grad) n (tangent-space clone)
  ``tangent_split_offsets``  LINE split: N(0, scales) with the smallest-axis component zeroed
  ``free_split_offsets``     SFM split: N(0, scales) (3DGS)
  ``near_any``               the neighbourhood test behind "G_L takes precedence over G_M"

Parameters follow the project contract: ``params`` is a ParameterDict (or dict of Parameters) with
means [N, 3], quats [N, 4] (wxyz, unnormalised), scales [N, 3] (log), opacities [N] (logits),
sh0 [N, 1, 3], shN [N, K, 3]; ``optimizers[key]`` is an Adam with one group holding ``params[key]``.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from splat.projection import quat_to_rotmat

SPLIT_SCALE_DIV = 1.6  # 3DGS: split children get the parent's scales / (0.8 * 2)


# ----------------------------------------------------------------------------------------------
# Row operations


def _check_state_rows(state: dict, n: int) -> None:
    """Every tensor in ``state`` is per-Gaussian: its first dimension must be N."""
    for key, value in state.items():
        if isinstance(value, Tensor) and (value.dim() == 0 or value.shape[0] != n):
            raise ValueError(f"state[{key!r}] has shape {tuple(value.shape)}; per-Gaussian state must "
                             f"have {n} rows (the number of Gaussians)")


@torch.no_grad()
def _rewrite(params, optimizers: dict, param_fn: Callable[[str, Tensor], Tensor],
             moment_fn: Callable[[Tensor], Tensor], names: list[str] | None = None) -> None:
    """Replace ``params[name]`` by ``param_fn(name, p)`` and each per-row Adam tensor v by
    ``moment_fn(v)``; the optimizer's group and state move to the new Parameter."""
    for name in list(params.keys()) if names is None else names:
        old = params[name]
        n_old = old.shape[0]
        new = torch.nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        params[name] = new
        opt = optimizers.get(name)
        if opt is None:
            continue
        slot = opt.state.pop(old, None)
        for group in opt.param_groups:
            group["params"] = [new if p is old else p for p in group["params"]]
        if slot is not None:
            for key, v in slot.items():  # exp_avg, exp_avg_sq (max_exp_avg_sq); "step" is shared
                if isinstance(v, Tensor) and v.dim() > 0 and v.shape[0] == n_old:
                    slot[key] = moment_fn(v)
            opt.state[new] = slot


@torch.no_grad()
def duplicate(params, optimizers: dict, state: dict, mask: Tensor, means: Tensor | None = None) -> int:
    """Append a copy of each Gaussian in ``mask`` [N] (3DGS clone); return how many.

    ``means`` [M, 3] (M = mask.sum(), in row order) places the copies elsewhere (IndoorGS tangent
    clone); default: at the parent's position. Copies get zero Adam moments; state rows are copied,
    so a copy inherits its parent's ``cue_type``.
    """
    n = params["means"].shape[0]
    if tuple(mask.shape) != (n,):
        raise ValueError(f"mask must have shape ({n},), got {tuple(mask.shape)}")
    _check_state_rows(state, n)
    sel = torch.where(mask)[0]
    m = len(sel)
    if means is not None and tuple(means.shape) != (m, 3):
        raise ValueError(f"clone means must have shape ({m}, 3), got {tuple(means.shape)}")
    if m == 0:
        return 0

    def param_fn(name: str, p: Tensor) -> Tensor:
        rows = means.to(p) if name == "means" and means is not None else p[sel]
        return torch.cat([p, rows])

    _rewrite(params, optimizers, param_fn, lambda v: torch.cat([v, v.new_zeros((m, *v.shape[1:]))]))
    for key, v in state.items():
        if isinstance(v, Tensor):
            state[key] = torch.cat([v, v[sel]])
    return m


@torch.no_grad()
def split(params, optimizers: dict, state: dict, mask: Tensor, offsets: Tensor) -> int:
    """Replace each Gaussian in ``mask`` [N] by two children at mean + offsets[k]; return how many.

    ``offsets`` [2, M, 3] world-space (M = mask.sum(), row order), from ``free_split_offsets`` or
    ``tangent_split_offsets``. Children get scales / 1.6 (3DGS), the parent's other parameters,
    zero Adam moments and the parent's state rows. New row order: kept rows, then children
    (first children of all parents, then second children).
    """
    n = params["means"].shape[0]
    if tuple(mask.shape) != (n,):
        raise ValueError(f"mask must have shape ({n},), got {tuple(mask.shape)}")
    _check_state_rows(state, n)
    sel, rest = torch.where(mask)[0], torch.where(~mask)[0]
    m = len(sel)
    if tuple(offsets.shape) != (2, m, 3):
        raise ValueError(f"split offsets must have shape (2, {m}, 3), got {tuple(offsets.shape)}")
    if m == 0:
        return 0

    def param_fn(name: str, p: Tensor) -> Tensor:
        if name == "means":
            children = (p[sel][None] + offsets.to(p)).reshape(-1, 3)  # [2M, 3]
        elif name == "scales":
            children = (p[sel] - math.log(SPLIT_SCALE_DIV)).repeat(2, 1)  # log(s / 1.6)
        else:
            children = p[sel].repeat(2, *[1] * (p.dim() - 1))
        return torch.cat([p[rest], children])

    _rewrite(params, optimizers, param_fn,
             lambda v: torch.cat([v[rest], v.new_zeros((2 * m, *v.shape[1:]))]))
    for key, v in state.items():
        if isinstance(v, Tensor):
            state[key] = torch.cat([v[rest], v[sel].repeat(2, *[1] * (v.dim() - 1))])
    return m


@torch.no_grad()
def remove(params, optimizers: dict, state: dict, mask: Tensor) -> int:
    """Delete the Gaussians in ``mask`` [N] with their Adam moments and state rows; return how many."""
    n = params["means"].shape[0]
    if tuple(mask.shape) != (n,):
        raise ValueError(f"mask must have shape ({n},), got {tuple(mask.shape)}")
    _check_state_rows(state, n)
    keep = torch.where(~mask)[0]
    if len(keep) == n:
        return 0
    _rewrite(params, optimizers, lambda name, p: p[keep], lambda v: v[keep])
    for key, v in state.items():
        if isinstance(v, Tensor):
            state[key] = v[keep]
    return n - len(keep)


@torch.no_grad()
def reset_opacities(params, optimizers: dict, value: float) -> None:
    """Clamp every opacity to at most ``value`` (post-sigmoid; 3DGS: 0.01) and zero its Adam moments."""
    if not 0.0 < value < 1.0:
        raise ValueError(f"opacity reset value must be in (0, 1), got {value}")
    cap = math.log(value) - math.log1p(-value)  # logit(value)
    _rewrite(params, optimizers, lambda name, p: torch.clamp(p, max=cap), torch.zeros_like,
             names=["opacities"])


# ----------------------------------------------------------------------------------------------
# IndoorGS §4.2 rules


def smallest_axis(quats: Tensor, log_scales: Tensor) -> tuple[Tensor, Tensor]:
    """Rotations R [M, 3, 3] (columns = local axes in world) and the index [M] of the smallest scale."""
    return quat_to_rotmat(quats), log_scales.argmin(-1)


def flat_normal(quats: Tensor, log_scales: Tensor, means: Tensor | None = None,
                camera_center: Tensor | None = None) -> Tensor:
    """Unit normal [M, 3] of flat Gaussians: n = R onehot(argmin s)  (IndoorGS §4.2).

    With ``means`` [M, 3] and ``camera_center`` [3], n is flipped so that its angle to the viewing
    direction (mean - camera centre) exceeds 90 degrees, i.e. n . (mean - C) <= 0 (faces the camera).
    """
    rot, idx = smallest_axis(quats, log_scales)
    n = rot.gather(2, idx[:, None, None].expand(-1, 3, 1)).squeeze(-1)  # column idx of R
    if camera_center is not None:
        if means is None:
            raise ValueError("flat_normal: flipping towards the camera needs the means")
        view = means - camera_center.to(means).reshape(1, 3)
        n = torch.where(((n * view).sum(-1, keepdim=True) > 0), -n, n)
    return n


def tangent_clone_means(means: Tensor, grads: Tensor, normals: Tensor,
                        step: Tensor | None = None) -> Tensor:
    """Positions [M, 3] of LINE clones: mu + grad - (n . grad) n  (IndoorGS §4.2, tangent clone).

    ``grads`` [M, 3] is the accumulated 3D mean gradient, ``normals`` [M, 3] unit flat normals.
    ``step`` None: the paper's formula verbatim with the raw gradient (displacements of order
    1e-6 m, i.e. a 3DGS in-place clone in practice). ``step`` [M] (metres): a displacement of that
    length along the same tangent direction, sign kept (mu + step * t / |t|); zero where the
    tangent gradient vanishes. Either way the displacement has no normal component.
    """
    # Normals from float32 rotations are unit only to ~1e-6; renormalising keeps the removed
    # normal component exact, and the second projection stops normalisation from amplifying
    # the rounding left in a tangent that is short next to the gradient.
    n = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    tangent = grads - (grads * n).sum(-1, keepdim=True) * n
    if step is None:
        return means + tangent
    length = tangent.norm(dim=-1, keepdim=True)
    direction = torch.where(length > 0, tangent / length.clamp_min(1e-30), torch.zeros_like(tangent))
    direction = direction - (direction * n).sum(-1, keepdim=True) * n
    return means + step[:, None].to(means) * direction


def _local_offsets(quats: Tensor, log_scales: Tensor, tangent: bool,
                   generator: torch.Generator | None) -> Tensor:
    rot, idx = smallest_axis(quats, log_scales)
    m = quats.shape[0]
    z = torch.randn((2, m, 3), generator=generator, device=quats.device, dtype=quats.dtype)
    if tangent:
        keep = torch.ones((m, 3), device=quats.device, dtype=quats.dtype)
        keep[torch.arange(m, device=quats.device), idx] = 0.0
        z = z * keep
    return torch.einsum("mij,bmj->bmi", rot, z * torch.exp(log_scales))  # [2, M, 3]


def tangent_split_offsets(quats: Tensor, log_scales: Tensor,
                          generator: torch.Generator | None = None) -> Tensor:
    """Offsets [2, M, 3] of LINE split children (IndoorGS §4.2, tangent split).

    A sample of N(0, diag(s^2)) in the Gaussian's local frame with the component along the smallest
    axis set to zero, rotated to world: the children stay in the Gaussian's tangent plane.
    """
    return _local_offsets(quats, log_scales, True, generator)


def free_split_offsets(quats: Tensor, log_scales: Tensor,
                       generator: torch.Generator | None = None) -> Tensor:
    """Offsets [2, M, 3] of SFM split children: R (s * z), z ~ N(0, I)  (3DGS split; IndoorGS §4.2 G_M)."""
    return _local_offsets(quats, log_scales, False, generator)


def near_any(points: Tensor, centres: Tensor, radii: Tensor, max_elems: int = 1 << 22) -> Tensor:
    """[A] bool: whether each point [A, 3] lies within radii[b] of some centre [B, 3].

    The neighbourhood test of "G_L takes precedence over G_M" (IndoorGS §4.2): chunked so that no
    more than ``max_elems`` distances are held at once.
    """
    out = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    if points.shape[0] == 0 or centres.shape[0] == 0:
        return out
    rows = max(1, max_elems // centres.shape[0])
    for i in range(0, points.shape[0], rows):
        d = torch.cdist(points[i:i + rows], centres)  # [rows, B]
        out[i:i + rows] = (d < radii[None]).any(-1)
    return out
