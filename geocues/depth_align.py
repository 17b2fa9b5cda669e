"""Depth alignment (paper §4.1, plane-like cues): fit each image's depth prior to the cues.

A monocular depth prior is right only up to an unknown per-image scale (and, for relative-depth
networks, shift). The paper estimates the scale by linear regression of the prior against the
depths of the line and SfM cues seen in the image; we fit scale *and* shift robustly
(:func:`fit_scale_shift`): a two-point RANSAC for a first guess, an occlusion check against that
guess (an anchor farther than the surface the prior sees is hidden behind it), then Huber IRLS.

A prior is either *depth* (z up to scale and shift) or *disparity* (inverse depth up to scale and
shift, as monocular estimators such as Depth-Anything and MiDaS write it): a disparity prior p is
fitted as 1/z = s·p + b, with the same RANSAC, occlusion check and Huber IRLS, its residuals measured
in metres. Each alignment records its ``kind``, so :meth:`DepthAlignment.apply` converts correctly.
Every fit is also compared with a fit of the other kind; a prior that the other kind explains much
better is flagged (``looks_like``), and ``geocues extract`` says so naming ``--prior-kind``.

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

from geocues.anchors import Anchors  # noqa: F401  (re-exported: its historical home)
from geocues.depth_warp import fit_warp, monomials, norm_uv
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
    """Fits that map the prior's median to less than this fraction of the anchors' median depth (for
    disparity: whose s · std(d) is below it times std(1/z)), or are not finite, are rejected as
    degenerate. Relative, so a prior in millimetres (scale ~ 1e-3) aligns as one in metres."""


PRIOR_KINDS = ("depth", "disparity")


@dataclass
class DepthAlignment:
    """Result for one image. kind "depth": aligned depth = s·p + b (b in metres); kind
    "disparity": aligned depth = 1 / (s·p + b) (b in 1/metres), p the prior as stored."""

    index: int  # camera index
    ok: bool
    reason: str = ""  # why it was skipped ("" when ok)
    kind: str = "depth"  # what the prior was fitted as: "depth" or "disparity" (see the class doc)
    scale: float = float("nan")
    shift: float = float("nan")  # metres (depth) or 1/metres (disparity)
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
    looks_like: str = ""  # the other kind when a fit of that kind explains the anchors much better
    inlier_share: float = float("nan")  # share of anchors within inlier_rel of this kind's fit
    rank_correlation: float = float("nan")  # Spearman of prior and anchor depth (inverse for disparity)
    other_inlier_share: float = float("nan")  # the same for a fit of the other kind (NaN: it failed)

    def apply(self, depth: np.ndarray, warp_max: float = 0.1) -> np.ndarray:
        """Aligned depth (s·d + b)·(1 + w(u, v)) -- 1 / (s·d + b)·(1 + w) for a disparity prior --,
        keeping 0 (invalid) where the prior is invalid (<= 0) or the result is <= 0. w is the warp
        correction (zero without one). ``depth`` is the prior as stored (disparity for that kind),
        possibly resized to another resolution (a downscaled training run): w is then evaluated at
        the centres of its pixels mapped into the image the fit was made on."""
        if not self.ok:
            raise ValueError(f"image {self.index}: no alignment ({self.reason})")
        if depth.ndim != 2:
            raise ValueError(f"depth must be [H, W], got shape {depth.shape}")
        out = _to_depth(depth, self.scale, self.shift, self.kind)
        if self.warp_degree > 0:
            h, w = depth.shape
            if self.width <= 0 or self.height <= 0 or abs(w / self.width - h / self.height) > 0.02 * w / self.width:
                raise ValueError(f"depth has shape {depth.shape}, not a resize of the "
                                 f"({self.height}, {self.width}) image the alignment was fit on")
            j, i = np.meshgrid((np.arange(w) + 0.5) * self.width / w, (np.arange(h) + 0.5) * self.height / h)
            A = monomials(*norm_uv(np.stack([j.ravel(), i.ravel()], 1), self.width, self.height),
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
        kind = kw.setdefault("kind", "depth")  # reports written before the kind was recorded: depth
        if kind not in PRIOR_KINDS:
            raise ValueError(f"alignment of image {kw.get('index')}: unknown prior kind {kind!r} "
                             f"(known: {', '.join(PRIOR_KINDS)})")
        return cls(**kw)


ALIGNMENTS_FILE = "depth_alignments.json"  # CUES/depth_alignments.json: what `splat train` reads


def write_alignments(out_dir: str | Path, per_image: list[dict], kind: str) -> Path:
    """CUES/depth_alignments.json: ``{"prior_kind": kind, "alignments": {image name: alignment}}``
    of the successful fits (the data a later stage reads travels in its own file; report.json is
    for people)."""
    from geocues.atomic import atomic_path

    rows = {row["name"]: row["alignment"] for row in per_image
            if row.get("alignment") and row["alignment"].get("ok") and "name" in row}
    path = Path(out_dir) / ALIGNMENTS_FILE
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"prior_kind": kind, "alignments": rows}, indent=1))
    return path


def load_alignments(cues: str | Path) -> dict[str, DepthAlignment]:
    """The successful per-image alignments of ``geocues extract``, keyed by image name, from
    CUES/depth_alignments.json (``cues`` is the folder or a file in it); cue folders written before
    that file existed are read from their report.json. Empty when the extract ran without priors."""
    return {name: DepthAlignment.from_dict(al) for name, al in _alignment_rows(cues)[0].items()}


def load_prior_kind(cues: str | Path, default: str = "depth") -> str:
    """What the extract took the depth priors for ("depth" / "disparity"); ``default`` if unrecorded."""
    return _alignment_rows(cues)[1] or default


def _alignment_rows(cues: str | Path) -> tuple[dict[str, dict], str | None]:
    path = Path(cues)
    folder = path if path.is_dir() or not path.suffix else path.parent  # CUES, or a file in it
    if (folder / ALIGNMENTS_FILE).is_file():
        data = json.loads((folder / ALIGNMENTS_FILE).read_text())
        return data.get("alignments", {}), data.get("prior_kind")
    report = folder / "report.json"
    if not report.is_file():
        raise FileNotFoundError(f"no {ALIGNMENTS_FILE} or report.json in {folder} "
                                "(run `geocues extract SCENE -o CUES` first)")
    data = json.loads(report.read_text())
    rows = {row["name"]: row["alignment"] for row in data.get("per_image", [])
            if row.get("alignment") and row["alignment"].get("ok") and "name" in row}
    return rows, data.get("prior_kind")


def _to_depth(d: np.ndarray, s: float, b: float, kind: str) -> np.ndarray:
    """Aligned depth of prior values d: s·d + b (depth), 1 / (s·d + b) (disparity; 0 where s·d + b
    <= 0, i.e. at or beyond infinity)."""
    if kind == "depth":
        return s * d + b
    w = s * d + b
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), 0.0)


def fit_scale_shift(d: np.ndarray, z: np.ndarray, cfg: DepthAlignConfig,
                    rng: np.random.Generator, kind: str = "depth") -> tuple[float, float, np.ndarray]:
    """Robust depth alignment (paper §4.1, "estimate a per-image depth scale by linear regression").

        depth:      (s, b) = argmin_{s, b} Σ_i ρ_δ(s · d_i + b − z_i)
        disparity:  (s, b) = argmin_{s, b} Σ_i ρ_δ(z_i² · (s · d_i + b − 1 / z_i))

    d: [N] prior values at the anchors' pixels, z: [N] the anchors' depths in the camera (metres);
    ρ_δ is the Huber loss with δ = huber_rel · median(z), minimised by IRLS from a two-point RANSAC
    start. A disparity residual is weighted by z² so that it is, to first order, the depth residual
    in metres: both kinds share thresholds. Anchors farther than (1 + inlier_rel) times the RANSAC
    surface are occluded and left out. With ``fit_shift`` False, b = 0 (the paper's scale-only
    regression). Returns (s, b, used [N]).
    """
    d = np.asarray(d, np.float64)
    z = np.asarray(z, np.float64)
    if kind not in PRIOR_KINDS:
        raise ValueError(f"unknown prior kind {kind!r} (known: {', '.join(PRIOR_KINDS)})")
    if d.shape != z.shape or d.ndim != 1:
        raise ValueError(f"d and z must be [N] of equal shape, got {d.shape} and {z.shape}")
    n = len(d)
    if n < 2:
        raise ValueError(f"need at least 2 anchors to fit, got {n}")
    y = z if kind == "depth" else 1.0 / z  # what the affine map of the prior predicts
    shift = cfg.fit_shift and np.std(d) > 0.02 * abs(np.mean(d))  # b is unobservable on a flat range
    tol = cfg.inlier_rel * z
    # a prior in any unit (millimetres: s ~ 1e-3): the scale floor is relative to the prior's values
    min_s = cfg.min_scale * np.median(z) / max(float(np.median(np.abs(d))), 1e-30) if kind == "depth" else 0.0

    # ---- two-point (one-point without shift) RANSAC: the hypothesis with the most inliers.
    best, best_count = (np.median(y / d), 0.0), -1
    for _ in range(cfg.ransac_iters):
        if shift:
            i, j = rng.choice(n, size=2, replace=False)
            if abs(d[i] - d[j]) < 1e-6 * max(abs(d[i]), 1e-6):
                continue
            s = (y[i] - y[j]) / (d[i] - d[j])
            b = y[i] - s * d[i]
        else:
            i = rng.integers(n)
            s, b = y[i] / d[i], 0.0
        if not (np.isfinite(s) and s > min_s):
            continue
        count = np.count_nonzero(np.abs(_to_depth(d, s, b, kind) - z) < tol)
        if count > best_count:
            best, best_count = (s, b), count
    s, b = best
    # ---- occlusion check: an anchor behind the surface seen by the prior is hidden there.
    used = (z - _to_depth(d, s, b, kind)) < tol
    if kind == "disparity":  # beyond infinity (0) is no surface: not an occluder either
        used &= _to_depth(d, s, b, kind) > 0
    # ---- Huber IRLS on the visible anchors.
    s, b = _refit(d, z, used, s, b, shift, cfg.huber_rel * float(np.median(z)), kind)
    return float(s), float(b), used


def _refit(d: np.ndarray, z: np.ndarray, used: np.ndarray, s: float, b: float, shift: bool,
           delta: float, kind: str) -> tuple[float, float]:
    """Huber IRLS of the prior's affine map to the depths z of the ``used`` anchors, residuals in
    metres (a disparity residual is weighted by z²)."""
    if kind == "depth":
        return _irls_affine(d, z, used, s, b, shift, delta)
    return _irls_affine(d, 1.0 / z, used, s, b, shift, delta, gain=z * z)


def _irls_affine(d: np.ndarray, z: np.ndarray, used: np.ndarray, s: float, b: float, shift: bool,
                 delta: float, gain: np.ndarray | None = None) -> tuple[float, float]:
    """Huber IRLS of z ≈ s d + b (b = 0 without ``shift``) over the ``used`` anchors from (s, b).
    ``gain`` [N]: each residual is multiplied by it before the Huber test and in the squares."""
    A = np.stack([d, np.ones_like(d)], axis=1) if shift else d[:, None]
    for _ in range(30):
        r = s * d + b - z
        if gain is not None:
            r = r * gain
        w = np.where(used, np.minimum(1.0, delta / np.maximum(np.abs(r), 1e-12)), 0.0)
        sw = np.sqrt(w) if gain is None else np.sqrt(w) * gain
        sol, *_ = np.linalg.lstsq(A * sw[:, None], z * sw, rcond=None)
        s_new, b_new = (float(sol[0]), float(sol[1])) if shift else (float(sol[0]), 0.0)
        done = abs(s_new - s) < 1e-9 * abs(s) + 1e-12 and abs(b_new - b) < 1e-9 * (1.0 if gain is None else
                                                                               abs(b) + 1e-12)
        s, b = s_new, b_new
        if done:
            break
    return s, b


def _degenerate(s: float, b: float, d: np.ndarray, z: np.ndarray, kind: str, cfg: DepthAlignConfig) -> bool:
    """A fit that cannot be a depth map: non-finite, or its scale too small for the prior's unit (for
    depth, s · median|d| / median z, 1 for a prior in metres or millimetres alike; for disparity,
    s · std(d) / std(1/z), 1 for an exact fit, ~0 for a flat one), below ``cfg.min_scale``."""
    if not (np.isfinite(s) and np.isfinite(b)):
        return True
    if kind == "depth":  # an absolute floor of 1e-3 dropped 9 of 24 views of millimetre priors (s ~ 0.000999)
        return not (s > 0 and s * np.median(np.abs(d)) > cfg.min_scale * np.median(z))
    return not (s > 0 and s * np.std(d) >= cfg.min_scale * np.std(1.0 / z))


def _inlier_share(d: np.ndarray, z: np.ndarray, s: float, b: float, kind: str, cfg: DepthAlignConfig) -> float:
    return float(np.mean(np.abs(_to_depth(d, s, b, kind) - z) < cfg.inlier_rel * z))


def _edge_mask(depth: np.ndarray, radius: int, rel: float) -> np.ndarray:
    """[H, W] True where the prior has a depth discontinuity (or an invalid pixel) within radius."""
    import cv2

    k = 2 * max(radius, 0) + 1
    big = np.where(depth > 0, depth, np.float32(1e9)).astype(np.float32)
    lo = cv2.erode(big, np.ones((k, k), np.uint8))
    hi = cv2.dilate(depth.astype(np.float32), np.ones((k, k), np.uint8))
    return (lo >= 1e9) | (hi > (1.0 + rel) * lo)


def kind_warning(fits: list[DepthAlignment], scene_json: Path, inlier_rel: float) -> str | None:
    """One line naming ``--prior-kind`` when the priors of at least half of the images that were
    fitted look like the other kind (``looks_like``); None otherwise."""
    fitted = [a for a in fits if a.n_anchors >= 2 and np.isfinite(a.inlier_share)]
    odd = [a for a in fitted if a.looks_like]
    if not odd or 2 * len(odd) < len(fitted):
        return None
    kind, other = odd[0].kind, odd[0].looks_like
    failed = sum(not a.ok for a in odd)
    share = float(np.median([a.other_inlier_share for a in odd]))
    return (f"the depth priors of {len(odd)} of {len(fitted)} images look like {other}, not {kind}: a {other} "
            f"fit keeps a median {share:.0%} of their anchors within {inlier_rel:.0%} of depth, the {kind} fit "
            + (f"failed on {failed} of them" if failed else "keeps fewer")
            + f"; pass --prior-kind {other} or set {{\"priors\": {{\"depth_kind\": \"{other}\"}}}} in {scene_json}")


MIN_RANK_CORRELATION = 0.2
"""A prior is fitted only where its values at the anchors rank with their depths at least this well
(Spearman; disparity ranks inversely). Measured on a benchmark room's views: exact 1.0, 10 % per-pixel
noise 0.72-0.92, a 15 % warp 0.61-0.97, 30 % noise 0.31-0.64; transposed -0.03-0.29, shuffled
-0.12-0.13, constant undefined (these 'aligned' at a 78 % median residual and fed the anchored term)."""


def _rank_correlation(d: np.ndarray, z: np.ndarray) -> float:
    """Spearman's rank correlation of ``d`` and ``z`` (ties share their average rank: a coarsely
    quantised prior; NaN when either is constant)."""
    from scipy.stats import rankdata

    if np.ptp(d) == 0 or np.ptp(z) == 0:
        return float("nan")
    return float(np.corrcoef(rankdata(d), rankdata(z))[0, 1])


def _compare_kinds(res: DepthAlignment, d: np.ndarray, z: np.ndarray, s: float, b: float,
                   cfg: DepthAlignConfig, seed: int) -> None:
    """Fit the prior as the other kind too (its own random stream: this kind's fit is unchanged)
    and flag it (``res.looks_like``) when that fit keeps at least half of the anchors within
    inlier_rel and a quarter more of them than this kind's fit (a failed fit keeps none)."""
    other = "disparity" if res.kind == "depth" else "depth"
    res.inlier_share = 0.0 if _degenerate(s, b, d, z, res.kind, cfg) else _inlier_share(d, z, s, b, res.kind, cfg)
    so, bo, _ = fit_scale_shift(d, z, cfg, np.random.default_rng([seed, 1]), other)
    if not _degenerate(so, bo, d, z, other, cfg):
        res.other_inlier_share = _inlier_share(d, z, so, bo, other, cfg)
        if res.other_inlier_share >= max(0.5, res.inlier_share + 0.25):
            res.looks_like = other


def align_depth_prior(cam: Camera, depth: np.ndarray, anchors_xyz: np.ndarray,
                      cfg: DepthAlignConfig, seed: int = 0, kind: str = "depth",
                      measured: np.ndarray | None = None) -> DepthAlignment:
    """Fit ``depth`` [H, W] (prior of camera ``cam``, z-depth or, with ``kind`` "disparity",
    inverse depth; <= 0 = invalid) to the anchors ``anchors_xyz`` [P, 3] (world, metres) that may be
    visible in it. ``measured`` [P] bool: the anchors this view measured (SfM points, 3D line
    samples); where at least ``cfg.min_anchors`` of them are usable, the fit and its rank test take
    only those (default all). `--floor.lines`' floor samples are hidden behind furniture in many
    views (40-87 % of the anchors of a held-out room's views): the rank test said 0.12-0.20 of exact
    priors (0.84-0.97 at the measured anchors) and one fit came out with a negative scale. Never
    raises on too little data: returns ``ok=False`` with a reason."""
    if kind not in PRIOR_KINDS:
        raise ValueError(f"unknown prior kind {kind!r} (known: {', '.join(PRIOR_KINDS)})")
    if depth.shape != (cam.height, cam.width):
        raise ValueError(f"depth prior of {cam.name} has shape {depth.shape}, expected "
                         f"({cam.height}, {cam.width})")
    X = np.asarray(anchors_xyz, np.float64).reshape(-1, 3)
    res = DepthAlignment(index=cam.index, ok=False, kind=kind)
    rej: dict[str, int] = {}
    uv, z = cam.project(X)
    front = z > 1e-6
    rej["behind_camera"] = int(np.sum(~front))
    inside = front & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) \
        & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    rej["outside_image"] = int(np.sum(front & ~inside))
    uv, z = uv[inside], z[inside]
    if measured is not None and np.shape(measured) != (len(X),):
        raise ValueError(f"measured must be [P] = [{len(X)}] bools (one per anchor), got shape {np.shape(measured)}")
    ours = np.ones(len(X), bool) if measured is None else np.asarray(measured, bool)
    ours = ours[inside]
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
    d, z, uv, ours = d[keep], z[keep], uv[keep], ours[keep]
    if ours.sum() >= max(cfg.min_anchors, 2) and not ours.all():  # enough measured ones: those only
        rej["not_measured"] = int((~ours).sum())
        d, z, uv = d[ours], z[ours], uv[ours]
    rng = np.random.default_rng(seed + cam.index)
    if len(d) > cfg.max_anchors:
        sel = rng.choice(len(d), size=cfg.max_anchors, replace=False)
        rej["subsampled"] = len(d) - cfg.max_anchors
        d, z, uv = d[sel], z[sel], uv[sel]
    res.rejected, res.n_anchors = rej, len(d)
    res.width, res.height = cam.width, cam.height
    if len(d) < max(cfg.min_anchors, 2):
        res.reason = f"too few anchors ({len(d)} < {cfg.min_anchors})"
        share = float(np.mean(depth > 0)) if depth.size else 0.0  # the prior itself: empty, or mostly <= 0?
        if share < 0.5:
            negative = float(np.mean(depth < 0)) if depth.size else 0.0
            res.reason += (f": the prior has valid (positive, finite) depth in {100 * share:.0f}% of its pixels"
                           + (f", {100 * negative:.0f}% negative (negated?)" if negative > 0.1 else ""))
        return res
    spread = float((np.percentile(z, 90) - np.percentile(z, 10)) / np.median(z))
    if cfg.fit_shift and spread < cfg.min_depth_spread:  # scale and shift are not separable
        res.reason = f"anchor depths too narrow to fit a shift (spread {spread:.3f} < {cfg.min_depth_spread})"
        return res
    s, b, used = fit_scale_shift(d, z, cfg, rng, kind)
    _compare_kinds(res, d, z, s, b, cfg, seed + cam.index)
    rho = _rank_correlation(d, z) * (-1.0 if kind == "disparity" else 1.0)
    res.rank_correlation = rho
    if not rho >= MIN_RANK_CORRELATION:  # NaN: a constant prior
        res.reason = (f"the prior does not follow the scene's depth (rank correlation {rho:.2f} < "
                      f"{MIN_RANK_CORRELATION} at its {len(d)} anchors, their depths spread {100 * spread:.0f} %): another "
                      f"view's prior, a constant one, {'depth' if kind == 'disparity' else 'disparity'} "
                      "(--prior-kind), or a view too flat to tell")
        return res
    if _degenerate(s, b, d, z, kind, cfg):
        res.reason = f"degenerate fit (scale {s:.4g}, shift {b:.4g})"
        return res
    base = _to_depth(d, s, b, kind)  # [N] affine-aligned prior at the anchors, metres
    tol = cfg.inlier_rel * z
    res.residual_affine_median_m = float(np.median(np.abs(base - z)[(z - base) < tol]))
    x, y = norm_uv(uv, cam.width, cam.height)
    degree = cfg.warp_degree
    while degree > 0 and (len(d) < 15 * len(monomials(x[:1], y[:1], degree).ravel())
                          or min(np.std(x), np.std(y)) < 0.15 * degree):
        degree -= 1  # too few anchors, or too clustered in the image, for this degree
    warp = np.zeros(len(d))
    coeffs = np.zeros(0)
    if degree > 0:  # z = (s d + b)(1 + w): alternate the warp fit and the affine refit
        shift = cfg.fit_shift
        for _ in range(4):  # each round also redoes the occlusion check with the corrected depth
            vis = (z - base * (1.0 + warp)) < tol
            coeffs = fit_warp(x[vis], y[vis], z[vis] / base[vis], degree, cfg)
            warp = np.clip(monomials(x, y, degree) @ coeffs, -cfg.warp_max, cfg.warp_max)
            s, b = _refit(d, z / (1.0 + warp), vis, s, b, shift, cfg.huber_rel * float(np.median(z)), kind)
            base = _to_depth(d, s, b, kind)
        if _degenerate(s, b, d, z, kind, cfg):
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
