"""Depth alignment (paper §4.1, plane-like cues): fit each image's depth prior to the cues.

A monocular depth prior is right only up to an unknown per-image scale (and, for relative-depth
networks, shift). The paper estimates the scale by linear regression of the prior against the
depths of the line and SfM cues seen in the image; we fit scale *and* shift robustly
(:func:`fit_scale_shift`): a two-point RANSAC for a first guess, an occlusion check against that
guess (an anchor farther than the surface the prior sees is hidden behind it), then Huber IRLS.

Anchors that fall on depth discontinuities of the prior are not used (the prior is blurred there
and a line cue on an occluding edge may belong to either side). Images with too few anchors are
skipped with the reason; every per-image result carries residuals (metres) for ``report.json``.
"""

from __future__ import annotations

import logging
import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from geocues.scene import Camera

log = logging.getLogger(__name__)


@dataclass
class DepthAlignConfig:
    """Robust scale-and-shift fit of each depth prior to the projected line and SfM cues."""

    min_anchors: int = 20
    """Skip an image whose prior has fewer usable anchor points than this."""
    max_anchors: int = 4000
    """Use at most this many anchors per image (a fixed random subset; speed)."""
    fit_shift: bool = True
    """Fit scale and shift (True) or scale only (False, as in the paper)."""
    ransac_iters: int = 200
    """Two-point RANSAC iterations for the initial fit."""
    inlier_rel: float = 0.03
    """RANSAC inlier threshold and occlusion tolerance, as a fraction of the anchor's depth."""
    min_depth_spread: float = 0.1
    """With fit_shift, skip images whose anchor depths span less than this (p90 - p10) / median."""
    huber_rel: float = 0.01
    """Huber threshold of the IRLS refinement, as a fraction of the median anchor depth."""
    edge_rel: float = 0.05
    """An anchor is on a depth edge if the prior's max/min over edge_px around it exceeds 1 + this."""
    edge_px: int = 2
    """Radius in pixels (at 640 px width) of the depth-edge test."""
    warp_degree: int = 0
    """Degree of a 2D polynomial correction of the prior's low-frequency warp (0 = off; see docs)."""
    warp_max: float = 0.1
    """Clamp that correction to +- this fraction of the depth."""
    warp_ridge: float = 1e-3
    """Ridge weight of the correction's coefficients (keeps it flat where anchors are few)."""
    min_scale: float = 1e-3
    """Fits with a scale below this (or not finite) are rejected as degenerate."""


@dataclass
class DepthAlignment:
    """Result for one image."""

    index: int  # camera index
    ok: bool
    reason: str = ""  # why it was skipped ("" when ok)
    scale: float = float("nan")
    shift: float = float("nan")  # metres
    n_candidates: int = 0  # anchors projected into the image in front of the camera
    n_anchors: int = 0  # anchors used in the fit (after edge / invalid-prior tests)
    n_inliers: int = 0  # anchors within the inlier threshold of the final fit
    n_occluded: int = 0  # anchors behind the aligned surface (occlusion check)
    warp_degree: int = 0  # degree of the warp correction used (0 = none)
    warp_coeffs: list[float] = field(default_factory=list)  # its monomial coefficients
    width: int = 0
    height: int = 0
    residual_affine_median_m: float = float("nan")  # median |residual| before the warp correction
    residual_median_m: float = float("nan")  # median |z_anchor - aligned depth|, non-occluded anchors
    residual_p90_m: float = float("nan")
    residual_rel_median: float = float("nan")  # median |r| / z_anchor
    rejected: dict[str, int] = field(default_factory=dict)  # reason -> anchors not used

    def apply(self, depth: np.ndarray, warp_max: float = 0.1) -> np.ndarray:
        """Aligned depth (s·d + b)·(1 + w(u, v)), keeping 0 (invalid) where the prior is invalid or
        the result is <= 0. w is the warp correction (zero without one). ``depth`` may be the prior
        resized to another resolution (a downscaled training run): w is then evaluated at the
        centres of its pixels mapped into the image the fit was made on."""
        if not self.ok:
            raise ValueError(f"image {self.index}: no alignment ({self.reason})")
        if depth.ndim != 2:
            raise ValueError(f"depth must be [H, W], got shape {depth.shape}")
        out = self.scale * depth + self.shift
        if self.warp_degree > 0:
            h, w = depth.shape
            if self.width <= 0 or self.height <= 0 or abs(w / self.width - h / self.height) > 0.02 * w / self.width:
                raise ValueError(f"depth has shape {depth.shape}, not a resize of the "
                                 f"({self.height}, {self.width}) image the alignment was fit on")
            j, i = np.meshgrid((np.arange(w) + 0.5) * self.width / w, (np.arange(h) + 0.5) * self.height / h)
            A = _monomials(*_norm_uv(np.stack([j.ravel(), i.ravel()], 1), self.width, self.height),
                           self.warp_degree)
            w = np.clip(A @ np.asarray(self.warp_coeffs), -warp_max, warp_max).reshape(depth.shape)
            out = out * (1.0 + w)
        return np.where((depth > 0) & (out > 0), out, 0.0).astype(np.float32)

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "DepthAlignment":
        """Inverse of :meth:`to_dict` (None back to NaN; unknown keys ignored)."""
        names = {f.name: f for f in fields(cls)}
        kw = {k: (float("nan") if v is None and isinstance(names[k].default, float) else v)
              for k, v in d.items() if k in names}
        return cls(**kw)


