"""Training and test views of a scene as rasterizer inputs: cameras, images and priors, cached.

Images are read once (scene scale, RGB) and kept as uint8 tensors (640x480: 0.9 MB a view); depth
and normal priors, when the scene has them (``SCENE/priors/{depth,normal}/``), are kept as float16
(metres for depth: 1 mm steps up to 2 m, 2 mm to 4 m, enough for a monocular prior's accuracy;
a depth map with values outside float16's normal range stays float32).

With the per-image alignments of ``geocues extract`` (``geocues.depth_align.load_alignments``), a
view also carries its depth prior *aligned to the cues* (metric, scale/shift/warp fitted to the line
and SfM cues it sees) and that fit's 90th-percentile residual: the anchor of the trainer's
anchored-depth term (splat/losses.py ``anchored_depth_loss``). With the extract's plane anchors
(``--loss.plane-anchor``, geocues.plane_anchors), the pixels where a view's own plane cues lie and
its aligned prior has no depth -- every such pixel, for a view without a prior -- take the plane's
depth as their anchor. With ``plane_normals`` (``--loss.plane-normals``), a view without a normal
prior takes the normals of its own plane points as one (zeros, "invalid", elsewhere).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from geocues.depth_align import DepthAlignment
from geocues.logs import warn_once
from geocues.plane_anchors import PlaneAnchors, anchor_depth, anchor_normals
from geocues.scene import Scene, upsampling_warning
from splat.camera import Camera

log = logging.getLogger(__name__)

_F16_MAX, _F16_TINY = float(np.finfo(np.float16).max), float(np.finfo(np.float16).tiny)


def _compact(a: np.ndarray) -> Tensor:
    """float16 copy of a depth map when every non-zero |value| lies in float16's normal range, else
    float32: a relative prior in other units (L_d takes "any positive scale") overflowed to Inf
    above 65504 or lost its valid pixels to 0 below ~6e-8 (fuzz finding, tests/test_fuzz_losses.py)."""
    nz = np.abs(a[a != 0])
    fits = nz.size == 0 or (float(nz.max()) <= _F16_MAX and float(nz.min()) >= _F16_TINY)
    return torch.from_numpy(a).half() if fits else torch.from_numpy(np.ascontiguousarray(a, np.float32))


@dataclass
class View:
    """One posed image ready for render(): tensors on the training device."""

    index: int  # position in Scene.cameras
    name: str  # image file name
    camera: Camera
    rgb: Tensor  # [H, W, 3] float32 in [0, 1]
    depth_prior: Tensor | None  # [H, W] float32 metres, 0 = invalid
    normal_prior: Tensor | None  # [H, W, 3] float32 unit camera frame, 0 = invalid
    depth_anchor: Tensor | None = None  # [H, W] float32 metres: the prior aligned to the cues, 0 = invalid
    anchor_p90: float = float("nan")  # 90th-percentile |residual| (m) of that alignment at the cues
    anchor_tight: Tensor | None = None  # [H, W] bool: anchor pixels from plane cues (held at the least tolerance)


class ViewSet:
    """The views of ``scene`` with indices ``indices`` (train or test split), loaded once."""

    def __init__(self, scene: Scene, indices: list[int], device: torch.device | str = "cpu",
                 load_priors: bool = True, desc: str = "views",
                 alignments: dict[str, DepthAlignment] | None = None, prior_kind: str = "depth",
                 plane_anchors: PlaneAnchors | None = None, plane_normals: PlaneAnchors | None = None,
                 plane_first: bool = False, plane_views: str = "own",
                 anchor_override: dict[str, np.ndarray] | None = None):
        """``plane_anchors`` / ``plane_normals``: the plane cues that fill (or, ``plane_first``, replace)
        a view's L_a anchor and give a view without a normal prior its normals; ``plane_views``:
        "own" (each view's own plane points) or "all" (those of every view of this set);
        ``anchor_override``: {image name: [H, W] depth} that replaces the aligned prior as the L_a
        anchor (the fused prior, splat/fused_prior.py), before the plane cues."""
        if plane_views not in ("own", "all"):
            raise ValueError(f"plane_views must be 'own' or 'all', got {plane_views!r}")
        self.scene, self.indices, self.device = scene, list(indices), torch.device(device)
        names = [scene.cameras[i].name for i in self.indices]
        shared = {id(p): p.of_views(names) for p in (plane_anchors, plane_normals) if p is not None and plane_views == "all"}

        def points(planes: PlaneAnchors, name: str) -> tuple[np.ndarray, np.ndarray]:
            return shared[id(planes)] if plane_views == "all" else planes.of(name)

        self._rgb: list[Tensor] = []
        self._depth: list[Tensor | None] = []
        self._normal: list[Tensor | None] = []
        self._anchor: list[Tensor | None] = []
        self._anchor_p90: list[float] = []
        self._tight: list[Tensor | None] = []
        self.cameras: list[Camera] = []
        for i in tqdm(self.indices, desc=f"loading {desc}", leave=False):
            cam = scene.cameras[i]
            self.cameras.append(Camera.from_Rt(cam.K, cam.R, cam.t, cam.width, cam.height, device=self.device))
            rgb = np.clip(np.round(scene.load_image(i) * 255.0), 0, 255).astype(np.uint8)
            self._rgb.append(torch.from_numpy(rgb))
            d = scene.depth_prior(i) if load_priors else None
            n = scene.normal_prior(i) if load_priors else None
            al = (alignments or {}).get(cam.name) if d is not None else None
            aligned = None if al is None else al.apply(d)
            if d is not None and prior_kind == "disparity":
                # L_d's correlation is blind to scale and shift, not to inverse: it gets depth, the
                # aligned one where the cues aligned it, else 1/p (exact up to scale for shift-free
                # disparity, the form Depth-Anything and MiDaS write)
                d = aligned if aligned is not None else np.where(d > 0, 1.0 / np.maximum(d, 1e-12), 0.0)
            if n is None and plane_normals is not None and len((pts := points(plane_normals, cam.name))[0]):
                n = anchor_normals(*pts, cam.K, cam.R, cam.t, cam.height, cam.width)
            self._depth.append(None if d is None else _compact(d))
            self._normal.append(None if n is None else torch.from_numpy(n).half())  # unit: fits
            if anchor_override is not None and cam.name in anchor_override:
                aligned = anchor_override[cam.name]
            tight = None
            if plane_anchors is not None and len((pts := points(plane_anchors, cam.name))[0]):
                on_plane = anchor_depth(*pts, cam.K, cam.R, cam.t, cam.height, cam.width)
                # plane_first: the plane pixels replace the prior's and are held at the least tolerance;
                # else they fill where it has none (at the view's tolerance: the rows measured so)
                use = (on_plane > 0) if aligned is None or plane_first else (aligned <= 0) & (on_plane > 0)
                aligned = np.where(use, on_plane, 0.0 if aligned is None else aligned)
                tight = use if plane_first else None
            self._anchor.append(None if aligned is None else _compact(aligned))
            self._tight.append(None if tight is None or not tight.any() else torch.from_numpy(tight))
            self._anchor_p90.append(float("nan") if al is None else float(al.residual_p90_m))
        # On a CUDA device the images and priors stay in pinned host memory: each step's copy to the
        # GPU then runs asynchronously, where a copy from pageable memory waits for the GPU to finish
        # everything queued before it (a stall per step; the copies are what a step needs, not a cache)
        self._pinned = self.device.type == "cuda"
        if self._pinned:
            for maps in (self._rgb, self._depth, self._normal, self._anchor, self._tight):
                maps[:] = [None if m is None else m.pin_memory() for m in maps]
        n_depth = sum(d is not None for d in self._depth)
        n_normal = sum(n is not None for n in self._normal)
        n_anchor = sum(a is not None for a in self._anchor)
        if load_priors:
            log.info("%s: %d views, %d with a depth prior, %d with an anchor for L_a, %d with a normal prior",
                     desc, len(self), n_depth, n_anchor, n_normal)
        else:  # held-out views are scored on their images alone
            log.info("%s: %d views (images only)", desc, len(self))

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def has_depth_priors(self) -> bool:
        return any(d is not None for d in self._depth)

    @property
    def has_normal_priors(self) -> bool:
        return any(n is not None for n in self._normal)

    def camera_centers(self) -> np.ndarray:
        """[V, 3] camera centres in world coordinates (float64)."""
        return np.stack([self.scene.cameras[i].center for i in self.indices]) if self.indices else np.zeros((0, 3))

    def _dev(self, t: Tensor) -> Tensor:
        """``t`` on the views' device; from pinned memory without waiting on a CUDA device (see __init__)."""
        return t.to(self.device, non_blocking=self._pinned)

    def image(self, k: int) -> Tensor:
        """[H, W, 3] float32 RGB in [0, 1] of view k (without its priors)."""
        return self._dev(self._rgb[k]).float() / 255.0

    def __getitem__(self, k: int) -> View:
        d, n, a, t = self._depth[k], self._normal[k], self._anchor[k], self._tight[k]
        return View(index=self.indices[k], name=self.scene.cameras[self.indices[k]].name, camera=self.cameras[k],
                    rgb=self._dev(self._rgb[k]).float() / 255.0,
                    depth_prior=None if d is None else self._dev(d).float(),
                    normal_prior=None if n is None else self._dev(n).float(),
                    depth_anchor=None if a is None else self._dev(a).float(), anchor_p90=self._anchor_p90[k],
                    anchor_tight=None if t is None else self._dev(t))


def warn_large_images(scene: Scene, downscale: float, limit: int = 1600) -> None:
    """One warning when the training images are over ``limit`` px on their longer side: a step renders
    every pixel (a 4032x3024 phone photo is 40x a 640x480 view), and 3DGS trains at most 1600 px wide.
    A ``downscale`` below 1 gets one too: it upsamples the photos (interpolated pixels, no detail)."""
    if up := upsampling_warning(downscale, "work per step", "trains at the photos' own size"):
        warn_once(log, f"{scene.root}: {up}")
    cam = max(scene.cameras, key=lambda c: max(c.width, c.height))
    side = max(cam.width, cam.height)
    if side > limit:
        factor = float(np.ceil(downscale * side / limit * 10) / 10)
        warn_once(log, f"{scene.root}: training images are up to {cam.width}x{cam.height} px (--downscale {downscale:g}): each "
                       f"step renders every pixel, {cam.width * cam.height / (640 * 480):.0f}x a 640x480 view's "
                       f"work; 3DGS trains at most {limit} px wide: --downscale {factor:g} trains at "
                       f"{round(cam.width * downscale / factor)}x{round(cam.height * downscale / factor)}")
