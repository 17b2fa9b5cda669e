"""SfM cues: statistical outlier removal (paper §4.1) and its hard cases."""

from __future__ import annotations

import numpy as np
import pytest

from geocues.scene import Points3D, Scene
from geocues.sfm_cues import SfmCueConfig, extract_sfm_cues, statistical_outlier_mask
from geocues.types import CueType

from cues_synth import distance_to_surface, make_room_scene


def _points(xyz: np.ndarray, error: float = 0.5) -> Points3D:
    n = len(xyz)
    return Points3D(np.arange(n), xyz, np.full((n, 3), 200, np.uint8), np.full(n, error),
                    np.full(n, 3, np.int32))


def _plane_with_outliers(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    inl = np.column_stack([rng.uniform(0, 2, 1500), rng.uniform(0, 2, 1500), rng.normal(0, 0.003, 1500)])
    out = rng.uniform([-3, -3, 1.0], [5, 5, 3.0], (40, 3))
    return np.concatenate([inl, out]), np.r_[np.ones(1500, bool), np.zeros(40, bool)]


class TestStatisticalOutlierMask:
    def test_removes_isolated_points(self):
        xyz, is_inlier = _plane_with_outliers()
        keep, thr = statistical_outlier_mask(xyz, nb_neighbors=20, std_ratio=2.0)
        assert not keep[~is_inlier].any(), "an isolated outlier survived"
        assert keep[is_inlier].mean() > 0.95
        assert thr > 0

    def test_matches_the_equation(self):
        from scipy.spatial import cKDTree

        xyz, _ = _plane_with_outliers(1)
        keep, thr = statistical_outlier_mask(xyz, nb_neighbors=10, std_ratio=1.0)
        d, _ = cKDTree(xyz).query(xyz, k=11)
        mean_d = d[:, 1:].mean(axis=1)
        assert np.mean(keep == (mean_d <= thr)) > 0.995

    def test_std_ratio_is_monotone(self):
        xyz, _ = _plane_with_outliers(2)
        kept = [statistical_outlier_mask(xyz, 20, r)[0].sum() for r in (0.5, 1.0, 2.0, 4.0)]
        assert kept == sorted(kept) and kept[0] < kept[-1]

    def test_too_few_points_keeps_all(self):
        keep, thr = statistical_outlier_mask(np.random.default_rng(0).random((5, 3)), 20, 2.0)
        assert keep.all() and np.isnan(thr)

    def test_bad_input(self):
        with pytest.raises(ValueError, match=r"\[N, 3\]"):
            statistical_outlier_mask(np.zeros((4, 2)), 3, 2.0)
        with pytest.raises(ValueError, match="nb_neighbors"):
            statistical_outlier_mask(np.zeros((4, 3)), 0, 2.0)


class TestExtractSfmCues:
    def test_counts_and_confidence(self):
        xyz, is_inlier = _plane_with_outliers()
        cues = extract_sfm_cues(_points(xyz, error=1.0), SfmCueConfig())
        assert cues.n_input == len(xyz)
        assert cues.removed["sor_outlier"] == len(xyz) - len(cues.kept) == cues.n_removed
        assert np.all(cues.cloud.cue_type == CueType.SFM)
        np.testing.assert_allclose(cues.cloud.confidence, 0.5)  # 1 / (1 + 1 px)
        np.testing.assert_allclose(cues.cloud.xyz, xyz[cues.kept])

    def test_prefilters(self):
        xyz, _ = _plane_with_outliers()
        pts = _points(xyz)
        pts.error[:100] = 5.0
        pts.track_length[100:150] = 2
        cues = extract_sfm_cues(pts, SfmCueConfig(max_reproj_error=2.0, min_track_length=3))
        assert cues.removed["reproj_error"] == 100 and cues.removed["track_length"] == 50
        assert not np.isin(np.arange(150), cues.kept).any()

    def test_empty_model(self):
        empty = Points3D(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                         np.zeros(0), np.zeros(0, np.int32))
        cues = extract_sfm_cues(empty, SfmCueConfig())
        assert len(cues.cloud) == 0 and cues.n_input == 0 and "empty_model" in cues.removed

    def test_sor_raises_the_share_near_the_surface(self, tmp_path):
        """On the synthetic room: SfM points with 10% floating outliers; the share within 5 cm of
        the true surface must be higher after SOR than before."""
        scene = Scene.load(make_room_scene(tmp_path / "room", n_views=2, priors="none",
                                           n_sfm=400, n_outliers=40))
        before = np.mean(distance_to_surface(scene.points.xyz) < 0.05)
        cues = extract_sfm_cues(scene.points, SfmCueConfig())
        after = np.mean(distance_to_surface(cues.cloud.xyz) < 0.05)
        assert after > before
        assert after > 0.97