def load_alignments(report: str | Path) -> dict[str, DepthAlignment]:
    """The successful per-image alignments recorded by ``geocues extract`` in CUES/report.json
    (``report`` is that file or its folder), keyed by image name. Empty when the extract ran
    without priors or its depth-alignment stage was off."""
    path = Path(report)
    path = path / "report.json" if path.is_dir() else path
    if not path.is_file():
        raise FileNotFoundError(f"no cue report at {path} (run `geocues extract SCENE -o CUES` first)")
    rows = json.loads(path.read_text()).get("per_image", [])
    out = {}
    for row in rows:
        al = row.get("alignment")
        if al and al.get("ok") and "name" in row:
            out[row["name"]] = DepthAlignment.from_dict(al)
    return out


@dataclass
class Anchors:
    """3D cue points (line samples and SfM points) that anchor depth priors and prior-free planes."""

    xyz: np.ndarray  # [P, 3] world, metres
    cue_type: np.ndarray  # [P] uint8 CueType
    group: np.ndarray  # [P] int64: line index for line samples, -1 - point index for SfM points
    views: dict[int, np.ndarray] = field(default_factory=dict)  # camera -> anchors known visible
    unknown: np.ndarray | None = None  # [P] bool: visibility unknown, test by projection in all views

    def __post_init__(self) -> None:
        p = len(self.xyz)
        self.xyz = np.asarray(self.xyz, np.float64).reshape(p, 3)
        if self.cue_type.shape != (p,) or self.group.shape != (p,):
            raise ValueError(f"anchors: cue_type {self.cue_type.shape} / group {self.group.shape} "
                             f"do not match xyz ({p}, 3)")
        if self.unknown is None:
            self.unknown = np.zeros(p, bool)

    def __len__(self) -> int:
        return len(self.xyz)

    def candidates(self, cam_index: int) -> np.ndarray:
        """Indices of anchors that may be seen by camera ``cam_index``: its known-visible anchors
        plus every anchor whose visibility is unknown."""
        known = self.views.get(cam_index, np.zeros(0, np.int64))
        return np.union1d(known, np.flatnonzero(self.unknown)).astype(np.int64)

    @staticmethod
    def build(sfm_xyz: np.ndarray | None = None, sfm_views: dict[int, np.ndarray] | None = None,
              line_points: np.ndarray | None = None, line_of_point: np.ndarray | None = None,
              line_views: list[np.ndarray] | None = None) -> "Anchors":
        """Anchors from SfM cues (``sfm_views``: camera -> row indices into ``sfm_xyz``; empty or
        None = unknown visibility) and line samples (``line_views[l]``: cameras supporting line l)."""
        from geocues.types import CueType

        parts_xyz, parts_type, parts_group, parts_unknown = [], [], [], []
        views: dict[int, list[np.ndarray]] = {}
        off = 0
        if sfm_xyz is not None and len(sfm_xyz):
            n = len(sfm_xyz)
            parts_xyz.append(np.asarray(sfm_xyz, np.float64).reshape(n, 3))
            parts_type.append(np.full(n, int(CueType.SFM), np.uint8))
            parts_group.append(-1 - np.arange(n, dtype=np.int64))
            has = bool(sfm_views) and any(len(v) for v in sfm_views.values())
            parts_unknown.append(np.full(n, not has))
            for cam, idx in (sfm_views or {}).items():
                views.setdefault(cam, []).append(np.asarray(idx, np.int64) + off)
            off += n
        if line_points is not None and len(line_points):
            n = len(line_points)
            lp = np.asarray(line_of_point, np.int64).reshape(n)
            parts_xyz.append(np.asarray(line_points, np.float64).reshape(n, 3))
            parts_type.append(np.full(n, int(CueType.LINE), np.uint8))
            parts_group.append(lp)
            parts_unknown.append(np.full(n, line_views is None))
            if line_views is not None:
                order = np.argsort(lp, kind="stable")
                starts = np.searchsorted(lp[order], np.arange(len(line_views) + 1))
                for li, cams in enumerate(line_views):
                    pts = order[starts[li]:starts[li + 1]] + off
                    for cam in np.asarray(cams, np.int64):
                        views.setdefault(int(cam), []).append(pts)
            off += n
        if not parts_xyz:
            return Anchors(np.zeros((0, 3)), np.zeros(0, np.uint8), np.zeros(0, np.int64))
        return Anchors(np.concatenate(parts_xyz), np.concatenate(parts_type),
                       np.concatenate(parts_group),
                       {c: np.unique(np.concatenate(v)) for c, v in views.items()},
                       np.concatenate(parts_unknown))


