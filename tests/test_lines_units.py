"""Unit tests of the line-cue building blocks (geocues.lines): detection conventions, epipolar
geometry, two-view triangulation, plane fitting, extents, merging, sampling, pairs, config."""

from __future__ import annotations

import numpy as np
import pytest

from geocues.lines import LineConfig, LineCues
from geocues.lines.detect import (Segments2D, cache_key, dedup_segments, detect_gray, detect_image,
                                  normal_map_to_channels, segment_colors)
from geocues.lines.match import epipolar_angle, epipolar_iou, fundamental, hamming, homog, match_pair
from geocues.lines.merge import (duplicate_pairs, fit_lines, member_planes, plane_angle_groups,
                                 robust_extent, sample_segments, Views)
from geocues.lines.triangulate import line_from_planes, segment_planes, triangulate_matches
from geocues.scene import Camera


def make_camera(C, target, index=0, width=640, height=480, f=525.0) -> Camera:
    C, target = np.asarray(C, float), np.asarray(target, float)
    z = target - C
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    return Camera(index, index + 1, f"{index:05d}.png", None, width, height, K, R, -R @ C)


def project_segment(cam: Camera, X: np.ndarray) -> np.ndarray:
    uv, z = cam.project(X)
    assert (z > 0).all()
    return uv.reshape(-1)  # (x1, y1, x2, y2)


@pytest.fixture()
def two_cams():
    return (make_camera([0.0, 0.0, 1.5], [0.3, 3.0, 1.4], 0),
            make_camera([0.6, 0.2, 1.6], [0.2, 3.0, 1.3], 1))


class TestDetect:
    def test_lsd_step_edge_is_in_colmap_pixels(self):
        # columns 0..99 dark, 100.. bright: the edge lies at x = 100 in COLMAP pixels
        g = np.zeros((200, 200), np.uint8)
        g[:, 100:] = 200
        segs = detect_gray(g, LineConfig(min_length_px=20))
        assert len(segs) == 1
        assert np.allclose(segs[0, [0, 2]], 100.0, atol=0.1), segs

    def test_fld_step_edge_is_in_colmap_pixels(self):
        g = np.zeros((200, 200), np.uint8)
        g[60:, :] = 200  # horizontal edge at y = 60
        segs = detect_gray(g, LineConfig(detector="fld", min_length_px=20))
        assert len(segs) >= 1
        assert np.allclose(segs[0, [1, 3]], 60.0, atol=0.6), segs

    def test_min_length_scales_with_width(self):
        g = np.zeros((87, 320), np.uint8)
        g[:, 160:] = 200  # the edge is about 85 px long
        assert len(detect_gray(g, LineConfig(min_length_px=80))) == 1  # 80 px at 640 = 40 px here
        assert len(detect_gray(g, LineConfig(min_length_px=200))) == 0  # 100 px here

    def test_bad_input_raises(self):
        with pytest.raises(ValueError, match="uint8"):
            detect_gray(np.zeros((10, 10), np.float32), LineConfig())
        with pytest.raises(ValueError, match="normal map"):
            normal_map_to_channels(np.zeros((10, 10)))

    def test_dedup_keeps_the_longer_duplicate(self):
        segs = np.array([[10, 10, 110, 10], [20, 11, 80, 11.5], [10, 40, 110, 40]], float)
        keep = dedup_segments(segs, angle_deg=3.0, dist_px=2.0)
        assert keep.tolist() == [0, 2]

    def test_dedup_prefers_rgb_over_an_offset_normal_map_segment(self):
        segs = np.array([[10, 10, 110, 10], [5, 13, 115, 13]], float)  # normal one: longer, 3 px off
        keep = dedup_segments(segs, 3.0, 2.0, priority=np.array([0, 1]), cross_dist_px=4.0)
        assert keep.tolist() == [0]
        assert dedup_segments(segs, 3.0, 2.0).tolist() == [0, 1]  # same source: 3 px apart is two

    def test_normal_crease_is_detected_only_from_normals(self):
        img = np.full((120, 160, 3), 0.5, np.float32)  # no colour edge at all
        n = np.zeros((120, 160, 3), np.float32)
        n[:, :80] = [0.0, 0.0, -1.0]
        n[:, 80:] = [0.7071, 0.0, -0.7071]  # a 45 degree crease at x = 80
        cfg = LineConfig(min_length_px=40)
        seg, counts = detect_image(img, None, cfg)
        assert len(seg) == 0 and counts["rgb"] == 0
        seg, counts = detect_image(img, n, cfg)
        assert counts["normal"] >= 1 and len(seg) == 1  # duplicates across channels merged
        assert seg.source[0] == 1 and np.allclose(seg.segs[0, [0, 2]], 80.0, atol=0.3)

    def test_segment_colors(self):
        img = np.zeros((50, 50, 3), np.float32)
        img[:, 25:] = [1.0, 0.5, 0.0]
        c = segment_colors(img, np.array([[30.0, 5, 30, 45], [5.0, 5, 5, 45]]))
        assert np.allclose(c, [[1.0, 0.5, 0.0], [0, 0, 0]])

    def test_cache_key_depends_on_params_and_size(self):
        a = cache_key(LineConfig(), 640, 480, False)
        assert a == cache_key(LineConfig(), 640, 480, False)
        assert a != cache_key(LineConfig(min_length_px=30), 640, 480, False)
        assert a != cache_key(LineConfig(), 320, 240, False)
        assert a != cache_key(LineConfig(), 640, 480, True)


