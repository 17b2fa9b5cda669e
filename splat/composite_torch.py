"""Reference compositing backend in plain torch (CPU or CUDA): the oracle for the other backends.

It follows the per-pixel rule of :mod:`splat.composite` in two passes:

1. **Selection** (no grad): Gaussians are binned into 4x4-pixel bins by their radius boxes and sorted
   by depth inside each bin; each pixel then walks its bin's list in chunks of candidates, applying
   the exact skip / stop rule with its running transmittance, and records the indices of the first
   ``max_per_pixel`` Gaussians it blends. Pixels (and bins) drop out as soon as they are saturated.
2. **Blending** (autograd): for each pixel, the selected Gaussians ``[P, K]`` are gathered, their
   alphas recomputed from the differentiable inputs, and the front-to-back sum evaluated with a
   cumulative product. Pixels are processed in chunks; when gradients are needed and there is more
   than one chunk, each chunk is checkpointed so memory stays bounded (e.g. 640x480, 200k Gaussians).

The cap ``max_per_pixel`` (default 64) is the only departure from the exact rule: a pixel that would
blend more Gaussians stops after that many (DESIGN.md: 32 was visibly wrong, 64 matched dense
compositing to 1e-4).
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from splat.composite import CompositeOut, check_composite_inputs

log = logging.getLogger(__name__)

BIN = 4  # selection bin size in pixels (BIN x BIN pixels share one depth-sorted list)
ALPHA_MIN = 1.0 / 255.0  # alphas below this are skipped (3DGS)
ALPHA_MAX = 0.99  # alphas are clamped to this (3DGS)
T_MIN = 1e-4  # a Gaussian that would drop T below this stops the pixel (3DGS)


def gaussian_alpha(dx: Tensor, dy: Tensor, conic_a: Tensor, conic_b: Tensor, conic_c: Tensor,
                   opacity: Tensor) -> tuple[Tensor, Tensor]:
    """Return (power, alpha) of a 2D Gaussian at offset (dx, dy) = mean - pixel centre.

    power = -1/2 (a dx^2 + c dy^2) - b dx dy;  alpha = min(0.99, o exp(power)) (3DGS, eq. 2 of the
    splatting paper). Shared by the selection and blending passes so that both take the same
    decisions bit for bit.
    """
    power = -0.5 * (conic_a * dx * dx + conic_c * dy * dy) - conic_b * dx * dy
    alpha = torch.clamp(opacity * torch.exp(torch.clamp(power, max=0.0)), max=ALPHA_MAX)
    return power, alpha


def _bin_pixels(width: int, height: int, device: torch.device) -> Tensor:
    """[nbins, BIN*BIN] flat pixel index of each bin's pixels, -1 where the bin leaves the image."""
    nbx, nby = -(-width // BIN), -(-height // BIN)
    by, bx = torch.meshgrid(torch.arange(nby, device=device), torch.arange(nbx, device=device),
                            indexing="ij")
    ly, lx = torch.meshgrid(torch.arange(BIN, device=device), torch.arange(BIN, device=device),
                            indexing="ij")
    rows = by.reshape(-1, 1) * BIN + ly.reshape(1, -1)  # [nbins, BIN*BIN]
    cols = bx.reshape(-1, 1) * BIN + lx.reshape(1, -1)
    pix = rows * width + cols
    return torch.where((rows < height) & (cols < width), pix, torch.full_like(pix, -1))


def _bin_pairs(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int
               ) -> tuple[Tensor, Tensor, Tensor]:
    """(Gaussian index per pair sorted by (bin, depth), pair count per bin, first pair per bin)."""
    device = means2d.device
    nbx, nby = -(-width // BIN), -(-height // BIN)
    ids = torch.nonzero(radii > 0).squeeze(1)
    ids = ids[torch.argsort(depths[ids], stable=True)]  # depth order, ties by index
    r = radii[ids].to(means2d.dtype)
    mx, my = means2d[ids, 0], means2d[ids, 1]
    # Touched columns j satisfy |j + 0.5 - mx| <= r; widen by one pixel (the exact box test runs
    # per pixel later) and clamp in float first so that far-away means do not overflow int64.
    j0 = torch.floor(torch.clamp(mx - r - 1.5, -1.0, width)).long().clamp(min=0)
    j1 = torch.floor(torch.clamp(mx + r + 0.5, -1.0, width)).long().clamp(max=width - 1)
    i0 = torch.floor(torch.clamp(my - r - 1.5, -1.0, height)).long().clamp(min=0)
    i1 = torch.floor(torch.clamp(my + r + 0.5, -1.0, height)).long().clamp(max=height - 1)
    bx0, bx1, by0, by1 = j0 // BIN, j1 // BIN, i0 // BIN, i1 // BIN
    ncx = (bx1 - bx0 + 1).clamp(min=0)
    ncy = (by1 - by0 + 1).clamp(min=0)
    ncx = torch.where((j1 >= j0) & (i1 >= i0), ncx, torch.zeros_like(ncx))
    npairs = ncx * ncy  # [n_valid]
    gid = torch.repeat_interleave(torch.arange(ids.numel(), device=device), npairs)
    first = torch.cumsum(npairs, 0) - npairs
    local = torch.arange(gid.numel(), device=device) - first[gid]
    bx = bx0[gid] + local % ncx[gid]
    by = by0[gid] + torch.div(local, ncx[gid], rounding_mode="floor")
    bin_id = by * nbx + bx
    bin_id, perm = torch.sort(bin_id, stable=True)  # stable: keeps depth order inside a bin
    pair_g = ids[gid[perm]]
    counts = torch.bincount(bin_id, minlength=nbx * nby)
    starts = torch.cumsum(counts, 0) - counts
    return pair_g, counts, starts


@torch.no_grad()
def select_contributors(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N]
    radii: Tensor,  # [N]
    width: int,
    height: int,
    max_per_pixel: int = 64,
    candidates_per_round: int = 32,
    max_round_elems: int = 1 << 22,
) -> tuple[Tensor, Tensor]:
    """Return (sel [H*W, K] Gaussian indices in blend order, -1 padded; n_contrib [H*W] int64).

    Applies the exact skip / stop rule of :mod:`splat.composite` with each pixel's running
    transmittance, stopping after ``max_per_pixel`` blended Gaussians. ``K = max(n_contrib)``.
    """
    device = means2d.device
    npix = width * height
    kmax = int(max_per_pixel)
    means2d, conics, opacities = means2d.detach(), conics.detach(), opacities.detach()
    pair_g, counts, starts = _bin_pairs(means2d, radii, depths, width, height)
    bin_pix = _bin_pixels(width, height, device)  # [nbins, BIN*BIN]
    trans = torch.ones(npix + 1, dtype=means2d.dtype, device=device)  # slot npix: outside pixels
    count = torch.zeros(npix + 1, dtype=torch.long, device=device)
    done = torch.zeros(npix + 1, dtype=torch.bool, device=device)
    done[npix] = True
    sel = torch.full((npix + 1, kmax), -1, dtype=torch.long, device=device)
    bin_pix = torch.where(bin_pix >= 0, bin_pix, torch.full_like(bin_pix, npix))
    cand = torch.arange(candidates_per_round, device=device)
    px_all = (torch.arange(npix + 1, device=device) % width).to(means2d.dtype) + 0.5
    py_all = torch.div(torch.arange(npix + 1, device=device), width, rounding_mode="floor"
                       ).to(means2d.dtype) + 0.5
    active = counts > 0
    group = max(1, max_round_elems // (BIN * BIN * candidates_per_round))
    rnd = 0
    while True:
        first = rnd * candidates_per_round
        bins = torch.nonzero(active & (counts > first)).squeeze(1)
        if bins.numel() == 0:
            break
        for b in torch.split(bins, group):
            pos = first + cand  # [Cc]
            ok = pos[None, :] < counts[b, None]  # [nb, Cc]
            g = pair_g[(starts[b, None] + pos[None, :]).clamp(max=max(pair_g.numel() - 1, 0))]
            pix = bin_pix[b]  # [nb, 16]
            dx = means2d[g, 0][:, None, :] - px_all[pix][:, :, None]  # [nb, 16, Cc]
            dy = means2d[g, 1][:, None, :] - py_all[pix][:, :, None]
            rad = radii[g].to(means2d.dtype)[:, None, :]
            power, alpha = gaussian_alpha(dx, dy, conics[g, 0][:, None, :], conics[g, 1][:, None, :],
                                          conics[g, 2][:, None, :], opacities[g][:, None, :])
            passes = (ok[:, None, :] & ~done[pix][:, :, None] & (dx.abs() <= rad) & (dy.abs() <= rad)
                      & (power <= 0) & (alpha >= ALPHA_MIN))
            pix, passes, alpha = pix.reshape(-1), passes.reshape(pix.numel(), -1), alpha.reshape(pix.numel(), -1)
            gg = g[:, None, :].expand(-1, BIN * BIN, -1).reshape(pix.numel(), -1)  # [R, Cc]
            t0 = trans[pix]
            a = torch.where(passes, alpha, torch.zeros_like(alpha))
            test_t = torch.cumprod(torch.cat([t0[:, None], 1.0 - a], 1), 1)[:, 1:]  # sequential T
            rank = count[pix][:, None] + torch.cumsum(passes.long(), 1)  # 1-based blend index
            blocker = passes & ((test_t < T_MIN) | (rank > kmax))
            blocked = torch.cumsum(blocker.long(), 1) > 0
            include = passes & ~blocked
            a_inc = torch.where(include, alpha, torch.zeros_like(alpha))
            trans[pix] = torch.cumprod(torch.cat([t0[:, None], 1.0 - a_inc], 1), 1)[:, -1]
            slot = count[pix][:, None] + torch.cumsum(include.long(), 1) - 1
            rows, cols = torch.nonzero(include, as_tuple=True)
            sel[pix[rows], slot[rows, cols]] = gg[rows, cols]
            n_new = count[pix] + include.sum(1)
            count[pix] = n_new
            done[pix] = done[pix] | blocked.any(1) | (n_new >= kmax)
            done[npix] = True
            trans[npix], count[npix] = 1.0, 0
        active = active & ~done[bin_pix].all(1)
        rnd += 1
    n_contrib = count[:npix]
    k = int(n_contrib.max()) if npix > 0 else 0
    return sel[:npix, :k].contiguous(), n_contrib


def _blend_rows(sel: Tensor, pix_xy: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor,
                features: Tensor, median_features: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
    """Blend selected Gaussians for a block of pixels: (sum_k f alpha T [R, C], T_final [R], median).

    sel [R, K] (-1 padded, blend order), pix_xy [R, 2] pixel centres. Differentiable.
    """
    valid = sel >= 0
    g = sel.clamp(min=0)
    dx = means2d[g, 0] - pix_xy[:, 0:1]  # [R, K]
    dy = means2d[g, 1] - pix_xy[:, 1:2]
    _, alpha = gaussian_alpha(dx, dy, conics[g, 0], conics[g, 1], conics[g, 2], opacities[g])
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1.0 - alpha, 1)  # [R, K] T after each Gaussian
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], 1)  # T before it
    weights = alpha * t_excl  # [R, K]
    out = torch.einsum("rk,rkc->rc", weights, features[g])  # [R, C]
    t_final = t_incl[:, -1] if sel.shape[1] > 0 else torch.ones_like(pix_xy[:, 0])
    median = None
    if median_features is not None:
        with torch.no_grad():
            cross = valid & (t_excl > 0.5) & (t_incl <= 0.5)
            has = cross.any(1)
            kmed = torch.argmax(cross.to(torch.int8), 1)
            gmed = torch.where(has, g.gather(1, kmed[:, None]).squeeze(1), torch.zeros_like(kmed))
        median = median_features[gmed] * has[:, None].to(median_features.dtype)
    return out, t_final, median


