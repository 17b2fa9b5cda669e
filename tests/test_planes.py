"""Plane-like cues, with and without depth priors, on the synthetic room."""

from __future__ import annotations

import numpy as np
import pytest

from geocues.depth_align import Anchors
from geocues.planes import (PlaneConfig, fit_plane_ransac, plane_cues_prior_free, plane_cues_with_prior,
                            ray_plane_depth, voxel_downsample)
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
        assert len(snap.xyz) > 500 and len(raw.xyz) > 500
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

    def test_no_anchors(self, room):
        scene, _, regions, _ = room
        pp = plane_cues_prior_free(scene.cameras[0], scene.load_image(0), regions[0], np.zeros((0, 3)),
                                   np.zeros(0, np.int64), PlaneConfig())
        assert len(pp.xyz) == 0 and pp.rejected.get("too_few_anchors", 0) == pp.n_regions > 0
        assert np.all(np.isfinite(pp.xyz))
