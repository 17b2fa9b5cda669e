"""Plane-like cues, with and without depth priors, on the synthetic room."""

from __future__ import annotations

import numpy as np
import pytest

from geocues.depth_align import Anchors
from geocues.plane_fit import (AnchoredPlane, fit_plane_groups, fit_plane_ransac, loo_group_residuals,
                               ray_plane_depth)
from geocues.plane_merge import consolidate_planes, multiview_conflict, multiview_support, voxel_downsample
from geocues.plane_regions import split_regions_by_lines
from geocues.planes import PlaneConfig, plane_cues_with_prior
from geocues.planes_free import _held_out_inliers, plane_cues_prior_free
from geocues.scene import Scene
from geocues.texture import TextureConfig, weak_texture_regions

from cues_synth import distance_to_surface, fake_line_cues, make_room_scene, render


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    scene = Scene.load(make_room_scene(tmp_path_factory.mktemp("planes") / "room", n_views=4,
                                       priors="none", n_sfm=300, n_outliers=0))
    depths = [render(c.K, c.R, c.t, c.width, c.height)[1] for c in scene.cameras]
    regions = [weak_texture_regions(scene.load_image(i), TextureConfig()).regions for i in range(4)]
    lines = fake_line_cues(scene.cameras)
    anchors = Anchors.build(sfm_xyz=scene.points.xyz, line_points=lines.points,
                            line_of_point=lines.point_line, line_views=lines.views)
    return scene, depths, regions, anchors


def _wall_normals_ok(xyz: np.ndarray, normal: np.ndarray) -> float:
    """Share of points whose normal is the axis normal of the room face they lie on."""
    from cues_synth import ROOM

    faces = [(0, 0.0), (0, ROOM[0]), (1, 0.0), (1, ROOM[1]), (2, 0.0), (2, ROOM[2])]
    ok = np.zeros(len(xyz), bool)
    for axis, v in faces:
        on = np.abs(xyz[:, axis] - v) < 0.03
        ok |= on & (np.abs(normal[:, axis]) > 0.99)
    return float(ok.mean())


