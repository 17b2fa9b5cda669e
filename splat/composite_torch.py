"""Reference compositing backend in plain torch (CPU or CUDA): the oracle for the other backends.

It follows the per-pixel rule of :mod:`splat.composite` in two passes:

1. **Selection** (no grad): Gaussians are binned into 4x4-pixel bins by their footprint (the radius
   box, tightened to where alpha can reach 1/255) and sorted by depth inside each bin; each pixel
   walks its bin's list in rounds of candidates, applying the exact skip / stop rule with its running
   transmittance, and records the first ``max_per_pixel`` Gaussians it blends. Saturated pixels and
   bins drop out early.
2. **Blending** (:class:`_BlendSelected`, a torch autograd Function): for each pixel the selected
   Gaussians are gathered and blended front to back with a cumulative product; the backward pass
   recomputes the alphas and applies the analytic gradient of front-to-back compositing (as 3DGS's
   backward.cu, with reverse cumulative sums). Pixels are sorted by their number of Gaussians and
   processed in chunks, so memory stays bounded (e.g. 640x480 with 200k Gaussians).

The cap ``max_per_pixel`` (default 256) is the only departure from the exact rule: a pixel that
would blend more Gaussians stops after that many. The selection table grows on demand, so the cap
costs nothing until pixels really blend that many; it bounds memory (pixels x cap) for
pathological inputs (thousands of faint Gaussians on one pixel). DESIGN.md's prototype used 64;
on splat.bench's room scene 64 still cut a few hundred pixels short, 128 was exact.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from splat.contracts import CompositeOut, check_composite_inputs

log = logging.getLogger(__name__)

BIN = 4  # selection bin size in pixels (BIN x BIN pixels share one depth-sorted list)
ALPHA_MIN = 1.0 / 255.0  # alphas below this are skipped (3DGS)
ALPHA_MAX = 0.99  # alphas are clamped to this (3DGS)
T_MIN = 1e-4  # a Gaussian that would drop T below this stops the pixel (3DGS)


def gaussian_alpha(dx: Tensor, dy: Tensor, conic_a: Tensor, conic_b: Tensor, conic_c: Tensor,
                   opacity: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(power, G, opacity * G) of a 2D Gaussian at offset (dx, dy) = mean - pixel centre.

    power = -1/2 (a dx^2 + c dy^2) - b dx dy;  G = exp(power)  (3DGS eq. 2 of the splatting
    paper; alpha = min(0.99, o G)). Shared by the selection and blending passes so that both take
    the same decisions bit for bit. exp is evaluated at min(power, 0) (power > 0 is skipped anyway).
    """
    power = -0.5 * (conic_a * dx * dx + conic_c * dy * dy) - conic_b * dx * dy
    gauss = torch.exp(torch.clamp(power, max=0.0))
    return power, gauss, opacity * gauss


