"""`geocues sfm`: pairs from poses, known-pose verification, triangulation and mapping on a tiny
ICL scene (10 frames at 320x240, checked against the reference mesh), caching, output folders."""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from cli.geocues_cli import main as geocues_main
from geocues import sfm_steps
from geocues.colmap_io import find_model_dir, quat_wxyz_to_rotmat, read_model, write_model
from geocues.scene import Scene
from geocues.sfm import SfmConfig, run

FRAMES = list(range(0, 50, 5))  # 10 frames along 0.6 m of the ICL trajectory


def make_tiny_icl(icl: Path, root: Path, frames: list[int] = FRAMES, scale: int = 2) -> Path:
    """Copy ICL frames downscaled by ``scale`` with an exactly scaled PINHOLE model, no points."""
    images, _ = read_model(icl / "sparse" / "0")
    sel = [images[i] for i in frames]
    (root / "images").mkdir(parents=True)
    (root / "gt").mkdir()
    for im in sel:
        img = cv2.imread(str(icl / "images" / im.name))
        im.width, im.height = img.shape[1] // scale, img.shape[0] // scale
        cv2.imwrite(str(root / "images" / im.name), cv2.resize(img, (im.width, im.height),
                                                              interpolation=cv2.INTER_AREA))
        im.K = np.diag([1.0 / scale, 1.0 / scale, 1.0]) @ im.K  # COLMAP pixel centres: exact
    write_model(root / "sparse" / "0", sel)
    (root / "gt" / "mesh.ply").symlink_to(icl / "reference_mesh.ply")
    return root


pytestmark = pytest.mark.usefixtures("restore_log_handlers")  # conftest.py


def _report(scene: Path) -> dict:
    return json.loads((scene / "sfm_report.json").read_text())


@pytest.fixture(scope="module")
def tiny(icl_dir: Path, tmp_path_factory) -> Path:
    return make_tiny_icl(icl_dir, tmp_path_factory.mktemp("tiny") / "scene")


@pytest.fixture(scope="module")
def triangulated(tiny: Path, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("tri") / "out"
    done = run(SfmConfig(), tiny, out)
    assert done == out  # the stage returns the scene folder it wrote
    return out, _report(out)


# ----------------------------------------------------------------------------- units
class TestSelectPairs:
    def test_nearest_and_angle_limit(self):
        centers = np.stack([np.arange(10) * 0.1, np.zeros(10), np.zeros(10)], 1)  # a line
        dirs = np.tile([0.0, 0.0, 1.0], (10, 1))
        dirs[9] = [0.0, 0.0, -1.0]  # the last camera looks the other way
        pairs = sfm_steps.select_pairs(centers, dirs, k=2, max_angle=60)
        assert (0, 1) in pairs and (0, 2) in pairs and (0, 3) not in pairs
        assert all(9 not in p for p in pairs)
        assert all(i < j for i, j in pairs) and len(set(pairs)) == len(pairs)
        assert all(j - i <= 2 for i, j in pairs)

    def test_stride_widens_baselines(self):
        centers = np.stack([np.arange(20) * 0.1, np.zeros(20), np.zeros(20)], 1)
        dirs = np.tile([0.0, 0.0, 1.0], (20, 1))
        near = sfm_steps.select_pairs(centers, dirs, k=2, max_angle=60, stride=1)
        wide = sfm_steps.select_pairs(centers, dirs, k=2, max_angle=60, stride=2)
        gaps = lambda ps: np.array([j - i for i, j in ps])  # noqa: E731
        assert gaps(wide).mean() > gaps(near).mean()
        assert gaps(near).max() <= 2 and gaps(wide).max() <= 3
        assert (gaps(wide) >= 2).sum() > (gaps(near) >= 2).sum()

    def test_bad_shapes(self):
        with pytest.raises(ValueError, match=r"\[N, 3\]"):
            sfm_steps.select_pairs(np.zeros((4, 2)), np.zeros((4, 2)), k=2, max_angle=60)


def test_sampson_matches_pycolmap():
    rng = np.random.default_rng(0)
    F = rng.normal(size=(3, 3))
    x1, x2 = rng.uniform(0, 640, (100, 2)), rng.uniform(0, 480, (100, 2))
    want = np.asarray(pycolmap.compute_squared_sampson_error(x1, x2, F))
    np.testing.assert_allclose(sfm_steps.sampson_sq(F, x1, x2), want, rtol=1e-9)


def test_align_to_reference_recovers_similarity():
    rng = np.random.default_rng(1)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 64, 48) if hasattr(
        pycolmap.Camera, "create_from_model_name") else pycolmap.Camera(
        camera_id=1, model="PINHOLE", width=64, height=48, params=[100.0, 100.0, 32.0, 24.0])
    rec.add_camera_with_trivial_rig(cam)
    ref = pycolmap.Reconstruction()
    ref.add_camera_with_trivial_rig(cam)
    s, R, t = 2.5, quat_wxyz_to_rotmat(rng.normal(size=4)), rng.normal(size=3)  # ref_from_rec
    for i in range(1, 6):
        Ri = quat_wxyz_to_rotmat(rng.normal(size=4))
        ci = np.array([0.1 * i, 0.0, 0.0])  # a straight trajectory: centres alone are ambiguous
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(Ri), -Ri @ ci)
        pose_ref = pycolmap.Rigid3d(pycolmap.Rotation3d(Ri @ R.T), -(Ri @ R.T) @ (s * R @ ci + t))
        for r, p in ((rec, pose), (ref, pose_ref)):
            im = pycolmap.Image(image_id=i, camera_id=1, name=f"{i}.png")
            r.add_image_with_trivial_frame(im, p)
    sim, err = sfm_steps.align_to_reference(rec, ref)
    assert err < 1e-9
    assert abs(sim.scale - s) < 1e-9
    np.testing.assert_allclose(np.asarray(sim.rotation.matrix()), R, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sim.translation), t, atol=1e-9)