class TestGeometry:
    def test_ray_plane_depth(self):
        rays = np.array([[0.0, 0.0, 1.0], [0.5, -0.2, 1.0], [1.0, 0.0, 0.0]])
        z = ray_plane_depth(rays, np.array([0.0, 0.0, 1.0]), -3.0)  # plane z = 3
        np.testing.assert_allclose(z[:2], [3.0, 3.0])
        assert np.isinf(z[2])
        n = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)  # tilted plane through (0, 0, 2)
        z = ray_plane_depth(rays[1:2], n, -n @ np.array([0.0, 0.0, 2.0]))
        X = rays[1] * z[0]
        assert n @ X - n @ np.array([0.0, 0.0, 2.0]) == pytest.approx(0.0, abs=1e-12)

    def test_fit_plane_ransac(self):
        rng = np.random.default_rng(0)
        P = np.column_stack([rng.random(300), rng.random(300), 0.5 + rng.normal(0, 0.002, 300)])
        P[:60] += rng.uniform(0.1, 1.0, (60, 3)) * [0, 0, 1]
        n, d, inl = fit_plane_ransac(P, 0.01)
        assert abs(abs(n[2]) - 1) < 1e-3 and abs(abs(d) - 0.5) < 5e-3
        assert inl[60:].mean() > 0.95 and inl[:60].mean() < 0.1
        with pytest.raises(ValueError, match="N >= 3"):
            fit_plane_ransac(P[:2], 0.01)

    def test_fit_plane_ransac_is_deterministic_per_seed(self):
        """Regression: Open3D's threaded segment_plane returned another plane on 4 of 20 identical
        calls, so the same scene and seed gave different PLANE cue counts."""
        rng = np.random.default_rng(1)
        P = np.r_[np.c_[rng.uniform(-1, 1, (5000, 2)), rng.normal(0, 0.01, 5000)],
                  rng.uniform(-1, 1, (3000, 3))]
        runs = [fit_plane_ransac(P, 0.02, seed=3) for _ in range(20)]
        for n, d, inl in runs[1:]:
            assert np.array_equal(n, runs[0][0]) and d == runs[0][1] and np.array_equal(inl, runs[0][2])
        assert abs(runs[0][0][2]) > 0.999 and inl[:5000].mean() > 0.9

    def test_fit_plane_groups_ignores_one_long_line(self):
        """A long off-plane line with 200 samples must not outvote 12 SfM points on the plane."""
        rng = np.random.default_rng(1)
        pts = np.column_stack([rng.random(12) * 2, rng.random(12) * 2, np.zeros(12)])  # plane z = 0
        t = np.linspace(0, 2, 200)[:, None]
        line = np.array([0.0, 1.0, 0.5]) + t * np.array([1.0, 0.0, 0.1])  # off the plane
        P = np.concatenate([pts, line])
        groups = np.r_[-1 - np.arange(12), np.zeros(200, np.int64)]
        n, d, inl, frac = fit_plane_groups(P, groups, 0.01, rng)
        assert abs(abs(n[2]) - 1) < 1e-6 and abs(d) < 1e-6 and inl[:12].all() and not inl[12:].any()
        assert frac == pytest.approx(12 / 13)
        _, _, inl_plain = fit_plane_ransac(P, 0.01)
        assert inl_plain[12:].mean() > 0.95, "plain RANSAC should have picked a plane through the line"

    def test_split_regions_by_lines(self, room):
        scene = room[0]
        cam = scene.cameras[0]
        regions = np.zeros((cam.height, cam.width), np.int32)
        # a vertical 3D segment in front of the camera, projecting across the whole image height
        c, R = cam.center, cam.R
        p = c + 2.0 * R[2] + 0.1 * R[0]
        seg = np.stack([p - 5.0 * R[1], p + 5.0 * R[1]])[None]
        out = split_regions_by_lines(cam, regions, seg, width_px=2, min_pixels=50)
        assert out.max() == 1 and np.all(out[:, :5] == out[0, 0]) and np.all(out[:, -5:] == out[0, -1])
        assert out[0, 0] != out[0, -1] and (out == -1).sum() < 4 * cam.height
        assert np.array_equal(split_regions_by_lines(cam, regions, np.zeros((0, 2, 3)), 2, 50), regions)

    def test_anchored_plane_uncertainty(self):
        """Two crossing lines fix a plane everywhere near them; one line fixes it only along
        itself, unless a prior normal is given."""
        t = np.linspace(-1, 1, 50)[:, None]
        l1 = t * np.array([1.0, 0, 0]) + [0, 0, 2.0]
        l2 = t * np.array([0, 1.0, 0]) + [0, 0, 2.0]
        w = np.full(50, 1 / 50)
        two = AnchoredPlane(np.concatenate([l1, l2]), np.r_[w, w], np.array([0.1, 0, 1.0]), sigma=0.01)
        np.testing.assert_allclose(np.abs(two.n), [0, 0, 1], atol=1e-9)
        assert two.d * np.sign(two.n[2]) == pytest.approx(-2.0)
        far = np.array([[0.3, 0.3, 2.0], [0.0, 3.0, 2.0]])
        assert two.std_at(far)[0] < 0.015 < two.std_at(far)[1]
        one = AnchoredPlane(l1, w, np.array([0, 0, 1.0]), sigma=0.01)
        assert one.std_at(np.array([[0.0, 0.5, 2.0]]))[0] > 1.0  # off the line: unknown
        assert one.std_at(np.array([[0.5, 0.0, 2.0]]))[0] < 0.015  # on it: known
        prior = AnchoredPlane(l1, w, np.array([0, 0, 1.0]), sigma=0.01, prior_normal_std_rad=np.radians(2))
        assert 0.01 < prior.std_at(np.array([[0.0, 0.5, 2.0]]))[0] < 0.03  # ~ 0.5 m * tan(2 deg)

    def test_multiview_support_and_fusion(self):
        rng = np.random.default_rng(0)
        wall = np.column_stack([rng.random(30000) * 2, np.zeros(30000), rng.random(30000) * 2])
        view = rng.integers(0, 3, 30000)  # three images see the wall y = 0
        ghost = np.column_stack([rng.random(300) * 2, np.full(300, 0.5), rng.random(300) * 2])
        X = np.concatenate([wall, ghost])
        V = np.r_[view, np.full(300, 3)]  # a fourth image puts a wrong plane at y = 0.5
        sup = multiview_support(X, V, radius=0.03, voxel=0.02)
        assert np.mean(sup[:30000] >= 2) > 0.999 and np.all(sup[30000:] == 1)  # (edge points may lack support)
        # fusion: the same wall from two images, 2 cm apart, meets in the middle
        a = np.column_stack([rng.random(500) * 2, np.full(500, 0.01), rng.random(500) * 2])
        b = np.column_stack([rng.random(500) * 2, np.full(500, -0.01), rng.random(500) * 2])
        planes = np.array([[0, -1.0, 0, 0.01], [0, -1.0, 0, -0.01]])
        out, nrm, nv = consolidate_planes(np.concatenate([a, b]), np.r_[np.zeros(500, int), np.ones(500, int)],
                                          planes, np.array([0, 1]), np.array([[1.0, -3.0, 1.0], [1.5, -3.0, 1.0]]),
                                          max_angle_deg=5, max_dist=0.05, min_ray_cos=0.1)
        assert np.all(nv == 2) and np.abs(out[:, 1]).max() < 1e-9
        assert np.all(nrm[:, 1] < -0.99)  # facing the cameras at y = -3

    def test_multiview_support_needs_the_same_orientation(self):
        """Regression (ICL, issue 3): planes of different images tilted through a wall and a chair
        in front of it cross the wall, and near the crossing every image 'supported' the others."""
        rng = np.random.default_rng(2)
        pts, views, nrms = [], [], []
        for v, tilt in enumerate(np.radians([-12.0, 0.0, 12.0])):  # three planes crossing at x = 1
            n = np.array([np.sin(tilt), -np.cos(tilt), 0.0])
            x = rng.random(20000) * 2
            z = rng.random(20000) * 2
            pts.append(np.column_stack([x, np.tan(tilt) * (x - 1.0), z]))
            views.append(np.full(20000, v))
            nrms.append(np.broadcast_to(n, (20000, 3)))
        X, V, N = np.concatenate(pts), np.concatenate(views), np.concatenate(nrms)
        near = np.abs(X[:, 0] - 1.0) < 0.02
        plain = multiview_support(X, V, radius=0.03, voxel=0.02)
        oriented = multiview_support(X, V, radius=0.03, voxel=0.02, normal=N, max_angle_deg=5.0)
        assert np.mean(plain[near] >= 3) > 0.9  # position alone: the crossing is 'seen by 3 images'
        assert np.all(oriented == 1)  # no two of them are the same plane
        with pytest.raises(ValueError, match="normal must be"):
            multiview_support(X, V, 0.03, 0.02, normal=N[:5], max_angle_deg=5.0)

    def test_multiview_conflict_outvotes_a_repeated_wrong_plane(self):
        """Two images repeat a wrong plane 3 cm in front of a wall that four images put at y = 0:
        the wrong plane has support (2 images) but is outvoted; the wall is kept."""
        rng = np.random.default_rng(3)
        m = 8000
        wall = [np.column_stack([rng.random(m), np.zeros(m), rng.random(m)]) for _ in range(4)]
        ghost = [np.column_stack([rng.random(m), np.full(m, -0.03), rng.random(m)]) for _ in range(2)]
        X = np.concatenate(wall + ghost)
        V = np.repeat(np.arange(6), m)
        N = np.broadcast_to([0.0, -1.0, 0.0], X.shape)
        agree, disagree = multiview_conflict(X, V, N, radius=0.05, offset=0.02, max_angle_deg=5.0, voxel=0.02)
        inner = (X[:, 0] > 0.1) & (X[:, 0] < 0.9) & (X[:, 2] > 0.1) & (X[:, 2] < 0.9)
        is_wall = V < 4
        assert np.all(agree[is_wall & inner] > disagree[is_wall & inner])
        assert np.all(agree[~is_wall & inner] < disagree[~is_wall & inner])
        assert np.all(agree[~is_wall] <= 2)
        a0, d0 = multiview_conflict(np.zeros((0, 3)), np.zeros(0, int), np.zeros((0, 3)), 0.05, 0.02, 5.0, 0.02)
        assert len(a0) == len(d0) == 0

    def test_voxel_downsample_counts_views(self):
        xyz = np.array([[0.001, 0.001, 0.001], [0.004, 0.002, 0.003], [0.5, 0.5, 0.5], [0.003, 0.0, 0.0]])
        nrm = np.array([[0, 0, 1.0], [0, 0, -1.0], [1, 0, 0], [0, 0, 1.0]])
        vx, vc, vn, nv = voxel_downsample(xyz, np.ones((4, 3)), nrm, np.array([0, 1, 0, 0]), 0.01)
        assert len(vx) == 2 and sorted(nv.tolist()) == [1, 2]
        k = int(np.argmax(nv))
        np.testing.assert_allclose(vx[k], xyz[[0, 1, 3]].mean(axis=0))
        np.testing.assert_allclose(np.abs(vn[k]), [0, 0, 1], atol=1e-6)  # opposite normals aligned
        with pytest.raises(ValueError, match="voxel size"):
            voxel_downsample(xyz, np.ones((4, 3)), nrm, np.zeros(4), 0.0)