class TestEpipolar:
    def test_fundamental_maps_points_to_their_epipolar_lines(self, two_cams):
        a, b = two_cams
        X = np.random.default_rng(0).uniform([-1, 2, 0.5], [1.5, 3, 2.0], (20, 3))
        ua, _ = a.project(X)
        ub, _ = b.project(X)
        F = fundamental(a, b)
        r = np.einsum("ni,ij,nj->n", homog(ub), F, homog(ua))
        scale = np.linalg.norm(homog(ua) @ F.T, axis=1)
        assert np.abs(r / scale).max() < 1e-6

    def test_epipolar_iou_of_true_match_is_one_and_of_a_far_segment_negative(self, two_cams):
        a, b = two_cams
        X = np.array([[0.0, 3.0, 0.8], [0.1, 3.0, 1.8]])
        sa, sb = project_segment(a, X)[None], project_segment(b, X)[None]
        assert epipolar_iou(sa, sb, fundamental(a, b))[0, 0] == pytest.approx(1.0, abs=1e-6)
        far = project_segment(b, X + [0, 0, 3.0])[None]
        assert epipolar_iou(sa, far, fundamental(a, b))[0, 0] < 0

    def test_epipolar_angle_is_zero_along_the_baseline(self):
        a = make_camera([0.0, 0.0, 1.5], [0.0, 3.0, 1.5], 0)
        b = make_camera([0.5, 0.0, 1.5], [0.5, 3.0, 1.5], 1)  # pure x translation
        e_a = a.K @ (a.R @ b.center + a.t)
        horiz = project_segment(a, np.array([[-0.5, 3.0, 1.2], [0.5, 3.0, 1.2]]))[None]
        vert = project_segment(a, np.array([[0.2, 3.0, 0.8], [0.2, 3.0, 1.8]]))[None]
        assert epipolar_angle(horiz, e_a)[0] < 1e-6
        assert epipolar_angle(vert, e_a)[0] == pytest.approx(90.0, abs=1e-6)

    def test_hamming(self):
        a = np.zeros((2, 32), np.uint8)
        b = np.zeros((1, 32), np.uint8)
        a[1, :2] = 0xFF
        assert hamming(a, b).ravel().tolist() == [0, 16]

    def test_match_pair_finds_true_matches_and_counts_degenerate_ones(self):
        a = make_camera([0.0, 0.0, 1.5], [0.0, 3.0, 1.5], 0)
        b = make_camera([0.5, 0.0, 1.5], [0.5, 3.0, 1.5], 1)
        lines = [np.array([[x, 3.0, 0.8], [x, 3.0, 1.8]]) for x in (-0.4, 0.1, 0.6)]
        lines.append(np.array([[-0.5, 3.0, 1.3], [0.8, 3.0, 1.3]]))  # along the baseline
        # parallel vertical lines all fill each other's epipolar bands: descriptors tell them apart
        desc = np.random.default_rng(1).integers(0, 256, (4, 32), dtype=np.uint8)
        seg_a = Segments2D(np.stack([project_segment(a, L) for L in lines]), np.zeros(4, np.uint8),
                           desc, np.zeros((4, 3), np.float32))
        seg_b = Segments2D(np.stack([project_segment(b, L) for L in lines]), np.zeros(4, np.uint8),
                           desc, np.zeros((4, 3), np.float32))
        ia, ib, counts = match_pair(seg_a, seg_b, a, b, LineConfig(matcher="lbd", topk_matches=1))
        assert set(zip(ia.tolist(), ib.tolist())) == {(0, 0), (1, 1), (2, 2)}
        assert counts["parallel_epipolar"] >= 1