# ----------------------------------------------------------------------------- bad input
class TestBadInput:
    def test_no_images_folder(self, tmp_path: Path):
        with pytest.raises(FileNotFoundError, match=str(tmp_path / "images")):
            run(SfmConfig(), tmp_path)

    def test_a_folder_of_photos_is_told_the_scene_layout(self, tmp_path: Path):
        """The first thing a user tries: the folder of photos itself, or its images/ folder."""
        photos = tmp_path / "photos"
        photos.mkdir()
        for k in range(3):
            cv2.imwrite(str(photos / f"{k}.jpg"), np.zeros((8, 8, 3), np.uint8))
        with pytest.raises(FileNotFoundError, match=f"{photos} holds 3 images itself.*move them into {photos / 'images'}/"):
            run(SfmConfig(), photos)
        photos.rename(tmp_path / "images")
        with pytest.raises(FileNotFoundError, match=f"pass the scene folder above it, {tmp_path}$"):
            run(SfmConfig(), tmp_path / "images")

    def test_triangulate_without_model(self, tmp_path: Path):
        (tmp_path / "images").mkdir()
        with pytest.raises(FileNotFoundError, match=r"needs a posed model.*cameras\.txt"):
            run(SfmConfig(mode="triangulate"), tmp_path)

    def test_map_with_too_few_images(self, tmp_path: Path):
        (tmp_path / "images").mkdir()
        cv2.imwrite(str(tmp_path / "images" / "a.png"), np.zeros((8, 8, 3), np.uint8))
        with pytest.raises(ValueError, match="at least 2 images"):
            run(SfmConfig(), tmp_path)

    def test_image_of_model_missing(self, tmp_path: Path):
        (tmp_path / "images").mkdir()
        from geocues.colmap_io import RawImage
        write_model(tmp_path / "sparse" / "0", [RawImage(1, 1, "x.png", "PINHOLE", 8, 8, np.eye(3),
                                                         np.eye(3), np.zeros(3))])
        with pytest.raises(FileNotFoundError, match=str(tmp_path / "images" / "x.png")):
            run(SfmConfig(), tmp_path)

    def test_cli_reports_error_in_one_line(self, tmp_path: Path, capsys):
        assert geocues_main(["sfm", str(tmp_path / "nope")]) == 1
        err = capsys.readouterr().err
        assert "error" in err and str(tmp_path / "nope") in err


