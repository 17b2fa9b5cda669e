"""2D line segments per image: OpenCV LSD / FastLineDetector on the RGB image and, when normal
priors exist, on the normal map (paper Fig. 3), duplicates of the two sources merged; LBD
descriptors and mean colours per segment; a per-image cache keyed by the detector parameters.

Segments are ``[N, 4]`` float64 rows ``(x1, y1, x2, y2)`` in COLMAP pixel coordinates (the centre
of the top-left pixel is (0.5, 0.5)).
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from geocues.atomic import atomic_path
from geocues.texture import file_stamp
from geocues.lines.config import LineConfig

log = logging.getLogger(__name__)

CACHE_VERSION = 2
LSD_SCALE = 0.8  # OpenCV's default LSD scale; its output needs + 0.5 / scale to reach COLMAP pixels
SOURCE_RGB, SOURCE_NORMAL = 0, 1


@dataclass
class Segments2D:
    """The 2D segments of one image."""

    segs: np.ndarray  # [N, 4] float64 (x1, y1, x2, y2), COLMAP pixel coordinates
    source: np.ndarray  # [N] uint8, SOURCE_RGB or SOURCE_NORMAL
    desc: np.ndarray  # [N, 32] uint8 LBD descriptor (computed on the RGB image)
    colors: np.ndarray  # [N, 3] float32 mean RGB along the segment, in [0, 1]

    def __len__(self) -> int:
        return len(self.segs)

    @classmethod
    def empty(cls) -> "Segments2D":
        return cls(np.zeros((0, 4)), np.zeros(0, np.uint8), np.zeros((0, 32), np.uint8),
                   np.zeros((0, 3), np.float32))


def segment_lengths(segs: np.ndarray) -> np.ndarray:
    """Lengths of segments [N, 4] in pixels, [N]."""
    return np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])


def detect_gray(gray: np.ndarray, cfg: LineConfig) -> np.ndarray:
    """Segments [N, 4] (COLMAP pixels) of a uint8 [H, W] image, shorter ones than
    ``cfg.min_length_px`` (scaled) dropped, at most ``cfg.max_segments`` longest kept."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"expected a uint8 [H, W] image, got {gray.dtype} {gray.shape}")
    if cfg.detector == "lsd":
        lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, LSD_SCALE)
        raw = lsd.detect(gray)[0]
        offset = 0.5 / LSD_SCALE  # LSD works at `scale` with pixel corners at 0: map back to COLMAP
    else:
        min_len = int(round(cfg.px(cfg.min_length_px, gray.shape[1])))
        fld = cv2.ximgproc.createFastLineDetector(length_threshold=max(min_len, 2))
        raw = fld.detect(gray)
        offset = 1.0  # FLD reports the integer pixel left/above a step edge (measured)
    if raw is None:
        return np.zeros((0, 4))
    segs = raw.reshape(-1, 4).astype(np.float64) + offset
    length = segment_lengths(segs)
    keep = length >= cfg.px(cfg.min_length_px, gray.shape[1])
    segs, length = segs[keep], length[keep]
    order = np.argsort(-length, kind="stable")[: cfg.max_segments]
    return segs[order]


def normal_map_to_channels(normal: np.ndarray) -> list[np.ndarray]:
    """Three uint8 images of a normal map [H, W, 3] (components mapped from [-1, 1] to [0, 255]);
    an edge between two planes shows in at least one of them."""
    if normal.ndim != 3 or normal.shape[2] != 3:
        raise ValueError(f"expected a normal map [H, W, 3], got {normal.shape}")
    u8 = np.clip((normal + 1.0) * 127.5, 0, 255).astype(np.uint8)
    return [np.ascontiguousarray(u8[:, :, c]) for c in range(3)]


