"""Multi-view photometric consistency L_mv (PGSR, Chen et al. 2024, §3.3; an extension here, not in
IndoorGS): the rendered depth and normal of a pixel define a local plane, the plane induces a
homography into a neighbouring training view, and the grey patch around the pixel must match the
patch the homography lands on (zero-mean NCC). L_d and L_a need depth priors; this term needs only
the posed photos, so it constrains the depth of textured surfaces on prior-free scenes (ICL, a
user's photos) — a flat Gaussian painted 5 cm in front of a textured wall warps its patch to the
wrong place in every other view.

Differences from PGSR, all measured choices or cost savings (docs/training_losses.md):
- no second render: the neighbour's *photo* is warped, so PGSR's forward-backward depth check (which
  needs the neighbour's rendered depth) is replaced by a robust rule: a pixel whose NCC is at or below
  ``min_ncc`` counts as occluded or unmatched and is left out (as ACMM / COLMAP drop poor matches);
- a random subset of ``n_samples`` pixels per step (PGSR samples too), patches of ``patch`` × ``patch``;
- neighbours are training views only (test views never reach the loss), chosen once per run as
  `geocues mvs` chooses them (optical axes within 40°, a triangulation angle of at least 2°).

Hard cases (tests/test_multiview.py): a patch whose reference texture is flat (std < ``min_std``:
NCC undefined), a plane seen edge-on, depth 0 or at the near plane, a homography that sends the patch
behind the neighbour or outside its image, views without overlap — each such pixel is left out, and
an empty set gives a 0 connected to the graph (zero gradients, never NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

NEAR = 1e-3  # metres: rendered depth at or below this has no plane
_MIN_COS = 0.05  # |cos| between the normal and the ray below this: the plane is seen edge-on


@dataclass
class SourceView:
    """What L_mv needs of a neighbouring view: its grey image and its pose relative to the reference."""

    gray: Tensor  # [H, W] float32 in [0, 1]
    K: Tensor  # [3, 3] intrinsics (COLMAP pixel centres)
    R_rel: Tensor  # [3, 3] reference camera -> source camera rotation
    t_rel: Tensor  # [3] reference camera -> source camera translation (x_s = R_rel x_r + t_rel)


def to_gray(rgb: Tensor) -> Tensor:
    """[H, W, 3] RGB in [0, 1] -> [H, W] luma (ITU-R 601, as `geocues mvs`)."""
    return rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114


def source_view(ref_camera, src_camera, src_rgb: Tensor) -> SourceView:
    """The SourceView of ``src_camera`` (a splat.camera.Camera with its image ``src_rgb`` [H, W, 3])
    seen from ``ref_camera``."""
    R_rel = src_camera.R @ ref_camera.R.T
    return SourceView(gray=to_gray(src_rgb), K=src_camera.K, R_rel=R_rel, t_rel=src_camera.t - R_rel @ ref_camera.t)


def plane_homographies(depth: Tensor, normal: Tensor, rays: Tensor, src: SourceView, K_ref: Tensor
                       ) -> tuple[Tensor, Tensor]:
    """Homographies [M, 3, 3] from reference pixels to source pixels induced by the plane through
    each sampled point X = depth · ray with normal ``normal`` (camera frame): with n·X = δ on the
    plane, x_s = (R + t nᵀ/δ) x_r, so H = K_s (R + t nᵀ/δ) K_r⁻¹. depth [M], normal [M, 3], rays [M, 3]
    (z = 1). Returns (H, valid [M]); invalid planes (depth ≤ NEAR, no normal, seen edge-on) get H = 0."""
    n_len = normal.detach().norm(dim=-1)
    ray_len = rays.norm(dim=-1)
    cos = (normal * rays).sum(-1) / (n_len * ray_len).clamp_min(1e-12)
    valid = (depth.detach() > NEAR) & (n_len > 0.5) & (cos.detach().abs() > _MIN_COS) & torch.isfinite(depth.detach())
    depth = torch.where(valid, depth, torch.ones_like(depth))  # NaN / Inf must not reach any gradient
    delta = depth * (normal * rays).sum(-1)  # n·X, metres (negative: normals face the camera)
    inv = torch.where(valid, 1.0 / torch.where(valid, delta, torch.ones_like(delta)), torch.zeros_like(delta))
    A = src.R_rel[None] + src.t_rel[None, :, None] * (normal * inv[:, None])[:, None, :]  # [M, 3, 3]
    H = src.K.to(depth)[None] @ A @ torch.linalg.inv(K_ref.to(depth))[None]
    return torch.where(valid[:, None, None], H, torch.zeros_like(H)), valid


def multiview_ncc_loss(depth: Tensor, normal: Tensor, gray_ref: Tensor, K_ref: Tensor, src: SourceView,
                       n_samples: int = 4096, patch: int = 7, min_std: float = 0.01, min_ncc: float = 0.0,
                       generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
    """L_mv: mean over kept sampled pixels of 1 − NCC(reference patch, homography-warped source patch).

    depth [H, W] rendered z-depth (m; the trainer passes the expected depth), normal [H, W, 3] rendered
    camera-frame normals, gray_ref [H, W] the reference photo in grey; K_ref [3, 3]. The gradient
    flows through the homography (the plane's depth and normal at the patch centre) into the
    sampling positions in the source photo. Returns (loss, {"kept": share of the samples used}).
    """
    h, w = depth.shape
    r = patch // 2
    dev = depth.device
    if h <= 2 * r or w <= 2 * r or n_samples <= 0:
        return depth.sum() * 0.0, {"kept": 0.0}
    ii = torch.randint(r, h - r, (n_samples,), generator=generator).to(dev)
    jj = torch.randint(r, w - r, (n_samples,), generator=generator).to(dev)
    K = K_ref.to(depth)
    rays = torch.stack([(jj + 0.5 - K[0, 2]) / K[0, 0], (ii + 0.5 - K[1, 2]) / K[1, 1], torch.ones_like(K[0, 0]).expand(n_samples)], -1)
    H, valid = plane_homographies(depth[ii, jj], normal[ii, jj], rays, src, K)
    off = torch.arange(-r, r + 1, device=dev)
    dy, dx = torch.meshgrid(off, off, indexing="ij")
    dy, dx = dy.reshape(-1), dx.reshape(-1)  # [P]
    ref = gray_ref.to(depth)[ii[:, None] + dy, jj[:, None] + dx]  # [M, P] exact pixels
    pix = torch.stack([jj[:, None] + dx + 0.5, ii[:, None] + dy + 0.5, torch.ones(n_samples, dx.numel(), device=dev)], -1)
    q = pix.to(depth) @ H.transpose(1, 2)  # [M, P, 3]
    z = q[..., 2]
    in_front = (z.detach() > 1e-6).all(-1)
    uv = q[..., :2] / torch.where(z.detach() > 1e-6, z, torch.ones_like(z))[..., None]
    hs, ws = src.gray.shape
    inside = ((uv.detach()[..., 0] >= 0) & (uv.detach()[..., 0] <= ws) & (uv.detach()[..., 1] >= 0)
              & (uv.detach()[..., 1] <= hs)).all(-1)
    grid = torch.stack([2 * uv[..., 0] / ws - 1, 2 * uv[..., 1] / hs - 1], -1)
    grid = torch.where((valid & in_front & inside)[:, None, None], grid, torch.zeros_like(grid))  # no Inf into grid_sample
    warped = F.grid_sample(src.gray.to(depth)[None, None], grid[None], mode="bilinear", padding_mode="border",
                           align_corners=False)[0, 0]  # [M, P]
    ref_c = ref - ref.mean(-1, keepdim=True)
    src_c = warped - warped.mean(-1, keepdim=True)
    var_r, var_s = (ref_c * ref_c).mean(-1), (src_c * src_c).mean(-1)
    defined = (var_r > min_std ** 2) & (var_s.detach() > 1e-8)
    denom = torch.sqrt(torch.where(defined, var_r * var_s, torch.ones_like(var_s)))
    ncc = torch.where(defined, (ref_c * src_c).mean(-1) / denom, torch.zeros_like(denom)).clamp(-1, 1)
    keep = valid & in_front & inside & defined & (ncc.detach() > min_ncc)
    n_keep = int(keep.sum())
    loss = torch.where(keep, 1.0 - ncc, torch.zeros_like(ncc)).sum() / max(n_keep, 1)
    return loss, {"kept": n_keep / n_samples}


def training_neighbours(scene, train_indices: list[int], n_neighbours: int = 4) -> list[list[int]]:
    """For each training view (position k in ``train_indices``), the positions of up to
    ``n_neighbours`` other training views chosen as `geocues mvs` chooses them
    (geocues.mvs.select_neighbours at the geometric mean of the view's SfM depth bounds)."""
    from geocues.mvs import MvsConfig, depth_bounds, select_neighbours

    cfg = MvsConfig(n_neighbours=n_neighbours)
    pos = {i: k for k, i in enumerate(train_indices)}
    out = []
    for i in train_indices:
        near, far = depth_bounds(scene, i)
        picks = select_neighbours(scene.cameras, i, cfg, float(np.sqrt(near * far)), candidates=train_indices)
        out.append([pos[j] for j in picks])
    return out