class TestTriangulate:
    def test_two_view_triangulation_is_exact(self, two_cams):
        a, b = two_cams
        X = np.array([[[0.2, 3.0, 0.7], [0.5, 2.6, 1.9]], [[-0.6, 2.5, 1.0], [0.4, 2.5, 1.1]]])
        sa = np.stack([project_segment(a, x) for x in X])
        sb = np.stack([project_segment(b, x + 0.3 * (x[1] - x[0])) for x in X])  # b sees another part
        Y, ok, counts = triangulate_matches(sa, a, sb, b, LineConfig())
        assert ok.all() and counts["behind_camera"] == 0
        assert np.allclose(Y, X, atol=1e-9)  # endpoints follow a's rays

    def test_line_from_planes(self, two_cams):
        a, b = two_cams
        X = np.array([[0.2, 3.0, 0.7], [0.5, 2.6, 1.9]])
        n1, d1 = segment_planes(project_segment(a, X)[None], a)
        n2, d2 = segment_planes(project_segment(b, X)[None], b)
        P, u = line_from_planes(n1, d1, n2, d2)
        w = X - P[0]
        assert np.allclose(np.cross(w, u[0]), 0.0, atol=1e-9)

    def test_random_matches_keep_only_valid_geometry(self, two_cams):
        # wrong matches put endpoints behind a camera, far away or along the rays: all counted
        a, b = two_cams
        rng = np.random.default_rng(0)
        sa = rng.uniform([0, 0, 0, 0], [640, 480, 640, 480], (300, 4))
        sb = rng.uniform([0, 0, 0, 0], [640, 480, 640, 480], (300, 4))
        cfg = LineConfig(max_depth_m=10.0)
        Y, ok, counts = triangulate_matches(sa, a, sb, b, cfg)
        assert ok.sum() + counts["behind_camera"] + counts["too_far"] + counts["ray_aligned"] == 300
        assert counts["behind_camera"] > 0 and counts["too_far"] > 0 and ok.sum() > 0
        for cam in (a, b):
            _, z = cam.project(Y[ok].reshape(-1, 3))
            assert (z > 0).all() and (z <= cfg.max_depth_m).all()


