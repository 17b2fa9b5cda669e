"""Weak-texture regions (paper §4.1, plane-like cues, first step).

The paper segments each image with SAM and measures texture by the density of SIFT keypoints per
segment. Without learned weights we segment with OpenCV's graph segmentation (Felzenszwalb) or
SLIC superpixels, then count SIFT keypoints per segment (:func:`keypoint_density`). Segments below a
density threshold are weak-texture regions; they are eroded away from their borders (where depth
priors are blurred and lines sit) and kept if still large enough.

Pixel parameters are given for a 640-pixel-wide image and scaled with the working width, so the
result does not depend on the input resolution. Results are cached per image (``.npz``), keyed by
the parameters and the image file's size and modification time.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np

log = logging.getLogger(__name__)

REF_WIDTH = 640  # pixel parameters below are for this image width


@dataclass
class TextureConfig:
    """Segmentation and SIFT-density test for weak-texture regions."""

    method: Literal["graph", "slic"] = "graph"
    """Segmentation: OpenCV graph segmentation (Felzenszwalb) or SLIC superpixels."""
    work_width: int = 640
    """Detect SIFT and build regions at this image width (never upsampled; labels map back by nearest)."""
    segment_width: int = 320
    """Segment at this image width (speed: graph segmentation at 640 px is ~4x slower)."""
    graph_sigma: float = 0.8
    """Graph segmentation: Gaussian smoothing sigma before segmenting."""
    graph_k: float = 300.0
    """Graph segmentation: scale parameter k (larger = larger segments)."""
    graph_min_size: int = 400
    """Graph segmentation: minimum segment size in pixels at 640 px width."""
    slic_region_size: int = 40
    """SLIC: superpixel size in pixels at 640 px width."""
    slic_ruler: float = 10.0
    """SLIC: compactness."""
    merge_step: float = 3.0
    """Merge neighbouring segments whose mean colour step across their border is below this (0-255; 0 = off)."""
    sift_contrast_threshold: float = 0.04
    """SIFT detector contrast threshold (OpenCV default 0.04)."""
    weak_density: float = 1.0
    """Weak texture: fewer SIFT keypoints than this per 1000 pixels, in a window around each pixel."""
    density_window: int = 48
    """Window side (pixels at 640 px width) of the per-pixel keypoint density (0 = per segment only)."""
    max_segment_density: float = 2.0
    """Segments denser than this (keypoints per 1000 px) hold no weak region at all."""
    erode_px: int = 4
    """Erode each weak region by this many pixels at 640 px width (keeps away from its borders)."""
    min_region_frac: float = 0.002
    """Drop weak regions smaller than this fraction of the image after erosion."""


@dataclass
class WeakTexture:
    """Weak-texture regions of one image (at the image's resolution)."""

    regions: np.ndarray  # [H, W] int32 weak-region id 0..R-1, -1 = not weak (or eroded away)
    density: np.ndarray  # [R] float32 SIFT keypoints per 1000 px of each weak region's segment
    n_segments: int  # segments found in the image
    n_keypoints: int  # SIFT keypoints found in the image

    @property
    def n_regions(self) -> int:
        return len(self.density)

    @property
    def weak_fraction(self) -> float:
        return float(np.mean(self.regions >= 0)) if self.regions.size else 0.0


def config_key(cfg: object, *extra: object) -> str:
    """Short stable hash of a config dataclass or dict (and extra values) for cache keys."""
    blob = json.dumps([cfg if isinstance(cfg, dict) else asdict(cfg), [str(e) for e in extra]],
                      sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:12]


def file_stamp(*paths: str | Path | None) -> str:
    """What a cache entry depends on in each file: its name, byte size and modification time
    (nanoseconds); "-" for None or a missing file. A file rewritten in place gets a new stamp."""
    parts = []
    for p in paths:
        if p is None or not Path(p).is_file():
            parts.append("-")
        else:
            st = Path(p).stat()
            parts.append(f"{Path(p).name}:{st.st_size}:{st.st_mtime_ns}")
    return "|".join(parts)


def tree_stamp(root: str | Path, subdirs: tuple[str, ...]) -> str:
    """Hash of the file stamps under ``root/<subdir>`` for each subdir (images, priors, model):
    a scene regenerated at the same path gets a new value."""
    h = hashlib.sha1()
    root = Path(root)
    for sub in subdirs:
        base = root / sub
        if not base.exists():
            continue
        for f in sorted(p for p in base.rglob("*") if p.is_file()):
            h.update(f"{f.relative_to(root)}={file_stamp(f)};".encode())
    return h.hexdigest()[:12]


def segment_image(bgr: np.ndarray, cfg: TextureConfig) -> np.ndarray:
    """Over-segment ``bgr`` [H, W, 3] uint8 -> labels [H, W] int32 in 0..S-1."""
    import cv2

    s = bgr.shape[1] / REF_WIDTH
    if cfg.method == "graph":
        seg = cv2.ximgproc.segmentation.createGraphSegmentation(
            sigma=cfg.graph_sigma, k=cfg.graph_k, min_size=max(1, int(round(cfg.graph_min_size * s * s))))
        labels = seg.processImage(bgr)
    elif cfg.method == "slic":
        lab = cv2.cvtColor(bgr, cv2.COLOR_BGR2LAB)
        slic = cv2.ximgproc.createSuperpixelSLIC(lab, algorithm=cv2.ximgproc.SLICO,
                                                 region_size=max(4, int(round(cfg.slic_region_size * s))),
                                                 ruler=cfg.slic_ruler)
        slic.iterate(10)
        labels = slic.getLabels()
    else:
        raise ValueError(f"unknown segmentation method {cfg.method!r}, expected 'graph' or 'slic'")
    labels = labels.astype(np.int32)
    used = np.bincount(labels.ravel()) > 0
    if not used.all():  # make ids contiguous
        labels = (np.cumsum(used) - 1).astype(np.int32)[labels]
    return labels


def merge_smooth_boundaries(labels: np.ndarray, bgr: np.ndarray, step: float) -> np.ndarray:
    """Merge adjacent segments whose border is smooth: the mean over their shared border of the
    largest per-channel difference across it (image blurred by sigma 1) is below ``step`` levels.
    labels: [H, W] int 0..S-1, bgr: [H, W, 3] uint8. Returns new contiguous labels [H, W]."""
    import cv2
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    img = cv2.GaussianBlur(bgr, (0, 0), 1.0).astype(np.float32)
    n = int(labels.max()) + 1
    a_list, b_list, d_list = [], [], []
    for la, lb, ia, ib in ((labels[:, :-1], labels[:, 1:], img[:, :-1], img[:, 1:]),
                           (labels[:-1, :], labels[1:, :], img[:-1, :], img[1:, :])):
        m = la != lb
        a_list.append(np.minimum(la[m], lb[m]))
        b_list.append(np.maximum(la[m], lb[m]))
        d_list.append(np.abs(ia[m] - ib[m]).max(axis=-1))
    a, b, d = (np.concatenate(x) for x in (a_list, b_list, d_list))
    if len(a) == 0:
        return labels
    key = a.astype(np.int64) * n + b
    uk, inv = np.unique(key, return_inverse=True)
    mean_d = np.bincount(inv, weights=d) / np.bincount(inv)
    sel = mean_d < step
    g = coo_matrix((np.ones(sel.sum()), (uk[sel] // n, uk[sel] % n)), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    return comp.astype(np.int32)[labels]


def keypoint_density(labels: np.ndarray, keypoints_xy: np.ndarray) -> np.ndarray:
    """Texture measure of the paper (§4.1): SIFT keypoints per segment area.

        ρ_s = 1000 · |{k : kp_k ∈ s}| / |s|      (keypoints per 1000 pixels)

    labels: [H, W] int segment ids 0..S-1; keypoints_xy: [K, 2] pixel coordinates (x, y), OpenCV's
    keypoint convention (pixel centres at integers). Returns ρ [S] float32.
    """
    if labels.ndim != 2:
        raise ValueError(f"labels must be [H, W], got shape {labels.shape}")
    kp = np.asarray(keypoints_xy, np.float64).reshape(-1, 2)
    h, w = labels.shape
    n_seg = int(labels.max()) + 1 if labels.size else 0
    area = np.bincount(labels.ravel(), minlength=n_seg).astype(np.float64)
    cols = np.clip(np.round(kp[:, 0]).astype(np.int64), 0, w - 1)
    rows = np.clip(np.round(kp[:, 1]).astype(np.int64), 0, h - 1)
    count = np.bincount(labels[rows, cols], minlength=n_seg).astype(np.float64)
    return (1000.0 * count / np.maximum(area, 1.0)).astype(np.float32)


def local_keypoint_density(keypoints_xy: np.ndarray, shape: tuple[int, int], window: int) -> np.ndarray:
    """Keypoints per 1000 pixels in a ``window`` x ``window`` box around each pixel, [H, W]."""
    import cv2

    h, w = shape
    kp = np.asarray(keypoints_xy, np.float64).reshape(-1, 2)
    hits = np.zeros((h, w), np.float32)
    cols = np.clip(np.round(kp[:, 0]).astype(np.int64), 0, w - 1)
    rows = np.clip(np.round(kp[:, 1]).astype(np.int64), 0, h - 1)
    np.add.at(hits, (rows, cols), 1.0)
    return 1000.0 * cv2.boxFilter(hits, -1, (window, window), normalize=True,
                                  borderType=cv2.BORDER_REFLECT)


def weak_texture_regions(image: np.ndarray, cfg: TextureConfig) -> WeakTexture:
    """Weak-texture regions of one RGB image [H, W, 3] (float in [0, 1] or uint8)."""
    import cv2

    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be [H, W, 3], got shape {image.shape}")
    h, w = image.shape[:2]
    rgb8 = image if image.dtype == np.uint8 else np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    bgr = np.ascontiguousarray(rgb8[:, :, ::-1])
    ww = max(16, min(w, int(cfg.work_width)))  # never upsample
    wh = max(16, int(round(h * ww / w)))
    small = bgr if (ww, wh) == (w, h) else cv2.resize(bgr, (ww, wh), interpolation=cv2.INTER_AREA)
    sw = max(16, min(ww, int(cfg.segment_width)))
    sh = max(16, int(round(wh * sw / ww)))
    seg_img = small if sw == ww else cv2.resize(small, (sw, sh), interpolation=cv2.INTER_AREA)
    labels = segment_image(seg_img, cfg)  # [sh, sw]
    if cfg.merge_step > 0:
        labels = merge_smooth_boundaries(labels, seg_img, cfg.merge_step)
    if sw != ww:
        labels = cv2.resize(labels, (ww, wh), interpolation=cv2.INTER_NEAREST)  # [wh, ww]
    sift = cv2.SIFT_create(contrastThreshold=cfg.sift_contrast_threshold)
    kps = sift.detect(cv2.cvtColor(small, cv2.COLOR_BGR2GRAY), None)
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    density = keypoint_density(labels, xy)  # [S]
    s = ww / REF_WIDTH
    win = int(round(cfg.density_window * s))
    if win > 1:  # weak pixels: low keypoint density around them, in a not too dense segment
        weak = (local_keypoint_density(xy, (wh, ww), win) < cfg.weak_density) \
            & (density < cfg.max_segment_density)[labels]
    else:  # the paper's rule alone: the segment's density
        weak = (density < cfg.weak_density)[labels]
    # Erode: keep weak pixels more than r pixels from any segment border or non-weak pixel. A
    # region is then a connected component of those pixels; it never crosses a segment border.
    border = ~weak
    border[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    border[1:, :] |= labels[1:, :] != labels[:-1, :]
    r = max(0, int(round(cfg.erode_px * s)))
    dist = cv2.distanceTransform((~border).astype(np.uint8), cv2.DIST_L2, 3)
    core = (dist > r).astype(np.uint8)
    n_cc, cc, stats, _ = cv2.connectedComponentsWithStats(core, connectivity=4)
    min_area = cfg.min_region_frac * ww * wh
    keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area) + 1  # component ids kept
    lut = np.full(n_cc, -1, np.int32)
    lut[keep] = np.arange(len(keep), dtype=np.int32)
    regions = lut[cc]  # [wh, ww]
    dens = keypoint_density(np.where(regions >= 0, regions + 1, 0), xy)[1:] if len(keep) else []
    if (ww, wh) != (w, h):
        regions = cv2.resize(regions, (w, h), interpolation=cv2.INTER_NEAREST)
    return WeakTexture(regions, np.asarray(dens, np.float32), int(labels.max()) + 1, len(kps))


def _cache_path(cache_dir: Path, image_path: Path, key: str) -> Path:
    st = image_path.stat()
    file_key = hashlib.sha1(f"{image_path.resolve()}|{st.st_size}|{st.st_mtime_ns}|{key}".encode()
                            ).hexdigest()[:16]
    return cache_dir / f"{image_path.stem}_{file_key}.npz"


def load_or_compute(image_path: Path, load_image, cfg: TextureConfig, cache_dir: Path | None,
                    size: tuple[int, int]) -> tuple[WeakTexture, bool]:
    """Weak texture of one image, from ``cache_dir`` when present. ``load_image()`` returns the RGB
    image; ``size`` = (width, height) is part of the key. Returns (result, came_from_cache)."""
    from geocues.atomic import atomic_path

    path = None
    if cache_dir is not None:
        path = _cache_path(Path(cache_dir), Path(image_path), config_key(cfg, size, file_stamp(image_path)))
        if path.is_file():
            try:
                with np.load(path) as z:
                    return WeakTexture(z["regions"], z["density"], int(z["n_segments"]),
                                       int(z["n_keypoints"])), True
            except (OSError, KeyError, ValueError) as exc:  # a broken cache entry is recomputed
                log.warning("texture cache %s unreadable (%s); recomputing", path, exc)
    wt = weak_texture_regions(load_image(), cfg)
    if path is not None:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, regions=wt.regions, density=wt.density,
                                    n_segments=wt.n_segments, n_keypoints=wt.n_keypoints)
    return wt, False
