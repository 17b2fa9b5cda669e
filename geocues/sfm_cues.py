"""SfM cues (paper §4.1, "SfM points"): the model's 3D points after statistical outlier removal.

The paper keeps the SfM points whose mean distance to their K nearest neighbours is not abnormally
high; Open3D's ``remove_statistical_outlier`` implements exactly that rule (see
:func:`statistical_outlier_mask`). Optional pre-filters on reprojection error and track length
are off by default. Every removed point is counted under a reason for ``report.json``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from geocues.cue_io import CueCloud
from geocues.scene import Points3D
from geocues.types import CueType

log = logging.getLogger(__name__)


@dataclass
class SfmCueConfig:
    """Statistical outlier removal of the SfM points."""

    sor_neighbors: int = 20
    """K: number of nearest neighbours whose mean distance is tested (Open3D nb_neighbors)."""
    sor_std_ratio: float = 2.0
    """Drop points whose mean K-NN distance exceeds the mean over all points by this many std."""
    max_reproj_error: float = 0.0
    """Drop points with a mean reprojection error above this many pixels first (0 = off)."""
    min_track_length: int = 0
    """Drop points seen in fewer images first (0 = off; models written without tracks have 0)."""


@dataclass
class SfmCues:
    """Result of the SfM cue stage."""

    cloud: CueCloud  # SFM-typed points that survived, confidence = 1 / (1 + reprojection error)
    kept: np.ndarray  # [M] indices into the scene's Points3D
    n_input: int
    removed: dict[str, int] = field(default_factory=dict)  # reason -> count
    sor_threshold: float = float("nan")  # the mean-K-NN-distance cut-off actually used, metres

    @property
    def n_removed(self) -> int:
        return int(sum(self.removed.values()))


def statistical_outlier_mask(xyz: np.ndarray, nb_neighbors: int, std_ratio: float
                             ) -> tuple[np.ndarray, float]:
    """Statistical outlier removal (paper §4.1), via Open3D ``remove_statistical_outlier``.

        d̄_i = (1/K) Σ_{j ∈ kNN(i)} ‖p_i − p_j‖,   keep p_i  ⇔  d̄_i ≤ μ(d̄) + r · σ(d̄)

    with K = ``nb_neighbors`` and r = ``std_ratio``. xyz: [N, 3] metres. Returns (keep mask [N] bool,
    the threshold μ + rσ in metres, recomputed here for the report). With N ≤ K nothing is removed
    (the statistic is undefined) and the threshold is NaN.
    """
    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be [N, 3], got shape {xyz.shape}")
    if nb_neighbors < 1:
        raise ValueError(f"nb_neighbors must be >= 1, got {nb_neighbors}")
    if std_ratio <= 0:
        raise ValueError(f"std_ratio must be > 0, got {std_ratio}")
    n = len(xyz)
    if n <= nb_neighbors:
        return np.ones(n, bool), float("nan")
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(points=o3d.utility.Vector3dVector(xyz))
    _, keep_idx = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    keep = np.zeros(n, bool)
    keep[np.asarray(keep_idx, np.int64)] = True
    # The same statistic for the report (Open3D does not return it): K-NN mean distances.
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xyz).query(xyz, k=nb_neighbors + 1)
    mean_d = d[:, 1:].mean(axis=1)
    thr = float(mean_d.mean() + std_ratio * mean_d.std(ddof=1))
    return keep, thr


def extract_sfm_cues(points: Points3D, cfg: SfmCueConfig) -> SfmCues:
    """Filter the scene's SfM points into SFM cues. An empty model gives an empty result (and a
    reason in ``removed``), never an error."""
    n = len(points)
    if n == 0:
        log.warning("SfM cues: the model has no 3D points; no SFM cues (`geocues sfm` triangulates them; when it ran and found none, its warning says why)")
        return SfmCues(CueCloud.empty(), np.zeros(0, np.int64), 0, {"empty_model": 0})
    xyz = np.asarray(points.xyz, np.float64)
    if xyz.shape != (n, 3):
        raise ValueError(f"points.xyz has shape {xyz.shape}, expected ({n}, 3)")
    keep = np.all(np.isfinite(xyz), axis=1)
    removed = {"non_finite": int(np.sum(~keep))}
    if cfg.max_reproj_error > 0:
        bad = keep & (points.error > cfg.max_reproj_error)
        removed["reproj_error"] = int(bad.sum())
        keep &= ~bad
    if cfg.min_track_length > 0:
        bad = keep & (points.track_length < cfg.min_track_length)
        removed["track_length"] = int(bad.sum())
        keep &= ~bad
    idx = np.flatnonzero(keep)
    sor_keep, thr = statistical_outlier_mask(xyz[idx], cfg.sor_neighbors, cfg.sor_std_ratio)
    if np.isnan(thr):
        removed["sor_skipped_too_few_points"] = 0
        log.warning("SfM cues: only %d points (<= K=%d): statistical outlier removal skipped",
                    len(idx), cfg.sor_neighbors)
    removed["sor_outlier"] = int(np.sum(~sor_keep))
    idx = idx[sor_keep]
    err = np.nan_to_num(np.asarray(points.error, np.float64)[idx], nan=0.0).clip(min=0.0)
    cloud = CueCloud.make(xyz[idx], points.rgb[idx], CueType.SFM, confidence=1.0 / (1.0 + err))
    log.info("SfM cues: %d of %d points kept; removed %s (SOR cut-off %.4f m)",
             len(idx), n, {k: v for k, v in removed.items() if v}, thr)
    return SfmCues(cloud, idx.astype(np.int64), n, removed, thr)