class TestWithPrior:
    def test_points_on_the_walls(self, room):
        scene, depths, regions, anchors = room
        cfg = PlaneConfig()
        n_pts = 0
        for i in range(4):
            cam = scene.cameras[i]
            prior = depths[i] * (1 + 0.01 * np.random.default_rng(i).normal(size=depths[i].shape))
            pp = plane_cues_with_prior(cam, scene.load_image(i), regions[i], prior.astype(np.float32),
                                       anchors.xyz[anchors.candidates(i)], cfg)
            if len(pp.xyz):
                d = distance_to_surface(pp.xyz)
                assert np.mean(d < 0.03) > 0.95, f"view {i}: {np.mean(d < 0.03):.3f} within 3 cm"
                assert _wall_normals_ok(pp.xyz, pp.normal) > 0.95
                rays = pp.xyz - cam.center
                assert np.all(np.sum(rays * pp.normal, axis=1) < 0), "normals must face the camera"
            n_pts += len(pp.xyz)
        assert n_pts > 5000

    def test_snap_removes_prior_offset(self, room):
        """A prior 4 % too far (a scale error moves each plane along its normal, 6-10 cm here):
        the anchors move the planes back."""
        scene, depths, regions, anchors = room
        i = 1
        prior = (1.04 * depths[i]).astype(np.float32)
        a = anchors.xyz[anchors.candidates(i)]
        snap = plane_cues_with_prior(scene.cameras[i], scene.load_image(i), regions[i], prior, a,
                                     PlaneConfig(agree_dist=0.12))
        raw = plane_cues_with_prior(scene.cameras[i], scene.load_image(i), regions[i], prior, a,
                                    PlaneConfig(agree_dist=0.12, snap_to_plane=False))
        assert len(snap.xyz) > 200 and len(raw.xyz) > 500  # snapped: only where the anchors fix the plane
        assert np.median(distance_to_surface(snap.xyz)) < 0.005
        assert np.median(distance_to_surface(raw.xyz)) > 0.04

    def test_rejects_planes_the_cues_contradict(self, room):
        scene, depths, regions, anchors = room
        i = 2
        # anchors pulled 25 % towards the camera: in front of the walls, not hidden by them
        a = anchors.xyz[anchors.candidates(i)]
        moved = a - 0.25 * (a - scene.cameras[i].center)
        pp = plane_cues_with_prior(scene.cameras[i], scene.load_image(i), regions[i], depths[i], moved,
                                   PlaneConfig())
        assert len(pp.xyz) == 0 and pp.rejected.get("disagrees_with_cues", 0) >= 1

    def test_no_anchors(self, room):
        scene, depths, regions, _ = room
        none = np.zeros((0, 3))
        pp = plane_cues_with_prior(scene.cameras[0], scene.load_image(0), regions[0], depths[0], none,
                                   PlaneConfig())
        assert len(pp.xyz) == 0 and pp.rejected.get("no_nearby_cues", 0) >= 1
        pp = plane_cues_with_prior(scene.cameras[0], scene.load_image(0), regions[0], depths[0], none,
                                   PlaneConfig(require_anchors=False))
        assert len(pp.xyz) > 1000 and np.mean(distance_to_surface(pp.xyz) < 0.03) > 0.95

    def test_fill_holes_covers_a_sparse_prior_on_the_wall(self, room):
        """An MVS-like prior with no depth in most of each region (a 24-px lattice of depth lines
        is all there is): only with fill_holes do the holes get plane points, on the walls; a
        region with no prior depth at all is handed back for the prior-free fit."""
        scene, depths, regions, anchors = room
        i = 1
        cam, image, a = scene.cameras[i], scene.load_image(i), anchors.xyz[anchors.candidates(i)]
        sparse = np.zeros_like(depths[i])
        sparse[::24] = depths[i][::24]
        sparse[:, ::24] = depths[i][:, ::24]
        off = plane_cues_with_prior(cam, image, regions[i], sparse, a, PlaneConfig(min_region_points=20))
        on = plane_cues_with_prior(cam, image, regions[i], sparse, a,
                                   PlaneConfig(min_region_points=20, fill_holes=True))
        assert len(on.xyz) > 3 * max(len(off.xyz), 1)
        assert np.mean(distance_to_surface(on.xyz) < 0.02) > 0.95
        assert _wall_normals_ok(on.xyz, on.normal) > 0.95
        assert len(on.planes) == len(off.planes)  # the same planes, over more of their pixels
        dense = plane_cues_with_prior(cam, image, regions[i], depths[i], a, PlaneConfig(fill_holes=True))
        k = int(np.bincount(regions[i][regions[i] >= 0]).argmax())  # the largest region loses its prior
        holed = np.where(regions[i] == k, 0, depths[i]).astype(np.float32)
        pp = plane_cues_with_prior(cam, image, regions[i], holed, a, PlaneConfig(fill_holes=True))
        assert pp.no_depth_regions == [k] and len(pp.xyz) < len(dense.xyz)
        assert plane_cues_with_prior(cam, image, regions[i], holed, a, PlaneConfig()).no_depth_regions == []

    def test_shape_mismatch(self, room):
        scene, depths, regions, anchors = room
        with pytest.raises(ValueError, match=r"must all be \(120, 160\)"):
            plane_cues_with_prior(scene.cameras[0], scene.load_image(0), regions[0][:10], depths[0],
                                  anchors.xyz, PlaneConfig())