# ----------------------------------------------------------------------------- tiny ICL
class TestTriangulate:
    def test_points_lie_on_the_reference_mesh(self, triangulated):
        out, rep = triangulated
        assert rep["mode"] == "triangulate" and rep["registered_images"] == 10
        assert rep["points"] > 400 and rep["verified_pairs"] >= 30
        assert rep["mean_track_length"] >= 3.0
        assert rep["gt_check"]["within_5cm"] > 0.9 and rep["gt_check"]["within_2cm"] > 0.65
        assert json.loads((out / "sfm_report.json").read_text())["points"] == rep["points"]

    def test_model_is_consistent_and_loads(self, triangulated, tiny: Path):
        out, rep = triangulated
        s = Scene.load(out)
        assert len(s) == 10 and len(s.points) == rep["points"]
        cfg = SfmConfig()
        assert s.points.track_length.min() >= 3  # two-view tracks are ignored
        assert s.points.error.max() <= cfg.max_reproj_error + 1e-6
        # poses and intrinsics are those of the input model (fixed during triangulation)
        src, _ = read_model(tiny / "sparse" / "0")
        for a, b in zip(src, s.cameras):
            np.testing.assert_allclose(b.R, a.R, atol=1e-9)
            np.testing.assert_allclose(b.t, a.t, atol=1e-9)
            np.testing.assert_allclose(b.K, a.K, atol=1e-9)
        # every point reprojects within the error bound into the images that see it
        for i, idx in s.points.visible_in.items():
            uv, z = s.cameras[i].project(s.points.xyz[idx])
            assert (z > 0).all()
            assert ((uv >= 0) & (uv <= [s.cameras[i].width, s.cameras[i].height])).all()
        assert s.points.rgb.max() > 0  # colours were extracted

    def test_out_folder_links_and_source_untouched(self, triangulated, tiny: Path):
        out, _ = triangulated
        assert (out / "images").is_symlink() and (out / "images").resolve() == (tiny / "images").resolve()
        assert (out / "gt").is_symlink() and (out / "gt" / "mesh.ply").is_file()
        assert (out / "sparse" / "0" / "points3D.bin").is_file()
        assert len(read_model(tiny / "sparse" / "0")[1].ids) == 0  # the input model kept no points
        assert (out / "cache" / "sfm" / "database.db").is_file()

    def test_model_with_tracks_survives_bin_txt(self, triangulated, tmp_path: Path):
        out, _ = triangulated
        (tmp_path / "txt").mkdir()
        pycolmap.Reconstruction(str(out / "sparse" / "0")).write_text(str(tmp_path / "txt"))
        (i0, p0), (i1, p1) = read_model(out / "sparse" / "0"), read_model(tmp_path / "txt")
        assert [a.name for a in i0] == [b.name for b in i1]
        o0, o1 = np.argsort(p0.ids), np.argsort(p1.ids)
        np.testing.assert_array_equal(p0.ids[o0], p1.ids[o1])
        np.testing.assert_allclose(p0.xyz[o0], p1.xyz[o1], rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(p0.track_length[o0], p1.track_length[o1])

    def test_a_finished_out_needs_overwrite(self, tiny, triangulated, capsys):
        out, rep = triangulated
        before = (out / "sfm_report.json").read_text()
        assert geocues_main(["sfm", str(tiny), "-o", str(out)]) == 1
        assert "pass --overwrite to replace it" in capsys.readouterr().err
        assert (out / "sfm_report.json").read_text() == before  # untouched

    def test_rerun_reuses_cache_and_in_place_write(self, triangulated, tmp_path: Path):
        src, rep = triangulated
        out = tmp_path / "copy"
        shutil.copytree(src, out, symlinks=True)
        cfg = replace(SfmConfig(), check_gt=False)
        assert run(cfg, out) == out  # OUT is a scene itself: write in place, reuse its cache
        again = _report(out)
        assert abs(again["points"] - rep["points"]) <= 0.02 * rep["points"]  # threaded BA: not bit-exact
        assert again["seconds"]["match"] == 0.0 and again["seconds"]["extract"] < rep["seconds"]["extract"]
        assert again["model"] == str((out / "sparse" / "0").resolve())
        assert (out / "sparse" / "0" / "images.bin").is_file()  # a binary model replaced in place: binary
        model = out / "sparse" / "0"
        rec = pycolmap.Reconstruction(str(model))
        for f in model.iterdir():
            f.unlink()
        rec.write_text(str(model))  # the user's model in text, as a hand-written or converted one is
        run(cfg, out)
        files = {f.name for f in model.iterdir()}  # replaced in place by a text model, not by .bin files
        assert {"cameras.txt", "images.txt", "points3D.txt"} <= files and not any(f.endswith(".bin") for f in files)
        # changing a matching parameter re-matches but keeps the features
        third = _report(run(replace(cfg, num_neighbors=3, exhaustive_below=5), out))
        assert third["pairs"] < again["pairs"] and third["seconds"]["match"] > 0


class TestMap:
    def test_incremental_mapping_aligned_to_poses(self, tiny: Path, tmp_path: Path):
        out = tmp_path / "map"
        rep = _report(run(SfmConfig(mode="map", check_gt=False), tiny, out))
        assert rep["mode"] == "map" and rep["registered_images"] >= 9 and rep["points"] > 300
        got = {c.name: c for c in Scene.load(out).cameras}
        ref = {c.name: c for c in Scene.load(tiny).cameras}
        dc = [np.linalg.norm(got[n].center - ref[n].center) for n in got]
        dr = [np.degrees(np.arccos(np.clip((np.trace(got[n].R.T @ ref[n].R) - 1) / 2, -1, 1))) for n in got]
        assert np.median(dc) < 0.02 and max(dr) < 3.0  # 0.6 m trajectory, 320x240 images
        assert "scale" not in Scene.load(out).metadata  # aligned to the posed model: metric, not marked


def test_cli_info_and_sfm(triangulated, capsys, tmp_path: Path):
    out, rep = triangulated
    assert geocues_main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"points     {rep['points']}" in text and "cameras    10" in text and "gt mesh" in text
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, symlinks=True)  # cached features and matches: fast
    assert geocues_main(["sfm", str(copy), "--no-check-gt", "--min-tri-angle", "8"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert "config" not in printed  # the CLI prints the figures, the JSON file keeps the config
    assert 0 < printed["points"] < rep["points"]  # a larger minimum angle keeps fewer points
    assert printed["mode"] == "triangulate" and "gt_check" not in printed


def test_images_only_map_then_undistort(icl_dir: Path, tmp_path: Path, caplog):
    """No model at all: incremental mapping estimates a SIMPLE_RADIAL camera (focal near ICL's 262.5 at
    320x240); the scene is refused until `geocues undistort` makes it PINHOLE (points kept)."""
    from geocues.rescale import RescaleConfig, metric_warning
    from geocues.rescale import run as rescale
    from geocues.undistort import UndistortConfig
    from geocues.undistort import run as undistort

    scene = make_tiny_icl(icl_dir, tmp_path / "s")
    shutil.rmtree(scene / "sparse")
    cv2.imwrite(str(scene / "images" / "zz_lens_cap.png"), np.full((240, 320, 3), 40, np.uint8))  # no features
    with caplog.at_level(logging.WARNING, logger="geocues.sfm"):
        rep = _report(run(SfmConfig(check_gt=False), scene, tmp_path / "out"))
    assert rep["mode"] == "map" and 9 <= rep["registered_images"] < rep["images"] == 11 and rep["points"] > 300
    assert f"{11 - rep['registered_images']} of 11 images are not in the model (" in caplog.text
    assert "zz_lens_cap.png" in caplog.text
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    (cam,) = rec.cameras.values()
    assert cam.model.name == "SIMPLE_RADIAL" and abs(cam.params[0] / 262.5 - 1) < 0.05
    with pytest.raises(ValueError, match="undistort"):
        Scene.load(tmp_path / "out")
    undistort(UndistortConfig(), tmp_path / "out", tmp_path / "und")
    s = Scene.load(tmp_path / "und")
    assert len(s) == rep["registered_images"] and len(s.points) == rep["points"]
    # its unit is COLMAP's, not a metre: marked, carried by undistort, named by every metric warning
    assert s.metadata["scale"] == "arbitrary" and "images alone" in metric_warning(s)
    back = rescale(RescaleConfig(scale=1.0), tmp_path / "und", tmp_path / "metric")  # the user knows it is
    m = Scene.load(back)
    assert "scale" not in m.metadata and m.metadata["frame"] == "mapped from images"  # still its own frame
    # rescaling keeps the model whole: tracks (SOR, the visibility of each view) and positions
    assert (m.points.track_length >= 2).all() and np.array_equal(m.points.track_length, s.points.track_length)
    np.testing.assert_allclose(m.points.xyz, s.points.xyz, atol=1e-9)
    twice = Scene.load(rescale(RescaleConfig(scale=2.0), tmp_path / "und", tmp_path / "x2"))
    np.testing.assert_allclose(twice.points.xyz, 2 * s.points.xyz, atol=1e-9)
    np.testing.assert_allclose([c.center for c in twice.cameras], [2 * c.center for c in s.cameras], atol=1e-9)


def test_two_images_leave_no_point_and_say_how_to_keep_some(icl_dir: Path, tmp_path: Path, caplog):
    """Two photos: every track has two views, so the default (3 views, no two-view tracks) keeps no
    point, and the cues would start from nothing; the warning names the options that keep them."""
    import logging

    scene = make_tiny_icl(icl_dir, tmp_path / "two", frames=[0, 5])
    with caplog.at_level(logging.WARNING, logger="geocues"):
        run(SfmConfig(), scene, tmp_path / "out")
    assert _report(tmp_path / "out")["points"] == 0
    assert "only 0 points from 2 images" in caplog.text
    assert "--min-track-length 2 --no-ignore-two-view-tracks" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="geocues"):
        run(SfmConfig(min_track_length=2, ignore_two_view_tracks=False), scene, tmp_path / "out2")
    assert _report(tmp_path / "out2")["points"] > 0


def test_map_gives_each_photo_size_a_camera(icl_dir: Path, tmp_path: Path):
    """A photo of another pixel size: one camera shared by all (COLMAP's SINGLE mode) skipped it, and the
    warning blamed the overlap; a phone's portrait photos were half of them. Each size has its camera."""
    scene = make_tiny_icl(icl_dir, tmp_path / "s")
    shutil.rmtree(scene / "sparse")
    odd = sorted((scene / "images").iterdir())[4]
    cv2.imwrite(str(odd), cv2.resize(cv2.imread(str(odd)), (400, 300), interpolation=cv2.INTER_CUBIC))
    run(SfmConfig(check_gt=False), scene, tmp_path / "out")
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    assert sorted((c.width, c.height) for c in rec.cameras.values()) == [(320, 240), (400, 300)]
    assert odd.name in {im.name for im in rec.images.values()}


def test_a_changed_photo_is_extracted_again(triangulated, tmp_path: Path, caplog):
    """The feature cache was keyed on the options and names only: `sfm --overwrite` after the photos
    changed (another room, a repaired file) mapped the old photos' features. Now their sizes and
    modification times are in its key."""
    src, rep = triangulated
    out = tmp_path / "copy"
    shutil.copytree(src, out)  # the photos as files of its own
    cfg = replace(SfmConfig(), check_gt=False)
    photo = sorted((out / "images").iterdir())[3]
    cv2.imwrite(str(photo), cv2.flip(cv2.imread(str(photo)), 1))
    with caplog.at_level(logging.INFO, logger="geocues.sfm"):
        again = _report(run(cfg, out))
    assert "discarding cached database" in caplog.text
    assert again["seconds"]["match"] > 0


def test_mapping_that_finds_no_model_says_why(icl_dir: Path, tmp_path: Path):
    """'too few matches: try more features' was said of two photos with 178 verified matches: photos
    that match but from one spot are named so, and photos that do not match are told apart."""
    close = make_tiny_icl(icl_dir, tmp_path / "close", frames=[0, 1, 2])
    shutil.rmtree(close / "sparse")
    with pytest.raises(ValueError, match=r"pairs of photos match, but none is a starting pair .*16 degrees"):
        run(SfmConfig(check_gt=False), close, tmp_path / "out_close")
    noise = tmp_path / "noise"
    (noise / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(3):  # nothing in common
        cv2.imwrite(str(noise / "images" / f"{k}.png"), rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match="no two photos share enough matches"):
        run(SfmConfig(check_gt=False), noise, tmp_path / "out_noise")


@pytest.mark.parametrize("bad, said", [
    ({"camera_model": "FOO"}, r"--camera-model 'FOO' is no COLMAP camera model; one of SIMPLE_PINHOLE, PINHOLE"),
    ({"camera_model": "simple_pinhole"}, r"\(camera model names are upper case\)"),
    ({"max_num_features": 0}, r"--max-num-features must be >= 1, got 0"),
    ({"sequential_overlap": 0}, r"--sequential-overlap must be >= 1, got 0"),
    ({"exhaustive_below": -3}, r"--exhaustive-below must be >= 0, got -3"),
    ({"min_track_length": 1}, r"--min-track-length must be >= 2"),
    ({"num_threads": 0}, r"--num-threads must be -1 \(all cores\) or >= 1"),
    ({"mapper_threads": -2}, r"--mapper-threads must be -1 \(all cores\) or >= 1"),
    ({"peak_threshold": float("nan")}, r"--peak-threshold must be a finite number"),
    ({"max_ratio": 2.0}, r"--max-ratio must be in \(0, 1.0\], got 2.0"),
    ({"min_tri_angle": -1.0}, r"--min-tri-angle must be in \[0, 90\)"),
])
def test_options_out_of_range_are_named_before_any_work(tmp_path: Path, bad, said):
    """pycolmap's own checks named no option ('Check failed: ExistsCameraModelWithName(...)') and left
    OUT behind; a sequential overlap of 0 matched no pair and blamed the photos."""
    (tmp_path / "photos" / "images").mkdir(parents=True)
    for k in range(3):
        cv2.imwrite(str(tmp_path / "photos" / "images" / f"{k}.png"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match=said):
        run(replace(SfmConfig(), **bad), tmp_path / "photos", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    SfmConfig().validate()


def test_a_mapping_that_keeps_no_point_fails_and_says_why_later(icl_dir: Path, tmp_path: Path):
    """A map of 16 photos that registered 2 of them with 0 points exited 0 (the next step failed on
    it); `geocues info OUT` then said the run was stopped and rerunning it reused what was done. Now
    it fails, and OUT's hint gives its reason."""
    scene = make_tiny_icl(icl_dir, tmp_path / "s", frames=[0, 5, 10])
    shutil.rmtree(scene / "sparse")
    with pytest.raises(ValueError, match=r"incremental mapping registered 3 of the 3 images in .* and kept 0 points: "
                                         r"no scene to build on. .*a room wants dozens of overlapping photos"):
        run(SfmConfig(check_gt=False, min_track_length=4), scene, tmp_path / "out")
    with pytest.raises(FileNotFoundError, match=r"the `geocues sfm` run that wrote .*out failed: incremental mapping "
                                                r"registered 3 of the 3 images"):
        find_model_dir(tmp_path / "out")
    run(SfmConfig(check_gt=False), scene, tmp_path / "out")  # the same folder, options that keep points
    assert find_model_dir(tmp_path / "out") == tmp_path / "out" / "sparse" / "0"
    assert "failed" not in json.loads((tmp_path / "out" / "cache" / "sfm" / "state.json").read_text())


def test_the_mapper_runs_on_one_thread_unless_asked(icl_dir: Path, tmp_path: Path, monkeypatch):
    """COLMAP's mapper on several threads gave 2 or 6 registered images of the same 16 photos, run to
    run, with one seed; --mapper-threads (1) is what it gets, --num-threads only extraction and matching."""
    seen = []
    real = pycolmap.incremental_mapping

    def spy(*args, options=None, **kw):
        seen.append(options.num_threads)
        return real(*args, options=options, **kw)

    monkeypatch.setattr(pycolmap, "incremental_mapping", spy)
    scene = make_tiny_icl(icl_dir, tmp_path / "s", frames=[0, 5, 10])
    shutil.rmtree(scene / "sparse")
    run(SfmConfig(check_gt=False, num_threads=2), scene, tmp_path / "one")
    run(SfmConfig(check_gt=False, mapper_threads=-1), scene, tmp_path / "all")
    assert seen == [1, -1]


def test_command_flags_repeat_the_options_that_differ():
    """The hint for a stopped run repeats its command: an option left out is another cache key (the
    features would be extracted again)."""
    from geocues.sfm_checks import command_flags

    assert command_flags(SfmConfig()) == []
    assert command_flags(SfmConfig(max_image_size=800, ignore_two_view_tracks=False, camera_model="PINHOLE")) == \
        ["--max-image-size 800", "--no-ignore-two-view-tracks", "--camera-model PINHOLE"]
