"""Training losses of IndoorGS (§4.3): L = L_rgb + λ_d L_d + λ_n L_n + λ_s L_s + λ_nc L_nc.

One function per term, named in its docstring; ``total_loss`` combines them for the trainer, with
this project's extensions L_a (here) and L_mv (splat/multiview.py) when their weights are > 0.
Inputs follow the renderer (splat/rasterize.py ``render``): rgb [H, W, 3] in [0, 1], depth [H, W]
z-depth in metres (0 = not covered), normal [H, W, 3] unit camera-frame normals facing the camera
(OpenCV axes, zeros = undefined), alpha [H, W]. Priors: depth [H, W] metres (0 = invalid), normals
[H, W, 3] unit camera frame (zeros = invalid); NaN / Inf prior pixels are invalid too (scene loading
already sets them to 0; tests/test_fuzz_losses.py). Intrinsics K [3, 3] use COLMAP pixel centres.

Every masked mean divides by max(count, 1), so an empty mask gives a 0 that is still connected to
the graph (zero gradients, never NaN).
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

from evaluation.image_metrics import ssim_map
from splat import compiled, losses_cuda
from splat.multiview import SourceView, multiview_ncc_loss, to_gray
from splat.loss_config import PRIOR_TERMS, LossConfig, without_priors  # noqa: F401 (the config re-exported)
from splat.losses_cpu import fused_applies, nc_loss, normal_prior_loss_fused, ssim_mean

log = logging.getLogger(__name__)

_NORM2_EPS = 1e-20  # squared length below which a (cross-product) normal counts as undefined


def _check_shape(name: str, x: Tensor, shape: tuple) -> None:
    """Raise ValueError unless ``x`` has ``shape`` (entries None match any size)."""
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    ok = x.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, x.shape))
    if not ok:
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(x.shape)}")


def _masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Mean of ``values`` where ``mask``; 0 (graph-connected) when the mask is empty."""
    picked = torch.where(mask, values, torch.zeros_like(values))
    return picked.sum() / mask.sum().clamp(min=1).to(values.dtype)


def rgb_loss(pred: Tensor, gt: Tensor, lambda_dssim: float = 0.2, fused_ssim: bool = True) -> Tensor:
    """L_rgb (IndoorGS §4.3, 3DGS Eq. 7): (1 − λ) L1 + λ (1 − SSIM).

    pred, gt: [H, W, 3] colours in [0, 1]. L1 is the mean over pixels and channels; SSIM is the
    3DGS one (11 × 11 Gaussian window, σ = 1.5, zero padding) of ``evaluation.image_metrics``, on
    the CPU by the fused C++ kernel of splat/losses_cpu.py, on a GPU by the CUDA kernels of
    splat/losses_cuda.py (this torch code compiled by splat/compiled.py where they did not build),
    unless ``fused_ssim`` is False. Returns a 0-dim tensor.
    """
    _check_shape("pred", pred, (None, None, 3))
    _check_shape("gt", gt, tuple(pred.shape))
    if fused_ssim and not gt.requires_grad and losses_cuda.applies(pred, gt):
        return losses_cuda.rgb_loss(pred, gt, lambda_dssim)
    if fused_ssim and not gt.requires_grad and compiled.applies(pred, gt):
        return compiled.call(_rgb_loss_torch, pred, gt.to(pred.dtype), float(lambda_dssim))
    l1 = (pred - gt).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim_mean(pred, gt.to(pred.dtype), fused_ssim))


def _rgb_loss_torch(pred: Tensor, gt: Tensor, lambda_dssim: float) -> Tensor:
    """``rgb_loss`` in torch alone (the graph splat/compiled.py compiles on a GPU)."""
    l1 = (pred - gt).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim_map(pred, gt).mean())


