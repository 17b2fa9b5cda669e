"""`geocues undistort`: what a PINHOLE scene keeps, what a warped scene leaves behind."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from geocues.scene import Scene


class TestUndistort:
    """A SIMPLE_RADIAL scene whose only content is a bright dot at the distorted projection of a known
    3D point: after undistortion the dot must sit at the PINHOLE projection in the new camera."""

    f, k, w, h = 100.0, 0.25, 160, 120

    def _distort(self, xn: np.ndarray) -> np.ndarray:
        r2 = (xn ** 2).sum(-1, keepdims=True)
        return xn * (1 + self.k * r2) * self.f + [self.w / 2, self.h / 2]  # COLMAP SIMPLE_RADIAL

    def _make(self, root: Path, X: np.ndarray) -> None:
        (root / "images").mkdir(parents=True)
        (root / "sparse" / "0").mkdir(parents=True)
        uv = self._distort(X[:2] / X[2])
        j, i = np.meshgrid(np.arange(self.w) + 0.5, np.arange(self.h) + 0.5)  # pixel centres
        blob = np.exp(-((j - uv[0]) ** 2 + (i - uv[1]) ** 2) / (2 * 1.5 ** 2))
        cv2.imwrite(str(root / "images" / "a.png"), np.repeat((blob * 255).round().astype(np.uint8)[..., None], 3, 2))
        m = root / "sparse" / "0"
        (m / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {self.w} {self.h} {self.f} {self.w / 2} {self.h / 2} {self.k}\n")
        (m / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")  # identity pose
        (m / "points3D.txt").write_text("")

    def test_dot_lands_on_pinhole_projection(self, tmp_path: Path):
        from geocues.undistort import UndistortConfig, run

        X = np.array([0.45, -0.3, 1.0])  # off-centre, where distortion moves it by several pixels
        self._make(tmp_path / "d", X)
        with pytest.raises(ValueError, match="geocues undistort"):
            Scene.load(tmp_path / "d")
        run(UndistortConfig(), tmp_path / "d", tmp_path / "u")
        s = Scene.load(tmp_path / "u")
        cam = s.cameras[0]
        img = s.load_image(0)[..., 0]
        j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        wgt = np.where(img > 0.3, img, 0)
        dot = np.array([(wgt * j).sum(), (wgt * i).sum()]) / wgt.sum()
        uv, _ = cam.project(X[None])
        moved = np.linalg.norm(self._distort(X[:2] / X[2]) - (X[:2] / X[2] * self.f + [self.w / 2, self.h / 2]))
        assert moved > 3.0  # the test would notice a missing undistortion
        np.testing.assert_allclose(dot, uv[0], atol=0.3)

    def test_refuses_in_place_and_existing_out(self, tmp_path: Path):
        from geocues.undistort import UndistortConfig, run

        self._make(tmp_path / "d", np.array([0.1, 0.1, 1.0]))
        with pytest.raises(ValueError, match="must differ"):
            run(UndistortConfig(), tmp_path / "d", tmp_path / "d")
        run(UndistortConfig(), tmp_path / "d", tmp_path / "u")
        with pytest.raises(ValueError, match=str(tmp_path / "u" / "sparse") + ".*--overwrite"):
            run(UndistortConfig(), tmp_path / "d", tmp_path / "u")
        run(UndistortConfig(), tmp_path / "d", tmp_path / "u", overwrite=True)
        assert sorted(p.name for p in (tmp_path / "u").iterdir()) == ["images", "sparse"]


def test_undistort_of_a_pinhole_scene_keeps_its_priors(tmp_path: Path):
    """Nothing is warped in a scene already pinhole: its priors still fit the copied images (they were
    dropped with 'they would need the same warp')."""
    from cues_synth import make_room_scene
    from geocues.undistort import UndistortConfig, run

    root = make_room_scene(tmp_path / "room", n_views=4, w=64, h=48, priors="all")
    out = run(UndistortConfig(), root, tmp_path / "und")
    a, b = Scene.load(root), Scene.load(out)
    assert b.has_depth_priors
    np.testing.assert_array_equal(a.depth_prior(1), b.depth_prior(1))


@pytest.mark.parametrize("distorted", [False, True])
def test_undistort_leaves_gt_depth_of_warped_images_behind(tmp_path: Path, caplog, distorted: bool):
    """gt/ was linked whole, so a warped scene's exact depth (the ablation's floor, splat render's GT-depth
    panels) was resized onto the undistorted images without a word (new-user audit): the mesh is carried,
    the per-pixel maps only where nothing was warped."""
    from cues_synth import make_room_scene
    from geocues.undistort import UndistortConfig, run

    root = make_room_scene(tmp_path / "room", n_views=4, w=64, h=48)
    (root / "gt" / "depth").mkdir(parents=True)
    np.save(root / "gt" / "depth" / "00000.npy", np.ones((48, 64), np.float32))
    (root / "gt" / "mesh.ply").write_text("ply\n")
    if distorted:
        (root / "sparse" / "0" / "cameras.txt").write_text("1 SIMPLE_RADIAL 64 48 40 32 24 0.05\n")
    with caplog.at_level("WARNING", logger="geocues"):
        out = run(UndistortConfig(), root, tmp_path / "und")
    gt = out / "gt"
    assert (gt / "mesh.ply").read_text() == "ply\n"
    assert (gt / "depth").exists() == (not distorted)
    assert gt.is_symlink() == (not distorted)  # a real folder of links only when something stayed behind
    assert ("gt/depth not carried over" in caplog.text) == distorted, caplog.text


def test_an_overwrite_remakes_gt_and_later_maps_stay_out(tmp_path: Path, caplog):
    """The first `_carry_gt` kept an existing OUT/gt: an OUT made before (gt/ linked whole, with the
    distorted images' depth) kept it through --overwrite, and a warped scene without gt/depth at the time
    got gt/ linked whole, so a gt/depth added later reached OUT (review)."""
    from cues_synth import make_room_scene
    from geocues.undistort import UndistortConfig, run

    root = make_room_scene(tmp_path / "room", n_views=4, w=64, h=48)
    (root / "gt").mkdir()
    (root / "gt" / "mesh.ply").write_text("ply\n")
    (root / "sparse" / "0" / "cameras.txt").write_text("1 SIMPLE_RADIAL 64 48 40 32 24 0.05\n")
    out = tmp_path / "und"
    out.mkdir()
    (out / "gt").symlink_to((root / "gt").resolve())  # what the earlier version left
    run(UndistortConfig(), root, out)
    (root / "gt" / "depth").mkdir()  # added after the run
    np.save(root / "gt" / "depth" / "00000.npy", np.ones((48, 64), np.float32))
    assert not (out / "gt").is_symlink() and not (out / "gt" / "depth").exists()
    with caplog.at_level("WARNING", logger="geocues"):
        run(UndistortConfig(), root, out, overwrite=True)
    assert not (out / "gt" / "depth").exists() and (out / "gt" / "mesh.ply").read_text() == "ply\n"
    assert "gt/depth not carried over" in caplog.text
    (out / "gt" / "notes.txt").write_text("mine")  # a folder holding the user's own files is kept
    run(UndistortConfig(), root, out, overwrite=True)
    assert (out / "gt" / "notes.txt").read_text() == "mine"
