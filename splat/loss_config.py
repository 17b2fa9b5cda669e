"""The IndoorGS loss's weights and switches (``--loss.*`` of `splat train`, §4.3): :class:`LossConfig`,
and the prior terms that ``TrainConfig.priors_until`` stops (splat/losses.py computes the terms)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal


@dataclass
class LossConfig:
    """Weights and switches of the IndoorGS loss (§4.3)."""

    lambda_dssim: float = 0.2
    """Weight of the D-SSIM part of L_rgb (3DGS): (1 - w) L1 + w D-SSIM, w in [0, 1]."""
    kernels: str = "fused"
    """L_rgb (with SSIM), L_n and L_nc: "fused" (C++ kernels with analytic gradients on the CPU,
    splat/losses_cpu.py; CUDA kernels on a GPU, splat/losses_cuda.py, or where those did not build
    and `--compile` is on, their torch code compiled, splat/compiled.py) or "torch" (autograd through
    their torch code, eagerly); the same loss and gradient up to float rounding
    (tests/test_losses_cpu.py, tests/test_losses_cuda.py, tests/test_compiled.py)."""
    lambda_depth: float = 0.1
    """λ_d, weight of the patch-PCC depth-prior loss L_d."""
    lambda_normal: float = 0.5
    """λ_n, weight of the normal-prior loss L_n."""
    lambda_flat: float = 100.0
    """λ_s, weight of the flattening loss L_s on line Gaussians."""
    lambda_nc: float = 0.1
    """λ_nc, weight of the depth-normal consistency loss L_nc."""
    patch_size: int = 32
    """Side S of the L_d patches in pixels, for 640x480 images (the trainer may scale it with the resolution)."""
    n_patches: int = 16
    """Number N of random non-overlapping L_d patches per view."""
    min_alpha_valid: float = 0.5
    """Pixels with rendered alpha at or below this are left out of L_d, L_n and L_nc."""
    use_depth: bool = True
    """Use L_d (needs depth priors)."""
    use_normal: bool = True
    """Use L_n (needs normal priors)."""
    use_flat: bool = True
    """Use L_s."""
    use_nc: bool = True
    """Use L_nc (from nc_from_iter on)."""
    nc_from_iter: int = 7000
    """First iteration of L_nc (7000, as PGSR / RaDe-GS start their geometric regularisers)."""
    flat_types: tuple[int, ...] = (1,)
    """Cue types flattened by L_s (geocues.types.CueType: SFM=0, LINE=1, PLANE=2); the paper: LINE."""
    nc_detach_depth: bool = False
    """Stop the L_nc gradient at the depth-derived normal (default: it flows into both)."""
    lambda_anchor: float = 5.0
    """λ_a, weight of the anchored-depth term L_a (not in the paper; 0 = the paper's loss): rendered
    depth against the depth prior aligned to the cues, beyond a tolerance. Active only for views
    whose prior the cue report aligned (docs/training_losses.md)."""
    anchor_tol_min: float = 0.03
    """Smallest tolerance τ of L_a in metres."""
    anchor_tol_p90: float = 0.5
    """τ = max(anchor_tol_min, this × the view's alignment 90th-percentile residual); 0.5 measured
    better than 1.0 at λ_a = 1 and 5 (docs/training_losses.md)."""
    plane_anchor: bool = False
    """L_a also holds, in each training view, the pixels where that view's own plane cues lie and its
    aligned prior has no depth (CUES/plane_anchors.npz; every such pixel when the view has no prior,
    so prior-free scenes get L_a on their weak-texture planes, with τ = anchor_tol_min there). An
    extension; needs lambda_anchor > 0."""
    plane_first: bool = False
    """With plane_anchor: where plane cues lie, their depth replaces the aligned prior's as L_a's
    anchor (τ = anchor_tol_min), instead of only filling where the prior has none. Measured: on the
    benchmark rooms the plane cues' depth is within 3 cm of GT on 88-93 % of their pixels, the aligned
    simulated prior on 25-48 % of the same pixels (docs/training_losses.md). An extension."""
    fused_anchor: bool = False
    """L_a's anchor is the TSDF fusion of every training view's aligned prior, rendered into the
    view (splat/fused_prior.py), where it has a surface; the view's own aligned prior elsewhere. An
    extension (the views' warps disagree and average out: 2.8 / 4.5 cm median error on the textured /
    bare room against 8.7 / 15.8 cm for the view's own aligned prior)."""
    fused_method: Literal["tsdf", "median"] = "tsdf"
    """How the aligned priors are fused: "tsdf" (a wide-truncation TSDF, ray cast) or "median" (in each
    pixel, the median of the view's prior and its nearest views' priors warped into it: no lean
    towards the farther prior, which the TSDF's free-space updates have)."""
    fused_neighbours: int = 32
    """Views warped into each view for fused_method "median"."""
    fused_voxel: float = 0.04
    """Voxel edge (m) of the fused prior's TSDF."""
    fused_trunc: float = 0.3
    """Truncation (m) of the fused prior's TSDF: wide, so that priors that disagree by a warp still average."""
    plane_views: Literal["own", "all"] = "own"
    """Whose plane cues a view's plane anchors (plane_anchor) and plane normals (plane_normals) take:
    "own" (the points its own planes put there) or "all" (every training view's, nearest first in
    each pixel: 3x the pixels on the benchmark rooms at the same error). An extension."""
    plane_normals: bool = False
    """Views without a normal prior take their own plane cues' normals as one (CUES/plane_anchors.npz,
    the pixels where the view's plane points lie; L_n then holds prior-free weak-texture planes
    flat). An extension; needs use_normal and lambda_normal > 0 to act."""
    lambda_mv: float = 0.0
    """λ_mv, weight of the multi-view photometric consistency L_mv (PGSR's; not in the paper; 0 = off):
    the rendered plane of a pixel warps its patch into a neighbouring training photo (splat/multiview.py)."""
    mv_from_iter: int = 7000
    """First iteration of L_mv, scaled with the run's length like nc_from_iter (PGSR starts at 7000)."""
    mv_samples: int = 4096
    """Pixels (patch centres) drawn per step for L_mv."""
    mv_patch: int = 7
    """Side of the L_mv patches in pixels (odd)."""
    mv_min_std: float = 0.01
    """L_mv leaves out patches whose grey standard deviation is below this (NCC undefined)."""
    mv_min_ncc: float = 0.0
    """L_mv leaves out pixels whose NCC is at or below this (occluded or unmatched)."""
    mv_neighbours: int = 4
    """Neighbouring training views per view; one is drawn per step."""


PRIOR_TERMS = ("depth", "anchor", "normal", "mv")
"""The terms TrainConfig.priors_until stops (L_d, L_a, L_n, L_mv), as total_loss names them."""


def without_priors(cfg: LossConfig, keep: tuple[str, ...] = ()) -> LossConfig:
    """``cfg`` with the terms that pull towards priors off (L_d, L_a, L_n, L_mv) but those named in
    ``keep``: what trains after TrainConfig.priors_until. L_rgb, L_s and L_nc are kept."""
    unknown = sorted(set(keep) - set(PRIOR_TERMS))
    if unknown:
        raise ValueError(f"--priors-kept: unknown terms {unknown}; choose from {', '.join(PRIOR_TERMS)}")
    off = {"depth": {"use_depth": False}, "anchor": {"lambda_anchor": 0.0}, "normal": {"use_normal": False},
           "mv": {"lambda_mv": 0.0}}
    return replace(cfg, **{k: v for term in PRIOR_TERMS if term not in keep for k, v in off[term].items()})


__all__ = ["LossConfig", "PRIOR_TERMS", "without_priors"]