def sample_patch_grid(height: int, width: int, patch_size: int, n_patches: int,
                      generator: torch.Generator | None = None, device: torch.device | str = "cpu"
                      ) -> tuple[Tensor, int, int]:
    """Top-left corners of ``n_patches`` distinct cells of a grid of patch_size² cells.

    The grid origin is shifted by a random offset in [0, H mod S] × [0, W mod S] (the same for all
    cells, so cells never overlap); then min(n_patches, number of cells) cells are drawn without
    replacement. An image side shorter than S gives patches of that side's length (an image
    smaller than one patch is one patch: the whole image). ``generator`` is a CPU generator.
    Returns (corners [M, 2] int64 (row, col), patch height, patch width).
    """
    if patch_size < 1 or n_patches < 1:
        raise ValueError(f"patch_size and n_patches must be >= 1, got {patch_size}, {n_patches}")
    ph, pw = min(patch_size, height), min(patch_size, width)
    rows, cols = height // ph, width // pw
    off = torch.randint(0, 10**9, (2,), generator=generator)
    oy, ox = int(off[0]) % (height - rows * ph + 1), int(off[1]) % (width - cols * pw + 1)
    cells = torch.randperm(rows * cols, generator=generator)[:n_patches]
    corners = torch.stack([oy + (cells // cols) * ph, ox + (cells % cols) * pw], -1)
    return corners.to(device), ph, pw


def _gather_patches(img: Tensor, corners: Tensor, ph: int, pw: int) -> Tensor:
    """[M, ph, pw] patches of ``img`` [H, W] at ``corners`` [M, 2]."""
    r = corners[:, :1] + torch.arange(ph, device=img.device)  # [M, ph]
    c = corners[:, 1:] + torch.arange(pw, device=img.device)  # [M, pw]
    return img[r[:, :, None], c[:, None, :]]


def depth_pcc_loss(depth: Tensor, prior: Tensor, valid: Tensor, patch_size: int, n_patches: int,
                   generator: torch.Generator | None = None, rel_std_eps: float = 1e-5) -> Tensor:
    """L_d (IndoorGS §4.3): (1/N) Σ_i (1 − PCC(P̂_i, P_mono,i)) over random non-overlapping patches.

    depth: [H, W] rendered z-depth (m); prior: [H, W] monocular depth (any positive scale/shift, up to
    float range: each patch's prior is rescaled by a power of two before the sums);
    valid: [H, W] bool, pixels to use (the caller's prior > 0 and alpha test). Patches are S × S
    cells of a grid (``sample_patch_grid``); the PCC uses only the valid pixels of a patch.
    A patch is skipped when fewer than half of its pixels are valid or when either side's std is
    below ``rel_std_eps`` × its mean |value| (flat, PCC undefined); the mean runs over the kept
    patches. Skipped patches go through ``torch.where`` with safe denominators, so values and
    gradients stay finite; with no kept patch the result is a graph-connected 0.
    The loss is in [0, 2]: 0 for prior = a·depth + b with a > 0, 2 for a < 0.
    """
    _check_shape("depth", depth, (None, None))
    _check_shape("prior", prior, tuple(depth.shape))
    _check_shape("valid", valid, tuple(depth.shape))
    h, w = depth.shape
    corners, ph, pw = sample_patch_grid(h, w, patch_size, n_patches, generator, depth.device)
    mb = _gather_patches(valid, corners, ph, pw).flatten(1)  # [M, P] bool
    m = mb.to(depth.dtype)
    # invalid pixels are selected out, not multiplied by 0: a NaN / Inf there (a prior's invalid
    # pixel) would leak into the sums as NaN (fuzz finding, tests/test_fuzz_losses.py)
    x = torch.where(mb, _gather_patches(depth, corners, ph, pw).flatten(1), 0.0)
    y = torch.where(mb, _gather_patches(prior.to(depth.dtype), corners, ph, pw).flatten(1), 0.0)
    # the PCC does not change when y is scaled: each patch's prior is brought to [1, 2) in magnitude by a
    # power of two (exact: the same bits of the PCC), so that a prior of any scale (1e18, 1e-30) neither
    # overflows nor underflows vy in float32 (an exact prior x 1e18 gave L_d 1, x 1e20 a NaN gradient)
    y = torch.ldexp(y, 1 - torch.frexp(y.abs().amax(1, keepdim=True)).exponent)  # exact on any device
    n = m.sum(1)  # [M]
    n_safe = n.clamp(min=1)
    mx, my = (x * m).sum(1) / n_safe, (y * m).sum(1) / n_safe
    dx, dy = (x - mx[:, None]) * m, (y - my[:, None]) * m
    vx, vy, cov = (dx * dx).sum(1), (dy * dy).sum(1), (dx * dy).sum(1)
    # std > eps |mean|  <=>  var / n > eps² mean²  (tiny absolute floor for all-zero patches)
    flat_x = vx <= n_safe * (rel_std_eps * mx) ** 2 + 1e-30
    flat_y = vy <= n_safe * (rel_std_eps * my) ** 2 + 1e-30
    keep = (n >= 0.5 * ph * pw) & ~flat_x & ~flat_y  # [M] bool
    denom = torch.sqrt(torch.where(keep, vx * vy, torch.ones_like(vx)))  # sqrt'(0) never reached
    pcc = cov / denom
    loss = _masked_mean(1.0 - pcc, keep)
    if log.isEnabledFor(logging.DEBUG):  # int() waits for a GPU: only when it is printed
        log.debug("depth PCC: %d of %d patches kept", int(keep.sum()), keep.numel())
    return loss


def normal_prior_loss(normal: Tensor, prior: Tensor, valid: Tensor, fused: bool = True) -> Tensor:
    """L_n (IndoorGS §4.3): mean |N̂ − N_mono|₁ over the valid pixels.

    normal, prior: [H, W, 3] unit camera-frame normals; valid: [H, W] bool. The L1 norm is summed
    over the 3 components and averaged over pixels (range [0, 2√3]); pixels where either normal is
    all zero (undefined) are dropped as well. Empty mask: graph-connected 0. On the CPU the fused
    kernel of splat/losses_cpu.py computes it, on a GPU splat/losses_cuda.py's (or, where they did not
    build, this code compiled by splat/compiled.py); this
    code is their oracle (``fused=False``); a prior that needs a gradient takes it.
    """
    _check_shape("normal", normal, (None, None, 3))
    _check_shape("prior", prior, tuple(normal.shape))
    _check_shape("valid", valid, tuple(normal.shape[:2]))
    fusable = fused and valid.dtype == torch.bool and not prior.requires_grad and prior.dtype == normal.dtype
    if fusable and fused_applies(normal, prior):
        return normal_prior_loss_fused(normal, prior, valid)
    if fusable and losses_cuda.applies(normal, prior, valid):
        return losses_cuda.normal_prior_loss(normal, prior, valid)
    if fusable and compiled.applies(normal, prior, valid):
        return compiled.call(_normal_prior_torch, normal, prior, valid)
    return _normal_prior_torch(normal, prior, valid)


def _normal_prior_torch(normal: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
    """``normal_prior_loss`` in torch alone (its oracle, and the graph compiled on a GPU)."""
    # an Inf prior pixel passes the "not all zero" test: non-finite pixels are invalid (fuzz finding)
    mask = valid & (normal.detach().abs().sum(-1) > 0) & (prior.abs().sum(-1) > 0) & torch.isfinite(prior).all(-1)
    return _masked_mean((normal - prior.to(normal.dtype)).abs().sum(-1), mask)


def flatten_loss(log_scales: Tensor, mask: Tensor) -> Tensor:
    """L_s (IndoorGS §4.3): mean over the masked Gaussians (G_L) of their smallest scale (m).

    log_scales: [N, 3] log-scales (log metres); mask: [N] bool. Returns mean_i exp(min_k s_ik)
    over masked i, a graph-connected 0 when the mask is empty. On a GPU the same mean is taken over
    all N with the unmasked ones zeroed (no boolean indexing, whose count would wait for the GPU;
    the sum's rounding order differs, so the CPU keeps the indexed form its results were made with).
    """
    _check_shape("log_scales", log_scales, (None, 3))
    _check_shape("mask", mask, (log_scales.shape[0],))
    if log_scales.is_cuda:
        return _flatten_masked(log_scales, mask)
    smallest = log_scales[mask].min(dim=1).values.exp()  # [M] metres
    return smallest.sum() / max(int(smallest.numel()), 1)


def _flatten_masked(log_scales: Tensor, mask: Tensor) -> Tensor:
    """``flatten_loss`` without boolean indexing (its GPU form)."""
    # exp only of the masked rows (an unmasked huge log-scale would give 0 * inf = NaN backward)
    smallest = torch.where(mask, log_scales.min(dim=1).values, 0.0).exp()
    return torch.where(mask, smallest, 0.0).sum() / mask.sum().clamp(min=1).to(log_scales.dtype)


def depth_to_normal(depth: Tensor, K: Tensor) -> Tensor:
    """N_depth of L_nc (IndoorGS §4.3): camera-frame normals [H, W, 3] from a z-depth map.

    depth: [H, W] z-depth (m, 0 = none); K: [3, 3] intrinsics, COLMAP pixel centres (pixel (i, j) at
    (j + 0.5, i + 0.5)). Pixel centres are back-projected, X = d ((u − cx)/fx, (v − cy)/fy, 1); the
    normal is the normalised cross product of the central differences X[i, j+1] − X[i, j−1] and
    X[i+1, j] − X[i−1, j], flipped to face the camera (n · X < 0). Exact for a plane. Zero at the
    border pixels, where any of the 5 depths used is 0, and where the cross product vanishes.
    """
    _check_shape("depth", depth, (None, None))
    _check_shape("K", K, (3, 3))
    h, w = depth.shape
    out = torch.zeros(h, w, 3, dtype=depth.dtype, device=depth.device)
    if h < 3 or w < 3:
        return out + 0.0 * depth[..., None]
    K = K.to(depth)
    v = torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5  # COLMAP pixel centres
    u = torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5
    x = ((u[None, :] - K[0, 2]) / K[0, 0]) * depth
    y = ((v[:, None] - K[1, 2]) / K[1, 1]) * depth
    pts = torch.stack([x, y, depth], -1)  # [H, W, 3] camera-frame points (m)
    dx = pts[1:-1, 2:] - pts[1:-1, :-2]  # [H-2, W-2, 3]
    dy = pts[2:, 1:-1] - pts[:-2, 1:-1]
    n = torch.linalg.cross(dx, dy, dim=-1)
    centre = pts[1:-1, 1:-1]
    n = torch.where((n * centre).sum(-1, keepdim=True) > 0, -n, n)
    norm2 = (n * n).sum(-1, keepdim=True)
    d = depth
    has = (d[1:-1, 2:] > 0) & (d[1:-1, :-2] > 0) & (d[2:, 1:-1] > 0) & (d[:-2, 1:-1] > 0) & (d[1:-1, 1:-1] > 0)
    has = has[..., None] & (norm2 > _NORM2_EPS)
    inner = torch.where(has, n * torch.rsqrt(torch.clamp(norm2, min=_NORM2_EPS)), torch.zeros_like(n))
    return torch.nn.functional.pad(inner.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)


def depth_normal_consistency_loss(normal: Tensor, depth: Tensor, K: Tensor, valid: Tensor,
                                  detach_depth_normal: bool = False, fused: bool = True) -> Tensor:
    """L_nc (IndoorGS §4.3): mean over pixels of (1 − N̂ · N_depth), N_depth = ``depth_to_normal``.

    normal: [H, W, 3] rendered normals; depth: [H, W] rendered z-depth (m; the trainer passes the
    alpha-normalised expected depth ``out["depth"]``); K: [3, 3]; valid: [H, W] bool. Pixels count
    where valid and both normals are defined. The paper writes a sum; the mean keeps λ_nc = 0.1
    independent of the image size (as in PGSR / RaDe-GS). By default the gradient flows into both
    the normals and the depth (2DGS / RaDe-GS / PGSR); ``detach_depth_normal`` stops it at N_depth.
    On the CPU the fused C++ kernel of splat/losses_cpu.py computes it, on a GPU the CUDA kernels of
    splat/losses_cuda.py (or, where they did not build, this code compiled by splat/compiled.py); this
    code is their oracle (``fused=False``).
    """
    _check_shape("normal", normal, (None, None, 3))
    _check_shape("depth", depth, tuple(normal.shape[:2]))
    _check_shape("valid", valid, tuple(normal.shape[:2]))
    fusable = fused and valid.dtype == torch.bool and normal.dtype == depth.dtype
    if fusable and fused_applies(normal, depth):
        return nc_loss(normal, depth, K, valid, detach_depth_normal)
    if fusable and losses_cuda.applies(normal, depth, valid):
        return losses_cuda.nc_loss(normal, depth, K, valid, detach_depth_normal)
    if fusable and compiled.applies(normal, depth, valid):
        return compiled.call(_nc_torch, normal, depth, K.to(depth), valid, bool(detach_depth_normal))
    return _nc_torch(normal, depth, K, valid, detach_depth_normal)


def _nc_torch(normal: Tensor, depth: Tensor, K: Tensor, valid: Tensor, detach_depth_normal: bool) -> Tensor:
    """``depth_normal_consistency_loss`` in torch alone (its oracle, and the graph compiled on a GPU)."""
    n_depth = depth_to_normal(depth, K)
    if detach_depth_normal:
        n_depth = n_depth.detach()
    mask = valid & (n_depth.detach().abs().sum(-1) > 0) & (normal.detach().abs().sum(-1) > 0)
    return _masked_mean(1.0 - (normal * n_depth).sum(-1), mask)


def anchored_depth_loss(depth: Tensor, anchor: Tensor, valid: Tensor, tolerance: float | Tensor) -> Tensor:
    """L_a (an extension, not in the paper): mean over ``valid`` pixels of max(0, |depth − anchor| − τ).

    depth: [H, W] rendered z-depth (m); anchor: [H, W] the depth prior aligned to the cues by
    ``geocues extract`` (metric; 0 = invalid); τ (m): the tolerance (``total_loss`` sets it from the
    alignment's residual: max(anchor_tol_min, anchor_tol_p90 × p90)), or an [H, W] map of them. L_d (patch PCC) is blind to a surface that moved along the view direction — a wall
    rebuilt 10 cm in front of itself has the same depth pattern — and in regions without cues
    nothing else holds it; L_a pulls back only depths farther than τ from the anchor, so it does not
    fight the finer geometry the other terms recover inside τ. Returns a 0-dim tensor (metres).
    """
    _check_shape("depth", depth, (None, None))
    _check_shape("anchor", anchor, tuple(depth.shape))
    _check_shape("valid", valid, tuple(depth.shape))
    if isinstance(tolerance, Tensor):
        _check_shape("tolerance", tolerance, tuple(depth.shape))
        if not bool((tolerance >= 0).all()):
            raise ValueError("tolerance must be >= 0 everywhere")
        tolerance = tolerance.to(depth.dtype)
    elif not tolerance >= 0.0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    excess = torch.relu((depth - anchor.to(depth.dtype)).abs() - tolerance)
    return _masked_mean(excess, valid & (anchor > 0) & torch.isfinite(anchor))  # Inf > 0: invalid too


def total_loss(out: dict[str, Tensor], gt_rgb: Tensor, camera_K: Tensor, params: dict[str, Tensor],
               cue_type: Tensor, cfg: LossConfig, step: int, depth_prior: Tensor | None = None,
               normal_prior: Tensor | None = None, generator: torch.Generator | None = None,
               depth_anchor: Tensor | None = None, anchor_p90: float = float("nan"),
               source: SourceView | None = None, anchor_tight: Tensor | None = None
               ) -> tuple[Tensor, dict[str, float]]:
    """L = L_rgb + λ_d L_d + λ_n L_n + λ_s L_s + λ_nc L_nc (IndoorGS §4.3) for one view, plus this
    project's λ_a L_a and λ_mv L_mv when their weights are > 0.

    out: ``render`` output (rgb, depth, normal, alpha); gt_rgb: [H, W, 3]; camera_K: [3, 3];
    params["scales"]: [N, 3] log-scales; cue_type: [N] int (SFM=0, LINE=1, PLANE=2); step: the
    iteration; depth_prior [H, W] m (0 = invalid), normal_prior [H, W, 3] (0 = invalid);
    depth_anchor [H, W] m and anchor_p90 (m): the cue-aligned prior and its residual for L_a
    (used when cfg.lambda_anchor > 0; a NaN anchor_p90 leaves τ = cfg.anchor_tol_min); anchor_tight
    [H, W] bool: the anchor pixels held at τ = cfg.anchor_tol_min (the plane cues'); source: a
    neighbouring training view for L_mv (used when cfg.lambda_mv > 0 and step >= mv_from_iter).
    A term is skipped when its switch is off, its prior is None, or (L_nc) step < nc_from_iter.
    L_s flattens the Gaussians whose type is in ``cfg.flat_types`` (LINE only by default, as the
    paper's G_L; PLANE Gaussians are not flattened unless 2 is added).
    Returns (total, {"rgb", "depth", "anchor", "normal", "flat", "nc", "mv" (the computed ones), "total"})
    with the unweighted term values as floats (and "mv_kept", the share of L_mv samples used).
    """
    for key in ("rgb", "depth", "normal", "alpha"):
        if key not in out:
            raise ValueError(f"out: missing key {key!r} (expected a splat.rasterize.render output)")
    h, w = out["depth"].shape
    _check_shape("cue_type", cue_type, (params["scales"].shape[0],))
    covered = out["alpha"] > cfg.min_alpha_valid
    terms: dict[str, tuple[float, Tensor]] = {"rgb": (1.0, rgb_loss(out["rgb"], gt_rgb, cfg.lambda_dssim,
                                                                          cfg.kernels == "fused"))}
    if cfg.use_depth and depth_prior is not None:
        _check_shape("depth_prior", depth_prior, (h, w))
        valid = covered & (depth_prior > 0) & torch.isfinite(depth_prior) & (out["depth"] > 0)
        terms["depth"] = (cfg.lambda_depth, depth_pcc_loss(out["depth"], depth_prior, valid, cfg.patch_size,
                                                           cfg.n_patches, generator))
    if cfg.lambda_anchor > 0 and depth_anchor is not None:
        _check_shape("depth_anchor", depth_anchor, (h, w))
        tol = cfg.anchor_tol_min if math.isnan(anchor_p90) else max(cfg.anchor_tol_min, cfg.anchor_tol_p90 * anchor_p90)
        if anchor_tight is not None and tol > cfg.anchor_tol_min:
            _check_shape("anchor_tight", anchor_tight, (h, w))
            tol = torch.where(anchor_tight, cfg.anchor_tol_min, tol).to(out["depth"].dtype)
        terms["anchor"] = (cfg.lambda_anchor, anchored_depth_loss(out["depth"], depth_anchor,
                                                                  covered & (out["depth"] > 0), tol))
    if cfg.use_normal and normal_prior is not None:
        terms["normal"] = (cfg.lambda_normal, normal_prior_loss(out["normal"], normal_prior, covered,
                                                                cfg.kernels == "fused"))
    if cfg.use_flat:
        mask = torch.zeros_like(cue_type, dtype=torch.bool)  # (no host-to-device copy of the list)
        for t in cfg.flat_types:
            mask |= cue_type == t
        terms["flat"] = (cfg.lambda_flat, flatten_loss(params["scales"], mask))
    if cfg.use_nc and step >= cfg.nc_from_iter:
        terms["nc"] = (cfg.lambda_nc, depth_normal_consistency_loss(out["normal"], out["depth"], camera_K, covered,
                                                                    cfg.nc_detach_depth, cfg.kernels == "fused"))
    extra = {}
    if cfg.lambda_mv > 0 and source is not None and step >= cfg.mv_from_iter:
        mv, stats = multiview_ncc_loss(out["depth"], out["normal"], to_gray(gt_rgb), camera_K, source,
                                       cfg.mv_samples, cfg.mv_patch, cfg.mv_min_std, cfg.mv_min_ncc, generator)
        terms["mv"], extra["mv_kept"] = (cfg.lambda_mv, mv), stats["kept"]
    total = sum(wt * t for wt, t in terms.values())
    values = torch.stack([t.detach() for _, t in terms.values()] + [total.detach()]).tolist()  # one sync
    return total, dict(zip(list(terms) + ["total"], values)) | extra