class TestPriorFree:
    def test_planes_from_line_cues(self, room):
        scene, _, regions, anchors = room
        total = 0
        for i in range(4):
            c = anchors.candidates(i)
            pp = plane_cues_prior_free(scene.cameras[i], scene.load_image(i), regions[i], anchors.xyz[c],
                                       anchors.group[c], PlaneConfig())
            total += len(pp.xyz)
            if len(pp.xyz):
                assert np.mean(distance_to_surface(pp.xyz) < 0.03) > 0.9
                assert _wall_normals_ok(pp.xyz, pp.normal) > 0.9
        assert total > 3000

    def test_one_line_does_not_fix_a_plane(self, room):
        scene, _, regions, _ = room
        lines = fake_line_cues(scene.cameras)
        cam = scene.cameras[1]
        # keep the single longest line that projects into the view
        uv, z = cam.project(lines.points)
        vis = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height)
        best = np.bincount(lines.point_line[vis]).argmax()
        sel = lines.point_line == best
        pp = plane_cues_prior_free(cam, scene.load_image(1), regions[1], lines.points[sel],
                                   lines.point_line[sel], PlaneConfig())
        assert len(pp.xyz) == 0
        assert set(pp.rejected) & {"single_line", "degenerate_anchors", "too_few_anchors"}

    def test_held_out_residuals(self):
        """Each group is predicted by the plane of the others: SfM points on a wall z = 2 and a line
        on the wall agree; a line 6 cm in front of the wall (the edge of an object) does not, although
        a plane fitted to all of them passes within 2 cm of every group."""
        rng = np.random.default_rng(4)
        wall = np.column_stack([rng.uniform(-0.5, 0.5, 6), rng.uniform(-0.5, 0.5, 6), np.full(6, 2.0)])
        t = np.linspace(-0.5, 0.5, 30)[:, None]
        on_wall = np.array([0.0, 0.6, 2.0]) + t * [1.0, 0.0, 0.0]
        in_front = np.array([0.0, 0.6, 1.94]) + t * [1.0, 0.0, 0.0]
        g = np.r_[-1 - np.arange(6), np.zeros(30, int)]
        n0 = np.array([0.0, 0.0, 1.0])
        _, r = loo_group_residuals(np.concatenate([wall, on_wall]), g, n0, 0.01, max_std=0.015)
        assert np.nanmax(r) < 1e-9
        ug, r = loo_group_residuals(np.concatenate([wall, in_front]), g, n0, 0.01, max_std=0.015)
        assert r[ug == 0][0] > 0.05 and ug[np.nanargmax(r)] == 0  # the line is the worst-predicted group
        fit = AnchoredPlane(np.concatenate([wall, in_front]), np.r_[np.ones(6), np.full(30, 1 / 30)], n0, 0.01)
        assert abs(fit.residual[6:].mean()) < 0.5 * r[ug == 0][0]  # in-sample, the line half hides
        # a group the others cannot pin down (the only anchor far off their span) is not tested
        _, r = loo_group_residuals(np.concatenate([wall[:3], in_front + [0, 3.0, 0]]),
                                   np.r_[-1 - np.arange(3), np.zeros(30, int)], n0, 0.01, max_std=0.015)
        assert np.isnan(r[-1])
        assert np.all(np.isnan(loo_group_residuals(wall[:2], g[:2], n0, 0.01, 0.015)[1]))  # < 3 groups

    def test_held_out_test_drops_an_off_surface_line(self):
        rng = np.random.default_rng(5)
        wall = np.column_stack([rng.uniform(-0.5, 0.5, 8), rng.uniform(-0.5, 0.5, 8), np.full(8, 2.0)])
        t = np.linspace(-0.5, 0.5, 30)[:, None]
        lines = [np.array([0.0, y, z]) + t * [1.0, 0.0, 0.0] for y, z in ((0.6, 1.94), (-0.6, 2.0))]
        lines.append(np.array([-0.6, 0.0, 2.0]) + t * [0.0, 1.0, 0.0])
        P = np.concatenate([wall, *lines])
        g = np.r_[-1 - np.arange(8), np.repeat([0, 1, 2], 30)]
        cfg = PlaneConfig()
        inl, why = _held_out_inliers(P, g, np.ones(len(P), bool), np.array([0.0, 0.0, 1.0]), cfg)
        assert why is None and not inl[g == 0].any() and inl[g != 0].all()
        cfg.free_loo_drop = False
        _, why = _held_out_inliers(P, g, np.ones(len(P), bool), np.array([0.0, 0.0, 1.0]), cfg)
        assert why == "anchors_fail_held_out_test"

    def test_parallel_lines_are_no_evidence(self, room):
        """Two parallel lines on different surfaces (a wall corner and a box edge 1 m in front)
        are coplanar, as any two parallel lines are: no plane from them alone."""
        from geocues.plane_regions import lines_confirm_plane

        t = np.linspace(0, 1, 30)[:, None]
        corner = np.array([0.0, 0.0, 4.0]) + t * [0, 1.0, 0]
        box = np.array([-1.0, 0.2, 3.0]) + t * [0, 0.5, 0]
        floor = np.array([0.0, 1.0, 4.0]) + t * [-1.0, 0, -0.5]
        g = np.r_[np.zeros(30, int), np.ones(30, int)]
        assert not lines_confirm_plane(np.concatenate([corner, box]), g)
        assert lines_confirm_plane(np.concatenate([corner, floor]), g)  # crossing lines: evidence
        third = np.array([1.0, 0.0, 4.0]) + t * [0, 1.0, 0]
        assert lines_confirm_plane(np.concatenate([corner, box, third]), np.r_[g, np.full(30, 2)])

    def test_no_anchors(self, room):
        scene, _, regions, _ = room
        pp = plane_cues_prior_free(scene.cameras[0], scene.load_image(0), regions[0], np.zeros((0, 3)),
                                   np.zeros(0, np.int64), PlaneConfig())
        assert len(pp.xyz) == 0 and pp.rejected.get("too_few_anchors", 0) == pp.n_regions > 0
        assert np.all(np.isfinite(pp.xyz))
