"""COLMAP model I/O: text <-> binary round trips through our writer and pycolmap, quaternions."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geocues.colmap_io import (RawImage, RawPoints, find_model_dir, quat_wxyz_to_rotmat,
                               quat_xyzw_to_wxyz, read_model, rotmat_to_quat_wxyz, write_model)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quat_wxyz_to_rotmat(q / np.linalg.norm(q))


def _images(n: int = 5, seed: int = 0) -> list[RawImage]:
    rng = np.random.default_rng(seed)
    K1 = np.array([[500.0, 0, 320.0], [0, 505.0, 240.0], [0, 0, 1]])
    K2 = np.array([[250.0, 0, 160.5], [0, 250.0, 120.25], [0, 0, 1]])
    out = []
    for i in range(n):
        cam, K, (w, h) = (1, K1, (640, 480)) if i % 2 == 0 else (2, K2, (320, 240))
        out.append(RawImage(image_id=10 + i, camera_id=cam, name=f"{i:05d}.png", model="PINHOLE",
                            width=w, height=h, K=K, R=_random_rotation(rng), t=rng.normal(size=3)))
    return out


def _mkdir(p: Path) -> str:
    p.mkdir(parents=True, exist_ok=True)  # pycolmap writes into an existing folder only
    return str(p)


def _sorted_points(p: RawPoints) -> tuple[np.ndarray, RawPoints]:
    """Points in id order (pycolmap's point map has no fixed order)."""
    o = np.argsort(p.ids)
    return o, RawPoints(p.ids[o], p.xyz[o], p.rgb[o], p.error[o], p.track_length[o],
                        [p.track_image_ids[i] for i in o])


def _assert_same_images(a: list[RawImage], b: list[RawImage]) -> None:
    assert [x.name for x in a] == [x.name for x in b]
    for x, y in zip(a, b):
        assert (x.image_id, x.camera_id, x.model, x.width, x.height) == \
               (y.image_id, y.camera_id, y.model, y.width, y.height)
        np.testing.assert_allclose(x.K, y.K, atol=1e-9)
        np.testing.assert_allclose(x.R, y.R, atol=1e-9)
        np.testing.assert_allclose(x.t, y.t, atol=1e-9)


class TestQuaternions:
    def test_rotmat_roundtrip(self):
        rng = np.random.default_rng(1)
        for _ in range(50):
            R = _random_rotation(rng)
            q = rotmat_to_quat_wxyz(R)
            assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
            np.testing.assert_allclose(quat_wxyz_to_rotmat(q), R, atol=1e-12)

    def test_pycolmap_xyzw_boundary(self):
        R = _random_rotation(np.random.default_rng(2))
        xyzw = np.asarray(pycolmap.Rotation3d(R).quat)
        np.testing.assert_allclose(quat_wxyz_to_rotmat(quat_xyzw_to_wxyz(xyzw)), R, atol=1e-12)


class TestRoundTrip:
    def test_text_to_binary_cameras_poses_names(self, tmp_path: Path):
        images = _images()
        write_model(tmp_path / "txt", images)
        assert (tmp_path / "txt" / "images.txt").is_file()
        pycolmap.Reconstruction(str(tmp_path / "txt")).write_binary(_mkdir(tmp_path / "bin"))
        assert not (tmp_path / "bin" / "images.txt").exists()
        imgs_txt, pts_txt = read_model(tmp_path / "txt")
        imgs_bin, pts_bin = read_model(tmp_path / "bin")
        _assert_same_images(imgs_txt, images)
        _assert_same_images(imgs_bin, images)
        assert len(pts_txt.ids) == len(pts_bin.ids) == 0

    def test_writer_binary_flag(self, tmp_path: Path):
        images = _images(3, seed=4)
        write_model(tmp_path / "m", images, binary=True)
        names = {p.name for p in (tmp_path / "m").iterdir()}
        assert {"cameras.bin", "images.bin", "points3D.bin"} <= names and not any(n.endswith(".txt") for n in names)
        _assert_same_images(read_model(tmp_path / "m")[0], images)

    def test_points_without_tracks(self, tmp_path: Path):
        rng = np.random.default_rng(5)
        n = 20
        pts = RawPoints(ids=np.arange(1, n + 1, dtype=np.int64), xyz=rng.normal(size=(n, 3)),
                        rgb=rng.integers(0, 256, (n, 3), dtype=np.uint8), error=rng.uniform(0, 2, n),
                        track_length=np.zeros(n, np.int32), track_image_ids=[np.zeros(0, np.int64)] * n)
        write_model(tmp_path / "m", _images(2), pts)
        _, back = _sorted_points(read_model(tmp_path / "m")[1])
        np.testing.assert_array_equal(back.ids, pts.ids)
        np.testing.assert_allclose(back.xyz, pts.xyz, rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(back.rgb, pts.rgb)
        np.testing.assert_allclose(back.error, pts.error, rtol=1e-5)

    def test_points_with_tracks_bin_txt_bin(self, tmp_path: Path):
        """A model with points and full tracks (pycolmap's synthetic dataset) survives bin <-> txt."""
        opts = pycolmap.SyntheticDatasetOptions()
        opts.num_rigs, opts.num_frames_per_rig, opts.num_points3D = 1, 4, 60
        opts.camera_model_id = pycolmap.CameraModelId.PINHOLE
        opts.camera_params = [400.0, 410.0, 256.0, 192.0]
        opts.camera_width, opts.camera_height = 512, 384
        pycolmap.set_random_seed(3)
        rec = pycolmap.synthesize_dataset(opts)
        assert rec.num_points3D() == 60
        rec.write_binary(_mkdir(tmp_path / "bin"))
        pycolmap.Reconstruction(str(tmp_path / "bin")).write_text(_mkdir(tmp_path / "txt"))
        pycolmap.Reconstruction(str(tmp_path / "txt")).write_binary(_mkdir(tmp_path / "bin2"))
        (i0, p0), (i1, p1), (i2, p2) = ((im, _sorted_points(p)[1]) for im, p in
                                        (read_model(tmp_path / d) for d in ("bin", "txt", "bin2")))
        _assert_same_images(i0, i1)
        _assert_same_images(i0, i2)
        for p in (p1, p2):
            np.testing.assert_array_equal(p.ids, p0.ids)
            np.testing.assert_allclose(p.xyz, p0.xyz, rtol=1e-9, atol=1e-9)
            np.testing.assert_array_equal(p.track_length, p0.track_length)
            for a, b in zip(p.track_image_ids, p0.track_image_ids):
                np.testing.assert_array_equal(np.sort(a), np.sort(b))
        assert p0.track_length.min() >= 2


class TestBadInput:
    def test_no_cameras_file_names_the_folder(self, tmp_path: Path):
        (tmp_path / "sparse" / "0").mkdir(parents=True)
        with pytest.raises(FileNotFoundError, match=str(tmp_path)):
            find_model_dir(tmp_path)

    def test_missing_scene_folder(self, tmp_path: Path):
        with pytest.raises(FileNotFoundError, match="does not exist"):
            find_model_dir(tmp_path / "nope")

    def test_missing_images_file(self, tmp_path: Path):
        write_model(tmp_path / "m", _images(2))
        (tmp_path / "m" / "images.txt").unlink()
        with pytest.raises(FileNotFoundError, match=r"no images\.txt or images\.bin in .*m"):
            read_model(tmp_path / "m")

    def test_empty_model_refused_by_writer(self, tmp_path: Path):
        with pytest.raises(ValueError, match=str(tmp_path / "m")):
            write_model(tmp_path / "m", [])
        assert not (tmp_path / "m").exists()

    def test_broken_file_is_valueerror_naming_folder(self, tmp_path: Path):
        write_model(tmp_path / "m", _images(2))
        (tmp_path / "m" / "cameras.txt").write_text("1 PINHOLE 640 480 not-a-number\n")
        with pytest.raises(ValueError, match=str(tmp_path / "m")):
            read_model(tmp_path / "m")

    def test_atomic_write_leaves_old_model_on_failure(self, tmp_path: Path):
        images = _images(2)
        write_model(tmp_path / "m", images)
        bad = _images(2)
        bad[0].K = None  # the writer fails half-way through
        with pytest.raises(TypeError):
            write_model(tmp_path / "m", bad)
        _assert_same_images(read_model(tmp_path / "m")[0], images)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # no temp folder left


@pytest.mark.parametrize("binary", [False, True])
def test_a_posed_model_without_a_points_file_reads_as_one_without_points(tmp_path, binary):
    """cameras + images only (what a user writes for known poses, `geocues sfm`'s input): read, 0 points."""
    model = write_model(tmp_path / "m", _images(), binary=binary)
    (model / f"points3D.{'bin' if binary else 'txt'}").unlink()
    images, points = read_model(model)
    _assert_same_images(images, _images())
    assert len(points.ids) == 0 and not any(model.glob("points3D.*"))  # the user's folder is left as it was


def test_text_model_mistakes_name_the_file_and_line(tmp_path):
    model = write_model(tmp_path / "m", _images(3))
    imgs = model / "images.txt"
    text = imgs.read_text()
    (model / "images.txt").write_text(text.replace(" 2 00001.png", " 7 00001.png"))
    with pytest.raises(ValueError, match=r"images.txt: line \d+: image 00001.png uses camera 7, which .*cameras.txt"):
        read_model(model)
    body = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]  # without the 2D-point lines
    imgs.write_text("\n".join(body) + "\n")
    with pytest.raises(ValueError, match=r"images.txt: line \d+ looks like another image, where the 2D points of "
                                         r"image 00000.png"):
        read_model(model)


def test_an_image_camera_edited_without_its_frame_names_the_rigs_and_frames_files(tmp_path):
    """pycolmap 4 writes rigs.txt and frames.txt; an image moved to another camera in images.txt alone
    failed with pycolmap's bare 'Check failed: frame->HasDataId(DataId())' (new-user audit)."""
    model = write_model(tmp_path / "m", _images(3))
    pycolmap.Reconstruction(str(model)).write_text(str(model))  # the newer format: rigs and frames too
    assert (model / "rigs.txt").is_file() and (model / "frames.txt").is_file()
    read_model(model)
    imgs = model / "images.txt"
    imgs.write_text(imgs.read_text().replace(" 2 00001.png", " 1 00001.png"))
    with pytest.raises(ValueError, match=r"could not read COLMAP model in .*: .*its rigs and frames files disagree "
                                         r"with its images file"):
        read_model(model)
    for name in ("rigs.txt", "frames.txt"):
        (model / name).unlink()
    assert [im.name for im in read_model(model)[0]] == ["00000.png", "00001.png", "00002.png"]  # as the hint says


def test_camera_lines_and_two_models_in_one_folder_are_named(tmp_path, caplog):
    """A camera line with another parameter count than its model's was pycolmap's bare 'Check failed:
    camera.VerifyParams()'; a folder with a binary and an edited text model read the binary in silence."""
    import logging
    import os

    model = write_model(tmp_path / "m", _images(3))
    cams = model / "cameras.txt"
    text = cams.read_text()
    first = next(ln for ln in text.splitlines() if ln and not ln.startswith("#"))
    cams.write_text(text.replace(first, first.replace(" PINHOLE ", " OPENCV ")))
    with pytest.raises(ValueError, match=r"cameras.txt: line \d+: camera \d+ \(OPENCV\) takes 8 parameters "
                                         r"\(fx fy cx cy k1 k2 p1 p2\), got 4"):
        read_model(model)
    cams.write_text(text.replace(first, first.replace(" PINHOLE ", " PINHOL ")))
    with pytest.raises(ValueError, match=r"camera \d+ has an unknown model 'PINHOL'"):
        read_model(model)
    cams.write_text(text)
    write_model(tmp_path / "b", _images(3), binary=True)
    for f in (tmp_path / "b").iterdir():
        os.replace(f, model / f.name)
    os.utime(model / "images.txt", (2e9, 2e9))  # the text model edited after the binary was written
    with caplog.at_level(logging.WARNING, logger="geocues"):
        read_model(model)
    assert "holds a binary and a text model: the binary one (*.bin) is read; images.txt is newer" in caplog.text


def test_no_model_names_what_the_folder_holds_instead(tmp_path):
    """The first command on a folder of photos, on a scene's images/ folder, or on a model kept in
    sparse/1 names the step that fixes it, not only the files it looked for."""
    import cv2

    photos = tmp_path / "photos"
    (photos / "images" / "seq1").mkdir(parents=True)
    for k in range(3):
        cv2.imwrite(str(photos / "images" / "seq1" / f"{k:04d}.JPG"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(FileNotFoundError, match=r"holds photos without a model: `geocues sfm .*photos -o MAP`"):
        find_model_dir(photos)
    (photos / "images" / "a.png").write_bytes((photos / "images" / "seq1" / "0000.JPG").read_bytes())
    with pytest.raises(FileNotFoundError, match=r"looks like a scene's images folder: pass the scene folder above it"):
        find_model_dir(photos / "images")
    cues = tmp_path / "cues"  # the cue folder or a run given as the scene (`splat train cues -c cues`)
    cues.mkdir()
    (cues / "cues.ply").write_text("ply")
    with pytest.raises(FileNotFoundError, match=r"is a cue folder \(cues.ply from `geocues extract`\): a command takes "
                                                r"it with -c/--cues"):
        find_model_dir(cues)
    (tmp_path / "run" / "point_cloud").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"is a training run \(`splat train -o`\)"):
        find_model_dir(tmp_path / "run")
    (photos / "cache" / "sfm").mkdir(parents=True)  # a `geocues sfm -o photos` stopped before its model
    with pytest.raises(FileNotFoundError, match=r"holds an unfinished `geocues sfm SCENE -o .*photos`.*run that "
                                                r"command again, it starts again \(it was stopped while extracting"):
        find_model_dir(photos)
    state = photos / "cache" / "sfm" / "state.json"
    state.write_text(json.dumps({"scene": "/data/my room", "extract": "k", "flags": ["--max-image-size 800"]}))
    with pytest.raises(FileNotFoundError, match=r"unfinished `geocues sfm '/data/my room' -o .*photos --max-image-size "
                                                r"800`.*run that command again, it reuses the features$"):
        find_model_dir(photos)  # stopped after its features, before its matches
    state.write_text(json.dumps({"scene": "/data/my room", "extract": "k", "match": "m"}))
    with pytest.raises(FileNotFoundError, match=r"it reuses the features and matches$"):
        find_model_dir(photos)
    state.write_text(json.dumps({"scene": "/data/my room", "extract": "k", "failed": "incremental mapping found "
                                 "no model for the images in x: no two photos share enough matches"}))
    with pytest.raises(FileNotFoundError, match=r"the `geocues sfm` run that wrote .*photos failed: incremental "
                                                r"mapping found no model"):
        find_model_dir(photos)
    write_model(tmp_path / "s" / "sparse" / "1", _images(2))
    with pytest.raises(FileNotFoundError, match=r"sparse/1 holds a model: move \(or link\) it to .*sparse/0"):
        find_model_dir(tmp_path / "s")


def test_images_are_listed_in_any_case_and_from_subfolders(tmp_path):
    from geocues.scene import list_images

    (tmp_path / "flat").mkdir()
    for name in ("b.JPG", "a.Jpeg", "c.tif", "notes.txt", "._b.JPG"):  # ._NAME: macOS's AppleDouble files
        (tmp_path / "flat" / name).write_bytes(b"")
    assert list_images(tmp_path / "flat") == ["a.Jpeg", "b.JPG", "c.tif"]
    (tmp_path / "nested" / "seq2").mkdir(parents=True)
    (tmp_path / "nested" / "seq1").mkdir()
    for name in ("seq2/0.png", "seq1/1.png", "seq1/0.png"):
        (tmp_path / "nested" / name).write_bytes(b"")
    assert list_images(tmp_path / "nested") == ["seq1/0.png", "seq1/1.png", "seq2/0.png"]