def _norm_uv(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates -> isotropic coordinates centred on the image, x in [-1, 1]."""
    half = width / 2.0
    return (uv[:, 0] - half) / half, (uv[:, 1] - height / 2.0) / half


def _monomials(x: np.ndarray, y: np.ndarray, degree: int) -> np.ndarray:
    """[N, T] monomials x^a y^b with 1 <= a + b <= degree (no constant: the affine fit has it)."""
    cols = [x ** a * y ** (k - a) for k in range(1, degree + 1) for a in range(k, -1, -1)]
    return np.stack(cols, axis=1) if cols else np.zeros((len(x), 0))


def fit_warp(x: np.ndarray, y: np.ndarray, ratio: np.ndarray, degree: int, cfg: "DepthAlignConfig"
             ) -> np.ndarray:
    """Smooth warp correction of an aligned prior (our addition for low-frequency prior errors).

        z_i / (s·d_i + b) − 1 ≈ w(x_i, y_i) = Σ_{1 ≤ a+b ≤ D} c_ab x_i^a y_i^b

    fitted by Huber IRLS (δ = huber_rel) with a ridge penalty ``warp_ridge`` · N · ‖c‖². x, y: [N]
    normalised image coordinates of the anchors, ratio: [N] z / (s d + b). Returns c [T]."""
    A = _monomials(x, y, degree)
    e = ratio - 1.0
    c = np.zeros(A.shape[1])
    lam = cfg.warp_ridge * len(e)
    for _ in range(10):
        r = A @ c - e
        w = np.minimum(1.0, cfg.huber_rel / np.maximum(np.abs(r), 1e-12))
        Aw = A * w[:, None]
        c_new = np.linalg.solve(A.T @ Aw + lam * np.eye(A.shape[1]), Aw.T @ e)
        if np.max(np.abs(c_new - c)) < 1e-7:
            c = c_new
            break
        c = c_new
    return c


def fit_scale_shift(d: np.ndarray, z: np.ndarray, cfg: DepthAlignConfig,
                    rng: np.random.Generator) -> tuple[float, float, np.ndarray]:
    """Robust depth alignment (paper §4.1, "estimate a per-image depth scale by linear regression").

        (s, b) = argmin_{s, b} Σ_i ρ_δ(s · d_i + b − z_i)

    d: [N] prior depths at the anchors' pixels, z: [N] the anchors' depths in the camera (metres);
    ρ_δ is the Huber loss with δ = huber_rel · median(z), minimised by IRLS from a two-point RANSAC
    start. Anchors farther than (1 + inlier_rel) times the RANSAC surface are occluded and left out.
    With ``fit_shift`` False, b = 0 (the paper's scale-only regression). Returns (s, b, used [N]).
    """
    d = np.asarray(d, np.float64)
    z = np.asarray(z, np.float64)
    if d.shape != z.shape or d.ndim != 1:
        raise ValueError(f"d and z must be [N] of equal shape, got {d.shape} and {z.shape}")
    n = len(d)
    if n < 2:
        raise ValueError(f"need at least 2 anchors to fit, got {n}")
    shift = cfg.fit_shift and np.std(d) > 0.02 * np.mean(d)  # b is unobservable on a flat range
    tol = cfg.inlier_rel * z

    # ---- two-point (one-point without shift) RANSAC: the hypothesis with the most inliers.
    best, best_count = (np.median(z / d), 0.0), -1
    for _ in range(cfg.ransac_iters):
        if shift:
            i, j = rng.choice(n, size=2, replace=False)
            if abs(d[i] - d[j]) < 1e-6 * max(d[i], 1e-6):
                continue
            s = (z[i] - z[j]) / (d[i] - d[j])
            b = z[i] - s * d[i]
        else:
            i = rng.integers(n)
            s, b = z[i] / d[i], 0.0
        if not (np.isfinite(s) and s > cfg.min_scale):
            continue
        count = np.count_nonzero(np.abs(s * d + b - z) < tol)
        if count > best_count:
            best, best_count = (s, b), count
    s, b = best
    # ---- occlusion check: an anchor behind the surface seen by the prior is hidden there.
    used = (z - (s * d + b)) < tol
    # ---- Huber IRLS on the visible anchors.
    s, b = _irls_affine(d, z, used, s, b, shift, cfg.huber_rel * float(np.median(z)))
    return float(s), float(b), used


def _irls_affine(d: np.ndarray, z: np.ndarray, used: np.ndarray, s: float, b: float, shift: bool,
                 delta: float) -> tuple[float, float]:
    """Huber IRLS of z ≈ s d + b (b = 0 without ``shift``) over the ``used`` anchors from (s, b)."""
    A = np.stack([d, np.ones_like(d)], axis=1) if shift else d[:, None]
    for _ in range(30):
        r = s * d + b - z
        w = np.where(used, np.minimum(1.0, delta / np.maximum(np.abs(r), 1e-12)), 0.0)
        sw = np.sqrt(w)
        sol, *_ = np.linalg.lstsq(A * sw[:, None], z * sw, rcond=None)
        s_new, b_new = (float(sol[0]), float(sol[1])) if shift else (float(sol[0]), 0.0)
        done = abs(s_new - s) < 1e-9 * abs(s) + 1e-12 and abs(b_new - b) < 1e-9
        s, b = s_new, b_new
        if done:
            break
    return s, b


def _edge_mask(depth: np.ndarray, radius: int, rel: float) -> np.ndarray:
    """[H, W] True where the prior has a depth discontinuity (or an invalid pixel) within radius."""
    import cv2

    k = 2 * max(radius, 0) + 1
    big = np.where(depth > 0, depth, np.float32(1e9)).astype(np.float32)
    lo = cv2.erode(big, np.ones((k, k), np.uint8))
    hi = cv2.dilate(depth.astype(np.float32), np.ones((k, k), np.uint8))
    return (lo >= 1e9) | (hi > (1.0 + rel) * lo)


def align_depth_prior(cam: Camera, depth: np.ndarray, anchors_xyz: np.ndarray,
                      cfg: DepthAlignConfig, seed: int = 0) -> DepthAlignment:
    """Fit ``depth`` [H, W] (prior of camera ``cam``) to the anchors ``anchors_xyz`` [P, 3] (world,
    metres) that may be visible in it. Never raises on too little data: returns ``ok=False`` with a
    reason."""
    if depth.shape != (cam.height, cam.width):
        raise ValueError(f"depth prior of {cam.name} has shape {depth.shape}, expected "
                         f"({cam.height}, {cam.width})")
    X = np.asarray(anchors_xyz, np.float64).reshape(-1, 3)
    res = DepthAlignment(index=cam.index, ok=False)
    rej: dict[str, int] = {}
    uv, z = cam.project(X)
    front = z > 1e-6
    rej["behind_camera"] = int(np.sum(~front))
    inside = front & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) \
        & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    rej["outside_image"] = int(np.sum(front & ~inside))
    uv, z = uv[inside], z[inside]
    res.n_candidates = len(z)
    cols = np.minimum(uv[:, 0].astype(np.int64), cam.width - 1)  # COLMAP: pixel j covers [j, j+1)
    rows = np.minimum(uv[:, 1].astype(np.int64), cam.height - 1)
    d = depth[rows, cols].astype(np.float64)
    valid = d > 0
    rej["invalid_prior"] = int(np.sum(~valid))
    radius = int(round(cfg.edge_px * cam.width / 640.0))
    on_edge = valid & _edge_mask(depth, radius, cfg.edge_rel)[rows, cols]
    rej["depth_edge"] = int(on_edge.sum())
    keep = valid & ~on_edge
    d, z, uv = d[keep], z[keep], uv[keep]
    rng = np.random.default_rng(seed + cam.index)
    if len(d) > cfg.max_anchors:
        sel = rng.choice(len(d), size=cfg.max_anchors, replace=False)
        rej["subsampled"] = len(d) - cfg.max_anchors
        d, z, uv = d[sel], z[sel], uv[sel]
    res.rejected, res.n_anchors = rej, len(d)
    res.width, res.height = cam.width, cam.height
    if len(d) < max(cfg.min_anchors, 2):
        res.reason = f"too few anchors ({len(d)} < {cfg.min_anchors})"
        return res
    spread = float((np.percentile(z, 90) - np.percentile(z, 10)) / np.median(z))
    if cfg.fit_shift and spread < cfg.min_depth_spread:  # scale and shift are not separable
        res.reason = f"anchor depths too narrow to fit a shift (spread {spread:.3f} < {cfg.min_depth_spread})"
        return res
    s, b, used = fit_scale_shift(d, z, cfg, rng)
    if not (np.isfinite(s) and np.isfinite(b) and s > cfg.min_scale):
        res.reason = f"degenerate fit (scale {s:.4g}, shift {b:.4g})"
        return res
    base = s * d + b  # [N] affine-aligned prior at the anchors
    tol = cfg.inlier_rel * z
    res.residual_affine_median_m = float(np.median(np.abs(base - z)[(z - base) < tol]))
    x, y = _norm_uv(uv, cam.width, cam.height)
    degree = cfg.warp_degree
    while degree > 0 and (len(d) < 15 * len(_monomials(x[:1], y[:1], degree).ravel())
                          or min(np.std(x), np.std(y)) < 0.15 * degree):
        degree -= 1  # too few anchors, or too clustered in the image, for this degree
    warp = np.zeros(len(d))
    coeffs = np.zeros(0)
    if degree > 0:  # z = (s d + b)(1 + w): alternate the warp fit and the affine refit
        shift = cfg.fit_shift
        for _ in range(4):  # each round also redoes the occlusion check with the corrected depth
            vis = (z - base * (1.0 + warp)) < tol
            coeffs = fit_warp(x[vis], y[vis], z[vis] / base[vis], degree, cfg)
            warp = np.clip(_monomials(x, y, degree) @ coeffs, -cfg.warp_max, cfg.warp_max)
            s, b = _irls_affine(d, z / (1.0 + warp), vis, s, b, shift, cfg.huber_rel * float(np.median(z)))
            base = s * d + b
        if not (np.isfinite(s) and s > cfg.min_scale):
            res.reason = f"degenerate fit with the warp correction (scale {s:.4g})"
            return res
    r = base * (1.0 + warp) - z
    occluded = -r > tol  # anchor farther than the aligned surface
    vis = ~occluded
    if vis.sum() < max(cfg.min_anchors, 2):
        res.reason = f"too few visible anchors after the occlusion check ({int(vis.sum())})"
        return res
    a = np.abs(r[vis])
    res.ok, res.scale, res.shift = True, s, b
    res.warp_degree, res.warp_coeffs = degree, [float(c) for c in coeffs]
    res.n_occluded = int(occluded.sum())
    res.n_inliers = int(np.sum(np.abs(r) < tol))
    res.residual_median_m = float(np.median(a))
    res.residual_p90_m = float(np.percentile(a, 90))
    res.residual_rel_median = float(np.median(a / z[vis]))
    return res