def composite_torch(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    depths: Tensor,  # [N]
    radii: Tensor,  # [N]
    width: int,
    height: int,
    *,
    background: Tensor | None = None,  # [C]
    median_features: Tensor | None = None,  # [N, M]
    max_per_pixel: int = 64,
    max_chunk_elems: int = 1 << 21,
) -> CompositeOut:
    """Composite with the rule of :mod:`splat.composite` in torch; see the module docstring.

    ``max_chunk_elems`` bounds pixels x K x channels per blending chunk (memory knob).
    """
    check_composite_inputs(means2d, conics, opacities, features, depths, radii, width, height,
                           background, median_features)
    if max_per_pixel < 1:
        raise ValueError(f"max_per_pixel must be >= 1, got {max_per_pixel}")
    device, dtype = means2d.device, means2d.dtype
    npix, nch = width * height, features.shape[1]
    sel, n_contrib = select_contributors(means2d, conics, opacities, depths, radii, width, height,
                                         max_per_pixel)
    rows = torch.nonzero(n_contrib > 0).squeeze(1)  # pixels with at least one Gaussian
    pix_xy = torch.stack([(rows % width).to(dtype) + 0.5,
                          torch.div(rows, width, rounding_mode="floor").to(dtype) + 0.5], 1)
    sel = sel[rows]
    k = max(sel.shape[1], 1)
    nmed = 0 if median_features is None else median_features.shape[1]
    chunk = max(1, max_chunk_elems // (k * (nch + nmed + 8)))
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad
        for t in (means2d, conics, opacities, features, median_features))
    outs, trans, meds = [], [], []
    for start in range(0, rows.numel(), chunk):
        args = (sel[start:start + chunk], pix_xy[start:start + chunk], means2d, conics, opacities,
                features, median_features)
        if needs_grad and rows.numel() > chunk:
            o, t, m = checkpoint(_blend_rows, *args, use_reentrant=False)
        else:
            o, t, m = _blend_rows(*args)
        outs.append(o)
        trans.append(t)
        meds.append(m)
    blended = torch.zeros(npix, nch, dtype=features.dtype, device=device)
    t_full = torch.ones(npix, dtype=dtype, device=device)
    if rows.numel() > 0:
        blended = blended.index_put((rows,), torch.cat(outs))
        t_full = t_full.index_put((rows,), torch.cat(trans))
    if background is not None:
        blended = blended + t_full[:, None] * background[None, :]
    median = None
    if median_features is not None:
        median = torch.zeros(npix, nmed, dtype=median_features.dtype, device=device)
        if rows.numel() > 0:
            median = median.index_put((rows,), torch.cat(meds))
        median = median.reshape(height, width, nmed)
    return CompositeOut(
        features=blended.reshape(height, width, nch),
        alpha=(1.0 - t_full).reshape(height, width),
        median=median,
        n_contrib=n_contrib.to(torch.int32).reshape(height, width),
    )
