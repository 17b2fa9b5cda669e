"""Benchmark rooms (evaluation.rooms): determinism, exact GT, documented prior errors, loading."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from evaluation.rooms.layout import make_room_geometry
from evaluation.rooms.priors import PriorConfig, simulate_depth_prior, simulate_normal_prior
from evaluation.rooms.trajectory import TrajectoryConfig, make_trajectory
from evaluation.rooms.writer import GENERATOR_VERSION, RoomConfig, make_room
from geocues.scene import Scene

TINY = RoomConfig(width=96, height=72, n_views=5, sfm=False)


@pytest.fixture(scope="module")
def rooms(tmp_path_factory) -> dict[str, Path]:
    """Tiny textured rooms (seed 0 twice, seed 1) and a tiny bare room, SfM off."""
    base = tmp_path_factory.mktemp("rooms")
    out = {"a": make_room(base / "a", TINY), "b": make_room(base / "b", TINY),
           "c": make_room(base / "c", replace(TINY, seed=1)),
           "bare": make_room(base / "bare", replace(TINY, layout="bare"))}
    return out


def _files(root: Path, pattern: str) -> list[Path]:
    files = sorted(root.glob(pattern))
    assert files, f"no {pattern} in {root}"
    return files


def _o3d_scene_and_mesh(path: Path):
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    V = np.asarray(mesh.vertices)
    F = np.asarray(mesh.triangles)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(vertex_positions=o3d.core.Tensor(V.astype(np.float32)),
                        triangle_indices=o3d.core.Tensor(F.astype(np.uint32)))
    return scene, V, F


class TestDeterminism:
    def test_same_seed_identical(self, rooms):
        a, b = rooms["a"], rooms["b"]
        assert (a / "gt/mesh.ply").read_bytes() == (b / "gt/mesh.ply").read_bytes()
        for pat in ("images/*.png", "gt/depth/*.npy", "gt/normal/*.npy", "priors/depth/*.npy",
                    "priors/normal/*.npy"):
            fa, fb = _files(a, pat), _files(b, pat)
            assert [f.name for f in fa] == [f.name for f in fb]
            for x, y in zip(fa, fb):
                assert x.read_bytes() == y.read_bytes(), f"{x} differs from {y}"
        assert json.loads((a / "scene.json").read_text()) == json.loads((b / "scene.json").read_text())

    def test_other_seed_differs(self, rooms):
        a, c = rooms["a"], rooms["c"]
        assert (a / "gt/mesh.ply").read_bytes() != (c / "gt/mesh.ply").read_bytes()
        ia, ic = _files(a, "images/*.png"), _files(c, "images/*.png")
        assert all(x.read_bytes() != y.read_bytes() for x, y in zip(ia, ic))
        pa, pc = (np.load(_files(r, "priors/depth/*.npy")[0]) for r in (a, c))
        assert not np.array_equal(pa, pc)

    def test_layout_independent_of_view_count(self):
        r1 = make_room_geometry("textured", np.random.default_rng(np.random.SeedSequence(3).spawn(4)[0]))
        r2 = make_room_geometry("textured", np.random.default_rng(np.random.SeedSequence(3).spawn(4)[0]))
        np.testing.assert_array_equal(r1.mesh.vertices, r2.mesh.vertices)


class TestGroundTruth:
    def test_depth_backprojects_onto_mesh(self, rooms):
        """Regression guard for the pixel convention too: rays through (j+0.5, i+0.5)."""
        import open3d as o3d

        root = rooms["a"]
        scene = Scene.load(root, test_every=0)
        rc, _, _ = _o3d_scene_and_mesh(root / "gt/mesh.ply")
        for cam in scene.cameras:
            depth = np.load(root / "gt/depth" / f"{cam.stem}.npy")
            assert depth.shape == (cam.height, cam.width) and depth.dtype == np.float32
            assert (depth > 0).all(), "a closed room has a hit at every pixel"
            Xc = cam.pixel_rays() * depth[..., None]  # [H, W, 3]
            Xw = (Xc.reshape(-1, 3) - cam.t) @ cam.R  # R^T (x - t)
            dist = rc.compute_distance(query_points=o3d.core.Tensor(Xw.astype(np.float32))).numpy()
            assert dist.max() < 1e-4, f"{cam.name}: max distance {dist.max():.2e} m"

    def test_normals_match_mesh_faces(self, rooms):
        import open3d as o3d

        root = rooms["a"]
        scene = Scene.load(root, test_every=0)
        rc, V, F = _o3d_scene_and_mesh(root / "gt/mesh.ply")
        fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        fn /= np.linalg.norm(fn, axis=1, keepdims=True)
        for cam in scene.cameras:
            d_world = cam.pixel_rays().reshape(-1, 3) @ cam.R  # R^T d
            rays = np.concatenate([np.broadcast_to(cam.center, d_world.shape), d_world], axis=1)
            tri = rc.cast_rays(rays=o3d.core.Tensor(rays.astype(np.float32)))["primitive_ids"].numpy()
            n_w = fn[tri.astype(np.int64)]
            # mesh normals face the free space: every visible face points back at the camera
            assert (np.einsum("ij,ij->i", n_w, d_world) < 0).all()
            gt = np.load(root / "gt/normal" / f"{cam.stem}.npy").reshape(-1, 3)
            np.testing.assert_allclose(gt, n_w @ cam.R.T, atol=1e-5)

    def test_mesh_materials(self, rooms):
        root = rooms["a"]
        meta = json.loads((root / "scene.json").read_text())
        tm = np.load(root / "gt/triangle_material.npy")
        _, _, F = _o3d_scene_and_mesh(root / "gt/mesh.ply")
        assert tm.shape == (len(F),)
        assert tm.min() >= 0 and tm.max() < len(meta["room"]["materials"])
        kinds = {m["kind"] for m in meta["room"]["materials"]}
        assert {"poster", "rug", "wood_floor", "fabric", "book"} <= kinds


class TestPriors:
    def test_metadata_says_simulated(self, rooms):
        meta = json.loads((rooms["a"] / "scene.json").read_text())
        assert meta["priors"]["simulated"] is True
        assert meta["layout"] == "textured" and meta["seed"] == 0
        assert meta["generator"]["version"] == GENERATOR_VERSION
        assert set(meta["priors"]["per_image"]) == {f"{k:05d}" for k in range(TINY.n_views)}
        assert meta["priors"]["config"] == PriorConfig().to_dict()

    def test_depth_prior_is_documented_affine_distortion(self, rooms):
        root, cfg = rooms["a"], PriorConfig()
        meta = json.loads((root / "scene.json").read_text())
        for f in _files(root, "gt/depth/*.npy"):
            gt = np.load(f)
            prior = np.load(root / "priors/depth" / f.name)
            par = meta["priors"]["per_image"][f.stem]["depth"]
            assert (prior > 0).all()
            undone = (prior - par["shift"]) / par["scale"]
            rel = np.abs(undone - gt) / gt
            assert 1e-4 < np.median(rel) < 3 * cfg.depth_warp + 3 * cfg.depth_noise
            # best affine fit gt ~ alpha * prior + beta: residual > 0 but bounded
            A = np.stack([prior.ravel(), np.ones(prior.size)], axis=1)
            coef, *_ = np.linalg.lstsq(A, gt.ravel().astype(np.float64), rcond=None)
            resid = np.sqrt(np.mean((A @ coef - gt.ravel()) ** 2)) / np.median(gt)
            assert 1e-4 < resid < 0.15, resid

    def test_depth_prior_without_distortions_is_exactly_affine(self, rooms):
        gt = np.load(_files(rooms["a"], "gt/depth/*.npy")[0])
        cfg = PriorConfig(depth_warp=0.0, depth_noise=0.0, depth_edge_blur_px=0.0)
        prior, par = simulate_depth_prior(gt, np.random.default_rng(0), cfg)
        np.testing.assert_allclose((prior - par["shift"]) / par["scale"], gt, rtol=1e-5)
        assert cfg.depth_scale_min <= par["scale"] <= cfg.depth_scale_max

    def test_normal_prior_close_but_not_equal(self, rooms):
        root = rooms["a"]
        scene = Scene.load(root, test_every=0)
        for cam in scene.cameras:
            gt = np.load(root / "gt/normal" / f"{cam.stem}.npy")
            pr = scene.normal_prior(cam.index)
            assert pr.shape == gt.shape
            np.testing.assert_allclose(np.linalg.norm(pr, axis=-1), 1.0, atol=1e-5)
            assert (np.einsum("hwc,hwc->hw", pr, cam.pixel_rays()) < 0).all(), "must face camera"
            ang = np.degrees(np.arccos(np.clip(np.einsum("hwc,hwc->hw", pr, gt), -1, 1)))
            assert 0.3 < np.median(ang) < 10.0, np.median(ang)

    def test_normal_prior_rounds_creases(self):
        """Blur acts at a crease (two faces meeting) and nowhere else."""
        n = np.zeros((40, 64, 3), np.float32)
        n[:, :32] = [0.0, 0.0, -1.0]
        n[:, 32:] = [-np.sqrt(0.5), 0.0, -np.sqrt(0.5)]
        rays = np.broadcast_to(np.array([0.0, 0.0, 1.0], np.float32), n.shape)
        cfg = PriorConfig(normal_warp_deg=0.0, normal_noise=0.0, normal_blur_px=3.0 * 640 / 64)
        pr, _ = simulate_normal_prior(n, rays, np.random.default_rng(0), cfg)
        ang = np.degrees(np.arccos(np.clip(np.einsum("hwc,hwc->hw", pr, n), -1, 1)))
        assert ang[:, 30:34].min() > 5.0 and ang[:, :5].max() < 1.0


class TestSceneAndLayouts:
    def test_loads_as_scene(self, rooms):
        scene = Scene.load(rooms["a"])
        assert len(scene) == TINY.n_views and scene.test_indices == [0]
        cam = scene.cameras[1]
        assert (cam.width, cam.height) == (96, 72)
        np.testing.assert_allclose(cam.K, TINY.intrinsics(), atol=1e-9)
        assert scene.has_depth_priors and scene.has_normal_priors and scene.gt_mesh_path is not None
        assert scene.load_image(1).shape == (72, 96, 3) and scene.depth_prior(1).shape == (72, 96)
        assert len(scene.points) == 0  # sfm off

    def test_bare_room_is_less_textured(self, rooms):
        from geocues.scene import Scene as S

        def grad_energy(root):
            sc = S.load(root, test_every=0)
            g = []
            for i in range(len(sc)):
                im = sc.load_image(i).mean(axis=-1)
                g.append(np.abs(np.diff(im, axis=1)).mean() + np.abs(np.diff(im, axis=0)).mean())
            return float(np.mean(g))

        assert grad_energy(rooms["a"]) > 1.5 * grad_energy(rooms["bare"])
        meta = json.loads((rooms["bare"] / "scene.json").read_text())
        assert len(meta["room"]["materials"]) < 10

    @pytest.mark.parametrize("layout", ["textured", "bare"])
    def test_room_sizes_and_trajectory(self, layout):
        for seed in range(4):
            room = make_room_geometry(layout, np.random.default_rng(seed))
            W, D, H = room.size
            assert 4 <= W <= 6 and 3 <= D <= 5 and 2.5 <= H <= 3
            v = room.mesh.vertices
            assert v.min() >= -1e-9 and (v.max(axis=0) <= np.array(room.size) + 1e-9).all()
            cfg = TrajectoryConfig()
            poses = make_trajectory(room.size, room.mesh.boxes, 60, np.random.default_rng(seed), cfg)
            C = np.array([-R.T @ t for R, t in poses])
            assert (C[:, 2] >= cfg.height_min - 1e-9).all() and (C[:, 2] <= cfg.height_max + 1e-9).all()
            assert (C[:, :2] > cfg.clearance).all() and (C[:, :2] < np.array([W, D]) - cfg.clearance).all()
            fwd = np.array([R[2] for R, _ in poses])
            step = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", fwd, np.roll(fwd, -1, 0)), -1, 1)))
            assert step.max() < 20.0, "consecutive views must overlap"
            assert np.linalg.norm(np.diff(C, axis=0), axis=1).max() < 0.5

    def test_bad_input(self, tmp_path, rooms):
        with pytest.raises(ValueError, match="layout"):
            make_room(tmp_path / "x", replace(TINY, layout="castle"))
        with pytest.raises(ValueError, match="already exists"):
            make_room(rooms["a"], TINY)
        # --image-noise nan/-1 gave noise-free images, --focal -525 a mirrored camera, --priors.depth-warp 100
        # negative prior depths, --trajectory.clearance nan was accepted
        for change, said in ((dict(image_noise=float("nan")), "--image-noise is a standard deviation"),
                             (dict(image_noise=-1.0), "--image-noise is a standard deviation"),
                             (dict(focal=-525.0), "--focal must be a finite focal length > 0"),
                             (dict(priors=replace(TINY.priors, depth_warp=100.0)), "--priors.depth-warp must be under 1/3"),
                             (dict(trajectory=replace(TINY.trajectory, clearance=float("nan"))),
                              "--trajectory.clearance must be a finite number")):
            with pytest.raises(ValueError, match=re.escape(said)):
                make_room(tmp_path / "x", replace(TINY, **change))
        assert not (tmp_path / "x").exists()


def test_sfm_points_lie_on_the_gt_mesh(tmp_path):
    """SfM really runs on the renders (known poses) and its points land on the GT surface."""
    pytest.importorskip("geocues.sfm")
    import open3d as o3d

    root = make_room(tmp_path / "room", RoomConfig(width=256, height=192, n_views=30, sfm=True))
    scene = Scene.load(root)
    assert len(scene.points) > 100
    assert not (root / "cache").exists()
    rc, _, _ = _o3d_scene_and_mesh(root / "gt/mesh.ply")
    d = rc.compute_distance(query_points=o3d.core.Tensor(scene.points.xyz.astype(np.float32))).numpy()
    assert np.median(d) < 0.01 and (d < 0.05).mean() > 0.8, (np.median(d), (d < 0.05).mean())
    report = json.loads((root / "make_room_report.json").read_text())
    assert report["sfm"]["run"] and str(tmp_path / "room") in json.dumps(report)
    assert ".room." not in json.dumps(report), "temporary folder name leaked into the report"


def test_cli_make_room(tmp_path, capsys):
    from cli.evaluate_cli import main

    out = tmp_path / "cli_room"
    rc = main(["make-room", str(out), "--layout", "bare", "--seed", "2", "--width", "48",
               "--height", "36", "--n-views", "3", "--no-sfm"])
    assert rc == 0 and str(out) in capsys.readouterr().out
    meta = json.loads((out / "scene.json").read_text())
    assert (meta["layout"], meta["seed"], meta["camera"]["width"]) == ("bare", 2, 48)
    assert len(list((out / "images").glob("*.png"))) == 3
    assert main(["make-room", str(out), "--no-sfm"]) == 1  # exists, no --overwrite: one clear error
    assert "already exists" in capsys.readouterr().err