def dedup_segments(segs: np.ndarray, angle_deg: float, dist_px: float,
                   priority: np.ndarray | None = None, cross_dist_px: float | None = None) -> np.ndarray:
    """Indices of segments [N, 4] to keep after dropping duplicates. Segments are ranked by
    ``priority`` [N] (lower first; default all equal), then by length; a segment is dropped when
    a higher-ranked one is within ``angle_deg``, both its endpoints lie within ``dist_px`` of
    that one's line (``cross_dist_px`` when their priorities differ) and at least half of it
    overlaps it. RGB segments rank before normal-map ones: a prior's edges are blurred and
    offset (1-2 px on the benchmark rooms' simulated priors), the image's are not."""
    n = len(segs)
    if n < 2:
        return np.arange(n)
    prio = np.zeros(n) if priority is None else np.asarray(priority, float)
    length = segment_lengths(segs)
    order = np.lexsort((-length, prio))
    s, length, prio = segs[order], length[order], prio[order]
    p, q = s[:, :2], s[:, 2:]
    d = (q - p) / np.maximum(length, 1e-9)[:, None]  # [N, 2] unit directions
    cos = np.abs(d @ d.T)  # [N, N]
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)  # [N, 2] unit normals
    # distance of endpoints of j (columns) to the line of i (rows)
    dp = np.abs(np.einsum("ik,ijk->ij", nrm, p[None] - p[:, None]))
    dq = np.abs(np.einsum("ik,ijk->ij", nrm, q[None] - p[:, None]))
    tp = np.einsum("ik,ijk->ij", d, p[None] - p[:, None])  # positions of j's ends along i
    tq = np.einsum("ik,ijk->ij", d, q[None] - p[:, None])
    lo, hi = np.minimum(tp, tq), np.maximum(tp, tq)
    overlap = np.clip(np.minimum(hi, length[:, None]) - np.maximum(lo, 0.0), 0.0, None)
    tol = np.where(prio[:, None] == prio[None, :], dist_px,
                   dist_px if cross_dist_px is None else cross_dist_px)
    dup = ((cos >= np.cos(np.deg2rad(angle_deg))) & (dp <= tol) & (dq <= tol)
           & (overlap >= 0.5 * length[None, :]))
    dup &= np.arange(n)[:, None] < np.arange(n)[None, :]  # only a higher-ranked one removes
    drop = np.zeros(n, bool)
    for i in range(n):  # greedy in rank order: a dropped segment removes nothing
        if not drop[i]:
            drop |= dup[i]
    return np.sort(order[~drop])


def segment_colors(image: np.ndarray, segs: np.ndarray, n_samples: int = 16) -> np.ndarray:
    """Mean colour [N, 3] of image [H, W, 3] (float, [0, 1]) sampled along segments [N, 4]."""
    if len(segs) == 0:
        return np.zeros((0, 3), np.float32)
    h, w = image.shape[:2]
    t = (np.arange(n_samples) + 0.5) / n_samples  # [S]
    xy = segs[:, None, :2] + t[None, :, None] * (segs[:, None, 2:] - segs[:, None, :2])  # [N, S, 2]
    col = np.clip(np.floor(xy[..., 0]).astype(np.int64), 0, w - 1)  # COLMAP pixel -> index
    row = np.clip(np.floor(xy[..., 1]).astype(np.int64), 0, h - 1)
    return image[row, col].mean(axis=1).astype(np.float32)


def lbd_descriptors(gray: np.ndarray, segs: np.ndarray) -> np.ndarray:
    """LBD binary descriptors [N, 32] uint8 of segments [N, 4] on a uint8 image (OpenCV
    ``line_descriptor.BinaryDescriptor``); rows it cannot describe are all-zero."""
    out = np.zeros((len(segs), 32), np.uint8)
    if len(segs) == 0:
        return out
    kls = []
    for k, (x1, y1, x2, y2) in enumerate(segs - 0.5):  # COLMAP -> OpenCV pixel centres
        kl = cv2.line_descriptor.KeyLine()
        kl.startPointX, kl.startPointY, kl.endPointX, kl.endPointY = x1, y1, x2, y2
        kl.sPointInOctaveX, kl.sPointInOctaveY, kl.ePointInOctaveX, kl.ePointInOctaveY = x1, y1, x2, y2
        kl.lineLength = float(np.hypot(x2 - x1, y2 - y1))
        kl.numOfPixels = int(max(abs(x2 - x1), abs(y2 - y1))) + 1
        kl.angle = float(np.arctan2(y2 - y1, x2 - x1))
        kl.octave, kl.class_id, kl.size = 0, k, float(abs((x2 - x1) * (y2 - y1)))
        kl.pt = (float(x1 + x2) / 2, float(y1 + y2) / 2)
        kl.response = kl.lineLength / max(gray.shape)
        kls.append(kl)
    bd = cv2.line_descriptor.BinaryDescriptor.createBinaryDescriptor()
    kls_out, desc = bd.compute(gray, kls)
    if desc is not None and len(kls_out):
        ids = np.array([kl.class_id for kl in kls_out], np.int64)
        out[ids] = desc[:, :32]
    return out