class TestFit:
    def views_and_planes(self, X):
        cams = [make_camera([x, 0.0, 1.5 + 0.1 * x], [0.3, 3.0, 1.3], k) for k, x in enumerate([-0.6, -0.2, 0.3, 0.7])]
        segs = np.stack([project_segment(c, X) for c in cams])
        return cams, segs

    def test_fit_lines_recovers_the_line(self):
        X = np.array([[0.1, 3.0, 0.6], [0.4, 2.7, 1.8]])
        cams, segs = self.views_and_planes(X)
        views = Views(cams)
        v = np.arange(len(cams))
        n, d = member_planes(segs, v, views)
        P, u, sigma = fit_lines(np.zeros(4, np.int64), n, d, np.ones(4), X[:1] + 0.05, 1)
        t = X[1] - X[0]
        assert abs(abs(u[0] @ t) / np.linalg.norm(t) - 1) < 1e-9
        w = X[0] - P[0]
        assert np.linalg.norm(w - (w @ u[0]) * u[0]) < 1e-6
        assert np.isfinite(sigma[0]) and sigma[0] > 0

    def test_plane_angle_groups_counts_distinct_viewpoints(self):
        X = np.array([[0.1, 3.0, 0.6], [0.4, 2.7, 1.8]])
        cams, segs = self.views_and_planes(X)
        n, _ = member_planes(segs, np.arange(4), Views(cams))
        u = (X[1] - X[0]) / np.linalg.norm(X[1] - X[0])
        g = plane_angle_groups(np.zeros(4, np.int64), n, u[None], 1, min_angle_deg=1.0)
        assert g[0] == 4
        g = plane_angle_groups(np.zeros(4, np.int64), n[[0, 0, 0, 1]], u[None], 1, min_angle_deg=1.0)
        assert g[0] == 2

    def test_robust_extent_ignores_a_single_overshoot(self):
        track = np.zeros(4, np.int64)
        view = np.arange(4)
        s = np.array([[0.0, 1.0], [0.1, 0.9], [-5.0, 0.95], [0.05, 9.0]])
        lo, hi = robust_extent(track, view, s, 1, min_share=0.2)  # k = 2 views
        assert lo[0] == pytest.approx(0.0) and hi[0] == pytest.approx(1.0)
        lo, hi = robust_extent(track, view, s, 1, min_share=0.75)  # k = 3 views
        assert lo[0] == pytest.approx(0.05) and hi[0] == pytest.approx(0.95)

    def test_robust_extent_unions_fragments_of_one_view_and_handles_one_view(self):
        track = np.array([0, 0, 0, 1])
        view = np.array([0, 0, 1, 2])
        s = np.array([[0.0, 0.4], [0.5, 1.0], [0.2, 0.8], [3.0, 4.0]])
        lo, hi = robust_extent(track, view, s, 3)
        assert (lo[0], hi[0]) == (pytest.approx(0.2), pytest.approx(0.8))  # covered by both views
        assert (lo[1], hi[1]) == (3.0, 4.0)  # a single view: its own interval
        assert np.isnan(lo[2]) and np.isnan(hi[2])

    def test_duplicate_pairs(self):
        S = np.array([[[0, 0, 0], [1, 0, 0]], [[0.5, 0.005, 0], [1.5, 0.005, 0]],
                      [[0, 0.2, 0], [1, 0.2, 0]], [[1.03, 0, 0], [2, 0, 0]]], float)
        pairs = {tuple(p) for p in duplicate_pairs(S, LineConfig(merge_dist_m=0.02, merge_gap_m=0.05)).tolist()}
        assert pairs == {(0, 1), (0, 3), (1, 3)}

    def test_sample_segments_spacing(self):
        S = np.array([[[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 0.005, 0]]], float)
        P, line = sample_segments(S, 0.01)
        for k in range(2):
            p = P[line == k]
            gaps = np.linalg.norm(np.diff(p, axis=0), axis=1)
            assert len(p) >= 2 and gaps.max() <= 0.01 + 1e-12
            assert np.allclose(p[[0, -1]], S[k])


class TestConfig:
    def test_validate(self):
        LineConfig().validate()
        for bad in (dict(min_views=1), dict(sample_step=0), dict(detector="hough"), dict(pair_depths_m=())):
            with pytest.raises(ValueError):
                LineConfig(**bad).validate()

    def test_px_scales_with_width(self):
        assert LineConfig().px(2.0, 320) == pytest.approx(1.0)

    def test_empty_line_cues_are_well_formed(self):
        e = LineCues.empty(rejected={"x": 1})
        assert len(e) == 0 and e.points.shape == (0, 3) and e.segments.shape == (0, 2, 3)
        with pytest.raises(ValueError):
            LineCues(np.zeros((1, 2, 3)), np.zeros(2, np.int64), [], np.zeros((1, 3), np.float32),
                     np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                     np.zeros((0, 3), np.float32))