def _bin_pixels(width: int, height: int, device: torch.device) -> Tensor:
    """[nbins, BIN*BIN] flat pixel index of each bin's pixels, H*W where the bin leaves the image."""
    nbx, nby = -(-width // BIN), -(-height // BIN)
    by, bx = torch.meshgrid(torch.arange(nby, device=device), torch.arange(nbx, device=device),
                            indexing="ij")
    ly, lx = torch.meshgrid(torch.arange(BIN, device=device), torch.arange(BIN, device=device),
                            indexing="ij")
    rows = by.reshape(-1, 1) * BIN + ly.reshape(1, -1)  # [nbins, BIN*BIN]
    cols = bx.reshape(-1, 1) * BIN + lx.reshape(1, -1)
    inside = (rows < height) & (cols < width)
    return torch.where(inside, rows * width + cols, torch.full_like(rows, width * height))


def _footprint_extent(conics: Tensor, opacities: Tensor, radii: Tensor) -> tuple[Tensor, Tensor]:
    """Half-extents (ex, ey) in pixels outside which no pixel can pass the rule: the radius box,
    tightened to the ellipse d^T Q d <= 2 ln(255 o) where o exp(power) >= 1/255 (0 if o < 1/255)."""
    q = conics.double()
    det = q[:, 0] * q[:, 2] - q[:, 1] * q[:, 1]
    tau = 2.0 * torch.log(torch.clamp(opacities.double() * 255.0, min=1e-300))
    r = radii.double()
    with torch.no_grad():
        ok = (det > 0) & torch.isfinite(det)
        safe_det = torch.where(ok, det, torch.ones_like(det))
        ex = torch.sqrt(torch.clamp(tau * q[:, 2] / safe_det, min=0.0))
        ey = torch.sqrt(torch.clamp(tau * q[:, 0] / safe_det, min=0.0))
        ex = torch.where(ok, torch.minimum(ex, r), r)  # non-PD conics: fall back to the radius box
        ey = torch.where(ok, torch.minimum(ey, r), r)
        live = (radii > 0) & (tau >= 0)
    return torch.where(live, ex, -1.0), torch.where(live, ey, -1.0)


def _bin_pairs(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, depths: Tensor,
               width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """(Gaussian index per pair sorted by (bin, depth), pair count per bin, first pair per bin)."""
    device = means2d.device
    nbx, nby = -(-width // BIN), -(-height // BIN)
    ex, ey = _footprint_extent(conics, opacities, radii)
    ids = torch.nonzero(ex >= 0).squeeze(1)
    ids = ids[torch.argsort(depths[ids], stable=True)]  # depth order, ties by index
    mx, my = means2d[ids, 0].double(), means2d[ids, 1].double()
    ex, ey = ex[ids], ey[ids]
    # Columns j with |j + 0.5 - mx| <= ex, widened by a pixel (the exact test runs per pixel);
    # clamp in float first so that far-away means cannot overflow int64.
    j0 = torch.floor(torch.clamp(mx - ex - 1.5, -1.0, width)).long().clamp(min=0)
    j1 = torch.floor(torch.clamp(mx + ex + 0.5, -1.0, width)).long().clamp(max=width - 1)
    i0 = torch.floor(torch.clamp(my - ey - 1.5, -1.0, height)).long().clamp(min=0)
    i1 = torch.floor(torch.clamp(my + ey + 0.5, -1.0, height)).long().clamp(max=height - 1)
    bx0, by0 = j0 // BIN, i0 // BIN
    ncx = (j1 // BIN - bx0 + 1).clamp(min=0)
    ncy = (i1 // BIN - by0 + 1).clamp(min=0)
    npairs = torch.where((j1 >= j0) & (i1 >= i0), ncx * ncy, torch.zeros_like(ncx))  # [n_live]
    gid = torch.repeat_interleave(torch.arange(ids.numel(), device=device), npairs)
    local = torch.arange(gid.numel(), device=device) - (torch.cumsum(npairs, 0) - npairs)[gid]
    ncx_g = ncx[gid]
    bin_id = (by0[gid] + torch.div(local, ncx_g, rounding_mode="floor")) * nbx + bx0[gid] + local % ncx_g
    bin_id, perm = torch.sort(bin_id, stable=True)  # stable: keeps depth order inside a bin
    counts = torch.bincount(bin_id, minlength=nbx * nby)
    return ids[gid[perm]], counts, torch.cumsum(counts, 0) - counts


@torch.no_grad()
def select_contributors(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N]
    radii: Tensor,  # [N]
    width: int,
    height: int,
    max_per_pixel: int = 256,
    candidates_per_round: int = 32,
    max_round_elems: int = 1 << 22,
) -> tuple[Tensor, Tensor, Tensor]:
    """Return (sel [R, K] int32, n_contrib [R] int32, pixel [R] int64) for R rows in bin-major order.

    Row r is pixel ``pixel[r]`` (flat index i * W + j; H * W for bin cells outside the image, which
    have no Gaussians); ``sel[r]`` lists the Gaussians it blends in order, -1 padded, and
    ``K = max(n_contrib)``. Applies the exact skip / stop rule of :mod:`splat.composite` with each
    pixel's running transmittance, stopping after ``max_per_pixel`` blended Gaussians. State is kept
    bin-major so that each round indexes whole bins.
    """
    device, dtype = means2d.device, means2d.dtype
    npix, kmax, cpr, bpix = width * height, int(max_per_pixel), int(candidates_per_round), BIN * BIN
    pair_g, counts, starts = _bin_pairs(means2d, conics, opacities, radii, depths, width, height)
    npairs = pair_g.numel()
    pair_g = torch.cat([pair_g, pair_g.new_zeros(1)]).to(torch.int32)  # pad slot: out-of-range
    # per-pair data, channel-first: mx, my, a, b, c, opacity, radius (pad: opacity 0 never passes)
    per_g = torch.cat([means2d, conics, opacities[:, None], radii[:, None].to(dtype)], 1).T
    packed = torch.cat([torch.index_select(per_g, 1, pair_g[:npairs]), per_g.new_zeros(7, 1)], 1)
    bin_pix = _bin_pixels(width, height, device)  # [nbins, 16], npix = outside the image
    nbins = bin_pix.shape[0]
    px_bin = (bin_pix % width).to(dtype) + 0.5  # [nbins, 16] pixel centres (junk where outside)
    py_bin = torch.div(bin_pix, width, rounding_mode="floor").to(dtype) + 0.5
    trans = torch.ones(nbins, bpix, dtype=dtype, device=device)
    count = torch.zeros(nbins, bpix, dtype=torch.int32, device=device)
    done = bin_pix >= npix  # [nbins, 16]
    # bin-major rows; columns grow on demand (doubling) up to kmax, so a large cap costs nothing
    # until pixels really blend that many Gaussians
    sel = torch.full((nbins * bpix, min(kmax, 2 * cpr)), -1, dtype=torch.int32, device=device)
    cand = torch.arange(cpr, device=device)
    active = (counts > 0) & ~done.all(1)
    group = max(1, max_round_elems // (bpix * cpr))
    rnd = 0
    while True:
        first = rnd * cpr
        bins = torch.nonzero(active & (counts > first)).squeeze(1)
        if bins.numel() == 0:
            break
        for b in torch.split(bins, group):
            nb = b.numel()
            pos = first + cand[None, :]  # [1, Cc]
            slot_idx = torch.where(pos < counts[b, None], starts[b, None] + pos, npairs).reshape(-1)
            data = torch.index_select(packed, 1, slot_idx).view(7, nb, 1, cpr)  # [7, nb, 1, Cc]
            dx = data[0] - px_bin[b][:, :, None]  # [nb, 16, Cc]
            dy = data[1] - py_bin[b][:, :, None]
            # gaussian_alpha's arithmetic, in place and in the same order (same bits)
            power = data[2] * dx
            power *= dx
            tmp = data[4] * dy
            tmp *= dy
            power += tmp
            power *= -0.5
            torch.mul(data[3], dx, out=tmp)
            tmp *= dy
            power -= tmp
            torch.maximum(dx.abs_(), dy.abs_(), out=tmp)
            passes = tmp <= data[6]  # inside the radius box
            passes &= power <= 0
            raw = power.clamp_(max=0.0).exp_()
            raw *= data[5]
            passes &= raw >= ALPHA_MIN  # min(0.99, raw) >= 1/255  <=>  raw >= 1/255
            done_b, count_b, t0 = done[b], count[b], trans[b]  # [nb, 16]
            passes &= ~done_b[:, :, None]
            one_minus = raw.clamp_(max=ALPHA_MAX).neg_().add_(1.0).masked_fill_(~passes, 1.0)
            full_t = torch.cumprod(torch.cat([t0[:, :, None], one_minus], 2), 2)  # [nb, 16, Cc + 1]
            rank = count_b[:, :, None] + torch.cumsum(passes, 2, dtype=torch.int32)  # 1-based index
            blocker = passes & ((full_t[:, :, 1:] < T_MIN) | (rank > kmax))
            has_block = blocker.any(2, keepdim=True)
            n_free = torch.where(has_block, blocker.to(torch.int8).argmax(2, keepdim=True), cpr)  # [nb,16,1]
            include = passes & (cand < n_free)
            trans[b] = full_t.gather(2, n_free).squeeze(2)  # T after the last included Gaussian
            # write the included Gaussians at their slots (rank - 1) of their pixels' rows
            ib, il, ic = torch.nonzero(include, as_tuple=True)
            row = b[ib] * bpix + il
            if ib.numel() > 0:
                need = int(rank[ib, il, ic].max())
                if need > sel.shape[1]:
                    grown = torch.full((sel.shape[0], min(kmax, max(need, 2 * sel.shape[1]))), -1,
                                       dtype=sel.dtype, device=device)
                    grown[:, : sel.shape[1]] = sel
                    sel = grown
            sel.view(-1)[row * sel.shape[1] + (rank[ib, il, ic] - 1)] = pair_g[slot_idx.view(nb, cpr)[ib, ic]]
            new_count = count_b + include.sum(2, dtype=torch.int32)
            count[b] = new_count
            done[b] = done_b | has_block.squeeze(2) | (new_count >= kmax)
        active &= ~done.all(1)
        rnd += 1
    n_contrib = count.reshape(-1)
    k = int(n_contrib.max()) if n_contrib.numel() > 0 else 0
    return sel[:, :k], n_contrib, bin_pix.reshape(-1)


def _gather_alpha(packed_t: Tensor, sel: Tensor, pix_xy: Tensor):
    """Recompute per (pixel, slot) quantities of the selected Gaussians (rows of one chunk).

    packed_t [6 + C, N] = (mx, my, a, b, c, opacity, features...) channel-first, sel [R, K]
    (-1 padded), pix_xy [R, 2]. Returns (idx [R*K], data [6 + C, R, K], dx, dy, G, alpha,
    unclamped) with alpha = 0 at pads.
    """
    rows, k = sel.shape
    valid = sel >= 0
    idx = sel.clamp(min=0).reshape(-1)
    data = torch.index_select(packed_t, 1, idx).view(-1, rows, k)  # [6 + C, R, K]
    # pads read Gaussian 0: zero them, or a non-finite value of Gaussian 0 reaches every padded pixel
    # (0 * NaN) and its gradient (the C++ backend never reads pads)
    data = torch.where(valid[None], data, data.new_zeros(()))
    dx = data[0] - pix_xy[:, 0:1]
    dy = data[1] - pix_xy[:, 1:2]
    _, gauss, raw = gaussian_alpha(dx, dy, data[2], data[3], data[4], data[5])
    unclamped = valid & (raw <= ALPHA_MAX)  # where d alpha / d raw = 1 (torch.clamp convention)
    alpha = torch.where(valid, torch.clamp(raw, max=ALPHA_MAX), torch.zeros_like(raw))
    return idx, data, dx, dy, gauss, alpha, unclamped


def _transmittance(alpha: Tensor) -> tuple[Tensor, Tensor]:
    """(T before each slot [R, K], T after the last [R]) for front-to-back alphas [R, K]."""
    t_incl = torch.cumprod(1.0 - alpha, 1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], 1)
    return t_excl, t_incl[:, -1]


class _BlendSelected(torch.autograd.Function):
    """sum_k f_k alpha_k T_k and T_final per pixel over its selected Gaussians (analytic backward).

    Inputs: packed_t [6 + C, N] (means2d, conics, opacities, features; channel-first), sel [P', K]
    sorted so that chunk rows share similar counts, pix_xy [P', 2], chunks: (start, stop, k) row
    ranges. Outputs: acc [P', C], t_final [P'], kmed [P'] (slot of the median Gaussian, -1 if none).
    """

    @staticmethod
    def forward(ctx, packed_t, sel, pix_xy, chunks):
        nch = packed_t.shape[0] - 6
        acc = packed_t.new_zeros(sel.shape[0], nch)
        t_final = packed_t.new_ones(sel.shape[0])
        kmed = torch.full((sel.shape[0],), -1, dtype=torch.long, device=sel.device)  # int64 for gather
        for start, stop, k in chunks:
            _, data, _, _, _, alpha, _ = _gather_alpha(packed_t, sel[start:stop, :k], pix_xy[start:stop])
            t_excl, t_last = _transmittance(alpha)
            acc[start:stop] = (data[6:] * (alpha * t_excl)[None]).sum(-1).T
            t_final[start:stop] = t_last
            cross = (alpha > 0) & (t_excl > 0.5) & (t_excl * (1.0 - alpha) <= 0.5)
            kmed[start:stop] = torch.where(cross.any(1), cross.to(torch.int8).argmax(1), -1)
        ctx.save_for_backward(packed_t, sel, pix_xy, t_final)
        ctx.chunks = chunks
        ctx.mark_non_differentiable(kmed)
        return acc, t_final, kmed

    @staticmethod
    def backward(ctx, g_acc, g_tfinal, _g_kmed):
        packed_t, sel, pix_xy, t_final = ctx.saved_tensors
        grad_t = torch.zeros_like(packed_t)
        if g_acc is None:
            g_acc = packed_t.new_zeros(sel.shape[0], packed_t.shape[0] - 6)
        if g_tfinal is None:
            g_tfinal = torch.zeros_like(t_final)
        for start, stop, k in ctx.chunks:
            idx, data, dx, dy, gauss, alpha, unclamped = _gather_alpha(
                packed_t, sel[start:stop, :k], pix_xy[start:stop])
            t_excl, _ = _transmittance(alpha)
            g_out = g_acc[start:stop].T.contiguous()[:, :, None]  # [C, R, 1]
            weights = alpha * t_excl  # [R, K]
            f_dot_g = (data[6:] * g_out).sum(0)  # [R, K]
            contrib = weights * f_dot_g
            # everything behind slot k (later Gaussians and the final T) carries a factor (1 - alpha_k)
            behind = contrib.sum(1, keepdim=True) - torch.cumsum(contrib, 1)
            behind = behind + (t_final[start:stop] * g_tfinal[start:stop])[:, None]
            d_raw = torch.where(unclamped, t_excl * f_dot_g - behind / (1.0 - alpha), torch.zeros_like(alpha))
            d_power = d_raw * data[5] * gauss
            g_pair = torch.empty_like(data)  # [6 + C, R, K]; zero at pads (alpha, d_raw are 0 there)
            g_pair[0] = -d_power * (data[2] * dx + data[3] * dy)
            g_pair[1] = -d_power * (data[3] * dx + data[4] * dy)
            g_pair[2] = -0.5 * d_power * dx * dx
            g_pair[3] = -d_power * dx * dy
            g_pair[4] = -0.5 * d_power * dy * dy
            g_pair[5] = d_raw * gauss
            g_pair[6:] = weights[None] * g_out
            grad_t.index_add_(1, idx, g_pair.view(g_pair.shape[0], -1))
        return grad_t, None, None, None


def _row_chunks(counts: Tensor, max_pairs: int, slack: float = 0.75) -> list[tuple[int, int, int]]:
    """Split rows sorted by descending count into (start, stop, k): k = the first row's count,
    rows * k <= max_pairs, and a chunk ends where counts drop below slack * k (bounded padding)."""
    counts_list = counts.tolist()
    chunks, start, n = [], 0, len(counts_list)
    while start < n:
        k = max(int(counts_list[start]), 1)
        limit = min(n, start + max(1, max_pairs // k))
        stop = start + 1
        while stop < limit and counts_list[stop] >= slack * k:
            stop += 1
        chunks.append((start, stop, k))
        start = stop
    return chunks


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
    max_per_pixel: int = 256,
    max_chunk_pairs: int = 1 << 20,
) -> CompositeOut:
    """Composite with the rule of :mod:`splat.composite` in torch; see the module docstring.

    ``max_chunk_pairs`` bounds pixels x Gaussians per blending chunk (the memory knob: a chunk
    holds about max_chunk_pairs * (C + 12) values).
    """
    check_composite_inputs(means2d, conics, opacities, features, depths, radii, width, height,
                           background, median_features)
    if max_per_pixel < 1:
        raise ValueError(f"max_per_pixel must be >= 1, got {max_per_pixel}")
    device, dtype = means2d.device, features.dtype
    npix, nch = width * height, features.shape[1]
    sel, counts, pixel = select_contributors(means2d, conics, opacities, depths, radii, width,
                                             height, max_per_pixel)
    # pixels with Gaussians, most-covered first, so that each chunk's K is tight
    order = torch.argsort(counts, descending=True, stable=True)[: int((counts > 0).sum())]
    sel, counts = sel[order].long(), counts[order]
    rows = pixel[order]  # flat pixel index of each row
    n_contrib = torch.zeros(npix, dtype=torch.int32, device=device).index_put((rows,), counts)
    pix_xy = torch.stack([(rows % width).to(dtype) + 0.5,
                          torch.div(rows, width, rounding_mode="floor").to(dtype) + 0.5], 1)
    packed_t = torch.cat([means2d.to(dtype), conics.to(dtype), opacities.to(dtype)[:, None], features],
                         1).T.contiguous()  # [6 + C, N]
    chunks = _row_chunks(counts, max_chunk_pairs)
    acc, t_rows, kmed = _BlendSelected.apply(packed_t, sel, pix_xy, chunks)
    blended = torch.zeros(npix, nch, dtype=dtype, device=device).index_put((rows,), acc)
    t_full = torch.ones(npix, dtype=dtype, device=device).index_put((rows,), t_rows)
    if background is not None:
        blended = blended + t_full[:, None] * background[None, :]
    median = None
    if median_features is not None:
        has = kmed >= 0
        gmed = torch.where(has, sel.gather(1, kmed.clamp(min=0)[:, None]).squeeze(1) if sel.shape[1] else kmed, 0)
        med_rows = median_features[gmed] * has[:, None].to(median_features.dtype)
        median = torch.zeros(npix, median_features.shape[1], dtype=median_features.dtype, device=device)
        median = median.index_put((rows,), med_rows).reshape(height, width, -1)
    return CompositeOut(
        features=blended.reshape(height, width, nch),
        alpha=(1.0 - t_full).reshape(height, width),
        median=median,
        n_contrib=n_contrib.reshape(height, width),
    )