def detect_image(image: np.ndarray, normal: np.ndarray | None, cfg: LineConfig) -> tuple[Segments2D, dict]:
    """Segments of one image [H, W, 3] float in [0, 1] (and its normal prior [H, W, 3] or None).
    Returns the segments and counts: rgb, normal (before merging), duplicates removed."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an RGB image [H, W, 3], got {image.shape}")
    h, w = image.shape[:2]
    gray = cv2.cvtColor((np.clip(image, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
    rgb_segs = detect_gray(gray, cfg)
    parts, sources = [rgb_segs], [np.full(len(rgb_segs), SOURCE_RGB, np.uint8)]
    n_normal = 0
    if normal is not None:
        if normal.shape != (h, w, 3):
            raise ValueError(f"normal prior has shape {normal.shape}, expected {(h, w, 3)}")
        nseg = [detect_gray(ch, cfg) for ch in normal_map_to_channels(normal)]
        nseg = np.concatenate(nseg) if nseg else np.zeros((0, 4))
        n_normal = len(nseg)
        parts.append(nseg)
        sources.append(np.full(len(nseg), SOURCE_NORMAL, np.uint8))
    segs, source = np.concatenate(parts), np.concatenate(sources)
    keep = dedup_segments(segs, cfg.dedup_angle_deg, cfg.px(cfg.dedup_dist_px, w), priority=source,
                          cross_dist_px=cfg.px(2.0 * cfg.dedup_dist_px, w))
    n_dup = len(segs) - len(keep)
    segs, source = segs[keep], source[keep]
    order = np.argsort(-segment_lengths(segs), kind="stable")[: 2 * cfg.max_segments]
    segs, source = segs[order], source[order]
    result = Segments2D(segs, source, lbd_descriptors(gray, segs), segment_colors(image, segs))
    return result, {"rgb": len(rgb_segs), "normal": n_normal, "duplicates": n_dup}


def cache_key(cfg: LineConfig, width: int, height: int, with_normals: bool, stamp: str = "") -> str:
    """Hash of everything that changes an image's 2D segments (``stamp``: the image's and its
    normal prior's file stamps, so a rewritten image is detected again)."""
    params = {"v": CACHE_VERSION, "files": stamp, "detector": cfg.detector, "min_length_px": cfg.min_length_px,
              "max_segments": cfg.max_segments, "dedup": [cfg.dedup_angle_deg, cfg.dedup_dist_px],
              "ref_w": cfg.reference_width, "size": [width, height], "normals": with_normals}
    return hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:12]


def _save_npz(path: Path, seg: Segments2D, counts: dict) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, segs=seg.segs, source=seg.source, desc=seg.desc, colors=seg.colors,
                 counts=np.array([counts["rgb"], counts["normal"], counts["duplicates"]]))


def detect_all(scene, cfg: LineConfig, cache_dir: Path | None = None) -> tuple[list[Segments2D], dict]:
    """2D segments of every image of ``scene``, cached per image under ``cache_dir/lines2d``.
    Returns the segments and per-image statistics (lists over images) for the report."""
    with_normals = cfg.use_normal_priors and scene.has_normal_priors
    out: list[Segments2D] = []
    stats = {"segments": [], "segments_rgb": [], "segments_normal": [], "duplicates_2d": [],
             "cached": 0}
    for cam in tqdm(scene.cameras, desc="lines: 2D segments", unit="img", leave=False):
        normal = scene.normal_prior(cam.index) if with_normals else None
        stamp = file_stamp(cam.image_path, scene.normal_prior_path(cam.index) if normal is not None else None)
        key = cache_key(cfg, cam.width, cam.height, normal is not None, stamp)
        path = None if cache_dir is None else Path(cache_dir) / "lines2d" / f"{cam.stem}_{key}.npz"
        if path is not None and path.is_file():
            with np.load(path) as z:
                seg = Segments2D(z["segs"], z["source"], z["desc"], z["colors"])
                counts = dict(zip(("rgb", "normal", "duplicates"), z["counts"].tolist()))
            stats["cached"] += 1
        else:
            seg, counts = detect_image(scene.load_image(cam.index), normal, cfg)
            if path is not None:
                _save_npz(path, seg, counts)
        if len(seg) == 0:
            log.info("lines: image %s has no 2D segments", cam.name)
        out.append(seg)
        stats["segments"].append(len(seg))
        stats["segments_rgb"].append(int(counts["rgb"]))
        stats["segments_normal"].append(int(counts["normal"]))
        stats["duplicates_2d"].append(int(counts["duplicates"]))
    return out, stats
