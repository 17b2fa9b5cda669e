"""Scene loading: split, downscale, priors (npy / 16-bit PNG), and bad input naming the path."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from geocues.colmap_io import RawImage, quat_wxyz_to_rotmat, write_model
from geocues.scene import Scene

W, H = 64, 48
K = np.array([[60.0, 0, 32.0], [0, 62.0, 24.0], [0, 0, 1]])


def make_scene(root: Path, n: int = 17, seed: int = 0) -> list[RawImage]:
    """A tiny scene: n random images W x H and a PINHOLE model with random poses."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    images = []
    for i in range(n):
        name = f"{i:05d}.png"
        cv2.imwrite(str(root / "images" / name), rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        q = rng.normal(size=4)
        images.append(RawImage(image_id=i + 1, camera_id=1, name=name, model="PINHOLE", width=W,
                               height=H, K=K, R=quat_wxyz_to_rotmat(q), t=rng.normal(size=3)))
    write_model(root / "sparse" / "0", images)
    return images


@pytest.fixture
def scene_dir(tmp_path: Path) -> Path:
    make_scene(tmp_path / "s")
    return tmp_path / "s"


class TestLoad:
    def test_cameras_match_model(self, scene_dir: Path):
        s = Scene.load(scene_dir)
        assert len(s) == 17 and [c.name for c in s.cameras] == sorted(c.name for c in s.cameras)
        c = s.cameras[3]
        assert (c.width, c.height) == (W, H) and c.image_path == scene_dir / "images" / "00003.png"
        np.testing.assert_allclose(c.K, K)
        np.testing.assert_allclose(c.R @ c.R.T, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(c.R @ c.center + c.t, 0, atol=1e-9)
        img = s.load_image(3)
        assert img.shape == (H, W, 3) and img.dtype == np.float32 and 0 <= img.min() and img.max() <= 1
        raw = cv2.imread(str(c.image_path))[:, :, ::-1]
        np.testing.assert_allclose(img, raw / 255.0, atol=1e-6)
        assert len(s.points) == 0 and not s.has_depth_priors and s.gt_mesh_path is None

    def test_exif_orientation_is_not_applied(self, scene_dir: Path):
        """A phone photo held upright is stored landscape with an EXIF rotation: COLMAP's intrinsics
        are for the stored pixels, so the image must load as stored, not turned (and then squashed)."""
        from PIL import Image

        raw = np.zeros((H, W, 3), np.uint8)
        raw[:8] = 255  # a white top band of the stored pixels
        exif = Image.Exif()
        exif[0x0112] = 6  # "rotate 90 degrees clockwise to display"
        Image.fromarray(raw).save(scene_dir / "images" / "00003.jpg", exif=exif, quality=95)
        (scene_dir / "images" / "00003.png").unlink()
        for f in (scene_dir / "sparse" / "0").glob("images.*"):
            f.write_bytes(f.read_bytes().replace(b"00003.png", b"00003.jpg"))
        img = Scene.load(scene_dir).load_image(3)
        assert img.shape == (H, W, 3)
        assert img[:6].mean() > 0.95 and img[12:].mean() < 0.05  # the band where it is stored

    def test_two_images_with_one_stem_are_refused(self, tmp_path: Path):
        """A camera rig's cam0/0001.png and cam1/0001.png would share priors/depth/0001.npy and every
        per-view output named by the stem."""
        rng = np.random.default_rng(0)
        images = []
        for k, name in enumerate(["cam0/0001.png", "cam1/0001.png"]):
            (tmp_path / "images" / name).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(tmp_path / "images" / name), rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
            images.append(RawImage(k + 1, 1, name, "PINHOLE", W, H, K, np.eye(3), rng.normal(size=3)))
        write_model(tmp_path / "sparse" / "0", images)
        with pytest.raises(ValueError, match=r"cam0/0001\.png and cam1/0001\.png .* share the file stem '0001'"):
            Scene.load(tmp_path)

    def test_model_folder_given_directly(self, scene_dir: Path):
        s = Scene.load(scene_dir / "sparse" / "0")
        assert s.root == scene_dir and len(s) == 17


class TestSplit:
    def test_every_8th_by_default(self, scene_dir: Path):
        s = Scene.load(scene_dir)
        assert s.test_indices == [0, 8, 16]
        assert s.train_indices == [i for i in range(17) if i not in (0, 8, 16)]

    def test_configurable(self, scene_dir: Path):
        assert Scene.load(scene_dir, test_every=5).test_indices == [0, 5, 10, 15]
        s = Scene.load(scene_dir, test_every=0)
        assert s.test_indices == [] and s.train_indices == list(range(17))

    @pytest.mark.parametrize("bad", [1, -2])
    def test_bad_split(self, scene_dir: Path, bad: int):
        with pytest.raises(ValueError, match="test_every"):
            Scene.load(scene_dir, test_every=bad)


class TestDownscale:
    def test_intrinsics_scale_exactly(self, scene_dir: Path):
        full, half = Scene.load(scene_dir), Scene.load(scene_dir, downscale=2.0)
        c1, c2 = full.cameras[5], half.cameras[5]
        assert (c2.width, c2.height) == (W // 2, H // 2)
        np.testing.assert_array_equal(c2.K[:2], full.cameras[5].K[:2] / 2.0)
        X = np.random.default_rng(1).normal(size=(50, 3)) + c1.center + 5 * c1.R[2]  # in front
        uv1, z1 = c1.project(X)
        uv2, z2 = c2.project(X)
        np.testing.assert_allclose(uv2, uv1 / 2.0, rtol=1e-12, atol=1e-9)  # COLMAP pixel centres
        np.testing.assert_allclose(z2, z1)
        assert half.load_image(5).shape == (H // 2, W // 2, 3)

    def test_pixel_rays_hit_pixel_centres(self, scene_dir: Path):
        c = Scene.load(scene_dir, downscale=4.0).cameras[0]
        rays = c.pixel_rays()  # [h, w, 3]
        X = (rays.reshape(-1, 3) * 3.0 - c.t) @ c.R  # camera -> world at z = 3
        uv, _ = c.project(X)
        j, i = np.meshgrid(np.arange(c.width) + 0.5, np.arange(c.height) + 0.5)
        np.testing.assert_allclose(uv, np.stack([j.ravel(), i.ravel()], 1), atol=1e-9)

    def test_bad_downscale(self, scene_dir: Path):
        with pytest.raises(ValueError, match="downscale"):
            Scene.load(scene_dir, downscale=0)


class TestPriors:
    def test_npy_depth_and_normal(self, scene_dir: Path):
        rng = np.random.default_rng(2)
        d = rng.uniform(0.5, 4, (H, W)).astype(np.float32)
        n = rng.normal(size=(H, W, 3)).astype(np.float32)
        (scene_dir / "priors" / "depth").mkdir(parents=True)
        (scene_dir / "priors" / "normal").mkdir(parents=True)
        np.save(scene_dir / "priors" / "depth" / "00002.npy", d)
        np.save(scene_dir / "priors" / "normal" / "00002.npy", n)
        s = Scene.load(scene_dir)
        assert s.has_depth_priors and s.has_normal_priors
        np.testing.assert_array_equal(s.depth_prior(2), d)
        np.testing.assert_allclose(s.normal_prior(2), n / np.linalg.norm(n, axis=-1, keepdims=True), atol=1e-6)
        assert s.depth_prior(3) is None and s.normal_prior(3) is None
        assert Scene.load(scene_dir, downscale=2.0).depth_prior(2).shape == (H // 2, W // 2)

    def test_png16_depth_with_scale(self, scene_dir: Path):
        mm = np.random.default_rng(3).integers(0, 5000, (H, W)).astype(np.uint16)
        (scene_dir / "priors" / "depth").mkdir(parents=True)
        cv2.imwrite(str(scene_dir / "priors" / "depth" / "00004.png"), mm)
        (scene_dir / "scene.json").write_text(json.dumps({"depth_png_scale": 1000.0}))
        d = Scene.load(scene_dir).depth_prior(4)
        assert d.dtype == np.float32
        np.testing.assert_allclose(d, mm / 1000.0, rtol=1e-6)
        assert (d == 0).sum() == (mm == 0).sum()  # 0 stays invalid

    def test_png16_normal(self, scene_dir: Path):
        n = np.zeros((H, W, 3), np.float32)
        n[..., 2] = -1.0  # facing the camera
        (scene_dir / "priors" / "normal").mkdir(parents=True)
        raw = np.round((n + 1) / 2 * 65535).astype(np.uint16)
        cv2.imwrite(str(scene_dir / "priors" / "normal" / "00001.png"), raw[:, :, ::-1])  # RGB on disk
        np.testing.assert_allclose(Scene.load(scene_dir).normal_prior(1), n, atol=1e-4)


class TestBadInput:
    def test_no_cameras_file(self, scene_dir: Path):
        (scene_dir / "sparse" / "0" / "cameras.txt").unlink()
        with pytest.raises(FileNotFoundError, match=r"no cameras\.txt or cameras\.bin in .*" + str(scene_dir)):
            Scene.load(scene_dir)

    def test_image_missing_on_disk(self, scene_dir: Path):
        (scene_dir / "images" / "00007.png").unlink()
        with pytest.raises(FileNotFoundError, match=str(scene_dir / "images" / "00007.png")):
            Scene.load(scene_dir)

    def test_image_of_wrong_size(self, scene_dir: Path):
        cv2.imwrite(str(scene_dir / "images" / "00006.png"), np.zeros((10, 10, 3), np.uint8))
        with pytest.raises(ValueError, match=str(scene_dir / "images" / "00006.png")):
            Scene.load(scene_dir)

    def test_prior_of_another_size_is_resized_with_a_warning(self, scene_dir: Path, caplog):
        (scene_dir / "priors" / "depth").mkdir(parents=True)
        other = scene_dir / "priors" / "depth" / "00003.npy"
        np.save(other, np.full((H * 2, W * 2), 2.5, np.float32))  # an estimator's output size
        scene = Scene.load(scene_dir)
        assert f"1 prior maps of {scene_dir} are not the size of their images" in caplog.text
        assert "(depth 00003.npy 128x96)" in caplog.text
        prior = scene.depth_prior(3)
        assert prior.shape == (H, W) and np.all(prior == 2.5)

    def test_prior_of_wrong_rank(self, scene_dir: Path):
        (scene_dir / "priors" / "depth").mkdir(parents=True)
        bad = scene_dir / "priors" / "depth" / "00003.npy"
        np.save(bad, np.ones((H, W, 3), np.float32))
        with pytest.raises(ValueError, match=str(bad) + r".*expected HxW"):
            Scene.load(scene_dir)

    def test_normal_prior_without_3_channels(self, scene_dir: Path):
        (scene_dir / "priors" / "normal").mkdir(parents=True)
        bad = scene_dir / "priors" / "normal" / "00003.npy"
        np.save(bad, np.ones((H, W), np.float32))
        with pytest.raises(ValueError, match=str(bad)):
            Scene.load(scene_dir)

    def test_empty_model(self, scene_dir: Path):
        model = scene_dir / "sparse" / "0"
        (model / "images.txt").write_text("# no images\n")
        with pytest.raises(ValueError, match=f"{model}.*no registered images"):
            Scene.load(scene_dir)

    def test_distorted_camera_refused_with_undistort_hint(self, scene_dir: Path):
        cams = scene_dir / "sparse" / "0" / "cameras.txt"
        cams.write_text(f"1 SIMPLE_RADIAL {W} {H} 60 32 24 0.05\n")
        with pytest.raises(ValueError, match="SIMPLE_RADIAL.*geocues undistort"):
            Scene.load(scene_dir)

    @pytest.mark.parametrize("line", [f"1 OPENCV {W} {H} 60 62 32 24 0 0 0 0",
                                      f"1 SIMPLE_RADIAL {W} {H} 61 32 24 0",
                                      f"1 FULL_OPENCV {W} {H} 60 62 32 24 0 0 0 0 0 0 0 0"])
    def test_zero_distortion_is_read_as_a_pinhole(self, scene_dir: Path, line: str):
        """Dataset converters write OPENCV (or SIMPLE_RADIAL) with every coefficient 0: that camera
        is a pinhole, read as one (as the nerfstudio reader does), with the same intrinsics."""
        (scene_dir / "sparse" / "0" / "cameras.txt").write_text(line + "\n")
        s = Scene.load(scene_dir)
        p = [float(v) for v in line.split()[4:]]
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if "SIMPLE" in line else p[:4]
        np.testing.assert_allclose(s.cameras[3].K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        assert s.distorted_models == []

    @pytest.mark.parametrize("line", [f"1 OPENCV {W} {H} 60 62 32 24 0 0 1e-9 0",
                                      f"1 OPENCV_FISHEYE {W} {H} 60 62 32 24 0 0 0 0"])
    def test_any_distortion_or_a_fisheye_is_still_refused(self, scene_dir: Path, line: str):
        (scene_dir / "sparse" / "0" / "cameras.txt").write_text(line + "\n")
        with pytest.raises(ValueError, match=line.split()[1] + ".*geocues undistort"):
            Scene.load(scene_dir)

    def test_info_summarises_a_distorted_scene_and_names_undistort(self, scene_dir: Path, capsys):
        """COLMAP's own mapper writes SIMPLE_RADIAL: `geocues info` is the first command a user runs
        on it, so it summarises the scene and names the step that makes it readable."""
        from cli.geocues_cli import main

        (scene_dir / "sparse" / "0" / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {W} {H} 60 32 24 0.05\n")
        assert main(["info", str(scene_dir)]) == 0
        out = capsys.readouterr().out
        assert "cameras    " in out and "fx 60.00" in out
        assert "distorted camera model SIMPLE_RADIAL" in out and f"geocues undistort {scene_dir}" in out
        assert Scene.load(scene_dir, allow_distorted=True).distorted_models == ["SIMPLE_RADIAL"]

    @pytest.mark.parametrize("dtype, kind", [(np.uint8, "depth"), (np.uint16, "depth"), (np.uint8, "disparity")])
    def test_an_8bit_depth_png_is_named_once(self, scene_dir: Path, caplog, dtype, kind):
        """An 8-bit PNG (a depth visualisation) read as millimetres held 0-0.255 m without a word; the
        warning comes once per process (`splat ablate` loads the scene again for every row)."""
        (scene_dir / "priors" / "depth").mkdir(parents=True)
        (scene_dir / "scene.json").write_text(json.dumps({"depth_png_scale": 1000, "priors": {"depth_kind": kind}}))
        for k in (0, 1):
            cv2.imwrite(str(scene_dir / "priors" / "depth" / f"0000{k}.png"), np.full((H, W), 200, dtype))
        with caplog.at_level("WARNING", logger="geocues"):
            Scene.load(scene_dir)
            Scene.load(scene_dir)
        said = "2 depth priors of %s are 8-bit PNGs (00000.png, 00001.png): 256 levels, read as depth at most " \
               "0.255 scene units (255 / depth_png_scale 1000)" % scene_dir
        assert caplog.text.count(said) == (dtype == np.uint8), caplog.text

    def test_png_depth_without_scale(self, scene_dir: Path):
        (scene_dir / "priors" / "depth").mkdir(parents=True)
        png = scene_dir / "priors" / "depth" / "00000.png"
        cv2.imwrite(str(png), np.full((H, W), 1000, np.uint16))
        with pytest.raises(ValueError, match=str(png) + ".*depth_png_scale"):  # at load, as docs/scenes.md says
            Scene.load(scene_dir)
        s = Scene.load(scene_dir, check_priors=False)
        with pytest.raises(ValueError, match=str(png) + ".*depth_png_scale"):
            s.depth_prior(0)

    def test_no_images_folder(self, scene_dir: Path):
        (scene_dir / "images").rename(scene_dir / "imgs")
        with pytest.raises(FileNotFoundError, match=str(scene_dir / "images")):
            Scene.load(scene_dir)


def test_training_warns_about_images_over_1600_px(tmp_path: Path, caplog):
    """A phone capture (4032x3024) trained at --downscale 1 gets one warning that names a --downscale
    bringing it to at most 1600 px; a 640x480 scene gets none."""
    from splat.views import warn_large_images

    rng = np.random.default_rng(0)
    for name, (w, h) in (("big", (4032, 3024)), ("small", (640, 480))):
        root = tmp_path / name
        (root / "images").mkdir(parents=True)
        cv2.imwrite(str(root / "images" / "a.png"), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        write_model(root / "sparse" / "0", [RawImage(1, 1, "a.png", "PINHOLE", w, h, K, np.eye(3), np.zeros(3))])
        caplog.clear()
        warn_large_images(Scene.load(root), 1.0)
        assert ("--downscale 2.6 trains at 1551x1163" in caplog.text) == (name == "big"), caplog.text
    warn_large_images(Scene.load(tmp_path / "big", downscale=2.0), 2.0)
    assert "--downscale 2.6 trains at 1551x1163" in caplog.text  # the factor is from the full size
    caplog.clear()
    warn_large_images(Scene.load(tmp_path / "small", downscale=0.5), 0.5)  # upsampling is named
    assert "--downscale 0.5 is below 1: the photos are UPSAMPLED 2x" in caplog.text, caplog.text


def test_a_reference_mesh_at_the_root_is_the_gt(tmp_path):
    """ICL-NUIM (and the shared copy of it) keeps its GT as reference_mesh.ply beside the model:
    `geocues info`, `evaluate MESH SCENE` and the cue metrics take it, as `geocues sfm -o` already did."""
    make_scene(tmp_path / "s")
    s = Scene.load(tmp_path / "s")
    assert s.gt_mesh_path is None
    (tmp_path / "s" / "reference_mesh.ply").write_text("ply\n")
    assert Scene.load(tmp_path / "s").gt_mesh_path == tmp_path / "s" / "reference_mesh.ply"
    (tmp_path / "s" / "gt").mkdir()
    (tmp_path / "s" / "gt" / "mesh.ply").write_text("ply\n")  # the scene layout's own wins
    assert Scene.load(tmp_path / "s").gt_mesh_path == tmp_path / "s" / "gt" / "mesh.ply"


def test_transparent_photos_are_warned_about(tmp_path, caplog):
    """RGBA photos with transparent pixels train as the colour those pixels store: one warning, counting
    every such photo, not only the first (a scene whose later photos alone had alpha got none); an opaque
    alpha channel none."""
    import logging

    for name, alpha, which in (("clear", 0, (0,)), ("opaque", 255, (0,)), ("later", 0, (1, 2))):
        make_scene(tmp_path / name, n=3)
        for k in which:
            img = cv2.imread(str(tmp_path / name / "images" / f"0000{k}.png"))
            rgba = np.dstack([img, np.full(img.shape[:2], 255, np.uint8)])
            rgba[: H // 4, :, 3] = alpha
            cv2.imwrite(str(tmp_path / name / "images" / f"0000{k}.png"), rgba)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="geocues"):
            Scene.load(tmp_path / name)
        assert ("alpha channel (" in caplog.text) == (name != "opaque"), caplog.text
        assert caplog.text.count("alpha channel") <= 1
        if name == "clear":
            assert "00000.png has an alpha channel (25% of its pixels" in caplog.text
        if name == "later":
            assert "2 of the 3 photos have an alpha channel (00001.png: 25% of its pixels" in caplog.text


def test_a_camera_index_outside_the_scene_is_named(tmp_path):
    """load_image(-1) returned the last image; 999 a bare IndexError."""
    make_scene(tmp_path / "s")
    s = Scene.load(tmp_path / "s")
    assert s.load_image(len(s) - 1).shape[2] == 3
    for bad in (-1, len(s), 1.0):
        for method in (s.load_image, s.depth_prior, s.normal_prior, s.depth_prior_path):
            with pytest.raises(IndexError, match=rf"camera index {bad!r} outside 0\.\.{len(s) - 1} of the scene"):
                method(bad)


def test_png_priors_a_user_brings_are_read_or_named(tmp_path):
    """A black PNG normal pixel is no normal (it read as (-1,-1,-1)/sqrt 3, a valid direction); a
    grey-scale normal PNG, a truncated depth PNG and a depth_png_scale that is not a positive number
    are one error naming the file or key (they were an IndexError, an AttributeError, a float())."""
    import cv2

    make_scene(tmp_path / "s")
    s = Scene.load(tmp_path / "s")
    cam = s.cameras[0]
    (tmp_path / "s" / "priors" / "normal").mkdir(parents=True)
    png = np.full((cam.height, cam.width, 3), (128, 128, 255), np.uint8)  # BGR: facing the camera (z -1)
    png[: cam.height // 4] = 0
    path = tmp_path / "s" / "priors" / "normal" / f"{cam.stem}.png"
    cv2.imwrite(str(path), png)
    n = Scene.load(tmp_path / "s").normal_prior(0)
    assert (n[: cam.height // 4] == 0).all() and (np.abs(np.linalg.norm(n[cam.height // 4:], axis=-1) - 1) < 1e-5).all()
    cv2.imwrite(str(path), png[..., 0])  # one channel
    with pytest.raises(ValueError, match=f"the normal prior {path} has shape .* expected an RGB image"):
        Scene.load(tmp_path / "s").normal_prior(0)
    path.unlink()
    (tmp_path / "s" / "priors" / "depth").mkdir(parents=True)
    dpath = tmp_path / "s" / "priors" / "depth" / f"{cam.stem}.png"
    cv2.imwrite(str(dpath), np.full((cam.height, cam.width), 2000, np.uint16))
    meta = tmp_path / "s" / "scene.json"
    for bad in ("mm", 0, -1000):
        meta.write_text(json.dumps({"depth_png_scale": bad}))
        with pytest.raises(ValueError, match=f"depth_png_scale must be a positive number .* got {bad!r}"):
            Scene.load(tmp_path / "s")
    meta.write_text(json.dumps({"depth_png_scale": 1000}))
    assert Scene.load(tmp_path / "s").depth_prior(0).max() == pytest.approx(2.0)
    dpath.write_bytes(dpath.read_bytes()[:60])  # a valid header, the data cut off
    with pytest.raises(ValueError, match=f"cannot read the depth prior {dpath}"):
        Scene.load(tmp_path / "s", check_priors=False).depth_prior(0)


def test_a_downscale_that_leaves_no_image_is_refused(tmp_path):
    """--downscale 1000 on 320-px images trained on 1-px images and reported a PSNR."""
    make_scene(tmp_path / "s")
    s = Scene.load(tmp_path / "s")
    w, h = s.cameras[0].width, s.cameras[0].height
    with pytest.raises(ValueError, match=rf"downscale 1000 makes .* \({w}x{h}\) \d+x\d+ px; a side under 8 px"):
        Scene.load(tmp_path / "s", downscale=1000)
    Scene.load(tmp_path / "s", downscale=min(w, h) / 8)  # the largest allowed


def test_prior_files_that_match_no_image_are_named_and_dotted_stems_find_theirs(tmp_path, capsys):
    """00005_depth.npy, 00005.png.npy, 99999.npy were ignored without a word; a stem with a dot
    (frame.0001) looked for frame.npy (Path.with_suffix), another image's name."""
    from cli.geocues_cli import main

    make_scene(tmp_path / "s")
    s = Scene.load(tmp_path / "s")
    depth = tmp_path / "s" / "priors" / "depth"
    depth.mkdir(parents=True)
    cam = s.cameras[0]
    for name in (f"{cam.stem}_depth.npy", f"{cam.name}.npy", "99999.npy", f"{cam.stem}.npy"):
        np.save(depth / name, np.ones((cam.height, cam.width), np.float32))
    (depth / f"{s.cameras[1].stem}.exr").write_bytes(b"not read")  # a format the loader does not read
    assert [p.name for p in Scene.load(tmp_path / "s").stray_priors("depth")] == sorted(
        [f"{cam.stem}_depth.npy", f"{cam.name}.npy", "99999.npy", f"{s.cameras[1].stem}.exr"])
    assert main(["info", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    assert "4 file(s) in priors/depth/ are no image's prior and are ignored" in out and "00000_depth.npy" in out, out
    from dataclasses import replace
    s = Scene.load(tmp_path / "s")
    s.cameras[1] = replace(s.cameras[1], name="frame.0001.png")  # stem frame.0001
    np.save(depth / "frame.npy", np.ones((cam.height, cam.width), np.float32))
    assert s.depth_prior_path(1) is None  # not frame.npy
    np.save(depth / "frame.0001.npy", np.ones((cam.height, cam.width), np.float32))
    assert s.depth_prior_path(1) == depth / "frame.0001.npy"


def test_a_photo_turned_by_its_exif_tag_is_named_as_the_cause_of_swapped_sides(tmp_path: Path):
    """A model made from upright (EXIF-applied) phone photos, the files stored sideways with Orientation
    6: the size error now says why; a plain size mismatch says nothing more."""
    from PIL import Image

    for name, orientation in (("turned", 6), ("plain", 1)):
        root = tmp_path / name
        (root / "images").mkdir(parents=True)
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(root / "images" / "a.jpg", exif=exif.tobytes())
        write_model(root / "sparse" / "0", [RawImage(1, 1, "a.jpg", "PINHOLE", 48, 64, K, np.eye(3), np.zeros(3))])
        with pytest.raises(ValueError, match="is 64x48 but its camera") as err:
            Scene.load(root)
        assert ("carries an EXIF rotation tag" in str(err.value)) == (name == "turned"), str(err.value)
