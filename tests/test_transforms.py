"""nerfstudio transforms.json scenes (issue 14, point 5): read at the boundary, same cameras as COLMAP.

A COLMAP scene (``make_room_scene``) is converted to transforms.json the way ns-process-data does it
(``write_transforms``: OpenGL camera axes, nerfstudio's world change recorded in
``applied_transform``, points in sparse_pc.ply); both are loaded and must agree to 1e-6.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from geocues.colmap_io import read_model
from geocues.nerfstudio_io import read_transforms, write_transforms
from geocues.scene import Scene

from cues_synth import make_room_scene


@pytest.fixture(scope="module")
def colmap_scene(tmp_path_factory):
    return make_room_scene(tmp_path_factory.mktemp("ns") / "room", n_views=5, priors="all", n_sfm=120,
                           n_outliers=5)


def _export(scene_dir, out_dir, applied_transform=True, depth_dir=None):
    """transforms.json for the COLMAP scene at ``scene_dir`` into ``out_dir`` (images copied there
    unless it is the same folder; depth priors moved to ``depth_dir`` and named per frame)."""
    images, points = read_model(scene_dir / "sparse" / "0")
    if out_dir != scene_dir:
        shutil.copytree(scene_dir / "images", out_dir / "images")
    path = write_transforms(out_dir / "transforms.json", images, [out_dir / "images" / im.name for im in images],
                            points, applied_transform=applied_transform)
    if depth_dir is not None:
        (out_dir / depth_dir).mkdir()
        meta = json.loads(path.read_text())
        for fr in meta["frames"]:
            stem = fr["file_path"].rsplit("/", 1)[-1].rsplit(".", 1)[0]
            shutil.copy(scene_dir / "priors" / "depth" / f"{stem}.npy", out_dir / depth_dir / f"{stem}.npy")
            fr["depth_file_path"] = f"{depth_dir}/{stem}.npy"
        path.write_text(json.dumps(meta))
    return path


def _assert_same_cameras(a: Scene, b: Scene, same_paths: bool = True):
    assert len(a) == len(b) and a.train_indices == b.train_indices
    for ca, cb in zip(a.cameras, b.cameras):
        assert ca.name == cb.name and (ca.width, ca.height) == (cb.width, cb.height)
        if same_paths:
            assert ca.image_path == cb.image_path
        else:
            assert ca.image_path.name == cb.image_path.name and ca.image_path.is_file() and cb.image_path.is_file()
        np.testing.assert_allclose(cb.K, ca.K, atol=1e-6, rtol=0)
        np.testing.assert_allclose(cb.R, ca.R, atol=1e-6, rtol=0)
        np.testing.assert_allclose(cb.t, ca.t, atol=1e-6, rtol=0)


class TestRead:
    @pytest.mark.parametrize("applied_transform", [True, False])
    def test_same_cameras_and_points_as_colmap(self, colmap_scene, tmp_path, applied_transform):
        out = tmp_path / "ns"
        out.mkdir()
        path = _export(colmap_scene, out, applied_transform=applied_transform)
        meta = json.loads(path.read_text())
        assert ("applied_transform" in meta) == applied_transform and meta["camera_model"] == "OPENCV"
        ref, ns = Scene.load(colmap_scene), Scene.load(out)  # the folder: it has no COLMAP model
        assert ns.model_dir == path and ns.root == out
        _assert_same_cameras(ref, ns, same_paths=False)
        np.testing.assert_allclose(ns.points.xyz, ref.points.xyz, atol=1e-6, rtol=0)
        np.testing.assert_array_equal(ns.points.rgb, ref.points.rgb)
        assert ns.points.visible_in and all(len(v) == 0 for v in ns.points.visible_in.values())  # no tracks

    def test_json_beside_a_colmap_model(self, colmap_scene, tmp_path, caplog):
        """A folder with both: the folder is read as COLMAP, the file given directly as nerfstudio; the
        choice is said once (it was silent, new-user audit)."""
        scene_dir = tmp_path / "both"
        shutil.copytree(colmap_scene, scene_dir)
        path = _export(scene_dir, scene_dir)
        with caplog.at_level("WARNING", logger="geocues"):
            assert Scene.load(scene_dir).model_dir == scene_dir / "sparse" / "0"
            Scene.load(scene_dir)
        assert caplog.text.count("the COLMAP model is read; give") == 1, caplog.text
        assert str(path) in caplog.text
        ref, ns = Scene.load(scene_dir), Scene.load(path)
        _assert_same_cameras(ref, ns)
        for i in range(len(ref)):  # priors/ by stem still works
            np.testing.assert_array_equal(ns.depth_prior(i), ref.depth_prior(i))
        half_ref, half_ns = Scene.load(scene_dir, downscale=2.0), Scene.load(path, downscale=2.0)
        _assert_same_cameras(half_ref, half_ns)

    def test_depth_file_path_is_the_depth_prior(self, colmap_scene, tmp_path):
        out = tmp_path / "ns"
        out.mkdir()
        _export(colmap_scene, out, depth_dir="depth")
        ref, ns = Scene.load(colmap_scene), Scene.load(out)
        assert ns.has_depth_priors and not (out / "priors").exists()
        for i in range(len(ref)):
            assert ns.depth_prior_path(i) == out / "depth" / f"{ref.cameras[i].stem}.npy"
            np.testing.assert_array_equal(ns.depth_prior(i), ref.depth_prior(i))

    def test_info_command(self, colmap_scene, tmp_path, capsys):
        from cli.geocues_cli import main

        out = tmp_path / "ns"
        out.mkdir()
        _export(colmap_scene, out)
        assert main(["info", str(out)]) == 0
        text = capsys.readouterr().out
        assert "transforms.json" in text and "cameras    5" in text
        assert "(without tracks" in text and "mean track length 0.00" not in text  # no made-up figures

    def test_sfm_cues_match(self, colmap_scene, tmp_path):
        """geocues extract reads it: the SfM cues (same points, same filter) are the COLMAP scene's."""
        import geocues.extract as ex
        from geocues.cue_io import read_cues_ply

        out = tmp_path / "ns"
        out.mkdir()
        _export(colmap_scene, out)
        cfg = ex.ExtractConfig(lines=False, planes=False)
        a = read_cues_ply(ex.run(cfg, colmap_scene, tmp_path / "cues_colmap") / "cues.ply")
        b = read_cues_ply(ex.run(cfg, out, tmp_path / "cues_ns") / "cues.ply")
        assert len(a.xyz) > 0
        np.testing.assert_allclose(b.xyz, a.xyz, atol=1e-5, rtol=0)  # cue PLY stores float32


class TestBadInput:
    @pytest.fixture()
    def ns(self, colmap_scene, tmp_path):
        out = tmp_path / "ns"
        out.mkdir()
        return _export(colmap_scene, out)

    def _edit(self, path, fn):
        meta = json.loads(path.read_text())
        fn(meta)
        path.write_text(json.dumps(meta))

    @pytest.mark.parametrize("field", ["fl_x", "fl_y", "cx", "cy", "w", "h"])
    def test_missing_intrinsic(self, ns, field):
        self._edit(ns, lambda m: m.pop(field))
        with pytest.raises(ValueError, match=rf"{ns}: frame 0 \(images/00000.png\) has no '{field}'"):
            Scene.load(ns.parent)

    def test_per_frame_intrinsics_win(self, ns, colmap_scene):
        def move(m):
            for fr in m["frames"]:
                fr["fl_x"] = m["fl_x"]
            m.pop("fl_x")
        self._edit(ns, move)
        _assert_same_cameras(Scene.load(colmap_scene), Scene.load(ns.parent), same_paths=False)

    @pytest.mark.parametrize("edit, message", [
        (lambda m: m["frames"][2].pop("transform_matrix"), r"frame 2 \(images/00002.png\) has no 'transform_matrix'"),
        (lambda m: m["frames"][1].pop("file_path"), r"frame 1 has no 'file_path'"),
        (lambda m: m.pop("frames"), r"no 'frames'"),
        (lambda m: m.update(k1=0.1), r"frame 0 \(images/00000.png\) has lens distortion \('k1' = 0.1\)"),
        (lambda m: m.update(camera_model="OPENCV_FISHEYE"), r"camera_model 'OPENCV_FISHEYE'"),
        (lambda m: m.update(w=160.5), r"w=160.5"),
        (lambda m: m["frames"][0].update(transform_matrix=[[1, 0, 0]]), r"'transform_matrix' of shape \(1, 3\)"),
        (lambda m: m["frames"][0]["transform_matrix"][0].pop(), r"'transform_matrix' is not a matrix of numbers"),
        (lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(0, 2.0), r"not a rotation"),
        (lambda m: m["frames"][4]["transform_matrix"][1].__setitem__(3, float("nan")),
         r"frame 4 \(images/00004.png\) has a non-finite 'transform_matrix' \(row 1, column 3: nan\)"),
        (lambda m: m["frames"][4]["transform_matrix"][2].__setitem__(0, None), r"non-finite 'transform_matrix' \(row 2, column 0"),
        (lambda m: m.update(applied_transform=[[2, 0, 0, 0]]), r"'applied_transform' must be"),
        (lambda m: m["frames"][3].update(depth_file_path="depth/missing.npy"), r"depth_file_path is missing"),
        (lambda m: m.update(ply_file_path="nope.ply"), r"ply_file_path is missing"),
    ])
    def test_bad_fields_are_named(self, ns, edit, message):
        self._edit(ns, edit)
        with pytest.raises((ValueError, FileNotFoundError), match=message) as info:
            Scene.load(ns.parent)
        assert str(ns) in str(info.value)

    def test_not_json(self, ns):
        ns.write_text("{ not json")
        with pytest.raises(ValueError, match=rf"cannot read {ns}"):
            read_transforms(ns)

    def test_missing_image(self, ns):
        (ns.parent / "images" / "00003.png").unlink()
        with pytest.raises(FileNotFoundError, match=r"images/00003.png"):
            Scene.load(ns.parent)


def test_commands_that_take_a_colmap_model_take_a_nerfstudio_scene(colmap_scene, tmp_path):
    """`geocues sfm` mapped a nerfstudio scene from its images alone (its poses thrown away, an
    arbitrary unit), `rescale` refused it, and the scene folders `mvs` and `simulate-priors` wrote held
    no cameras at all. Now its cameras go along as a COLMAP model: the same cameras everywhere."""
    from geocues.rescale import RescaleConfig, run as rescale
    from geocues.sfm import link_scene

    ns = tmp_path / "ns"
    ns.mkdir()
    _export(colmap_scene, ns)
    scene = Scene.load(ns)
    out = tmp_path / "linked"  # what `geocues mvs` / `simulate-priors` write around their priors
    link_scene(ns, out, ("images", "sparse", "gt"))
    _assert_same_cameras(scene, Scene.load(out), same_paths=False)
    big = rescale(RescaleConfig(scale=2.0), ns, tmp_path / "x2")
    for a, b in zip(scene.cameras, Scene.load(big).cameras):
        np.testing.assert_allclose(b.center, 2.0 * a.center, atol=1e-6)
    from geocues import sfm

    seen = {}
    real = sfm.U.triangulate
    sfm.U.triangulate = lambda ref, *a, **k: seen.setdefault("ref", ref) and real(ref, *a, **k)
    try:
        sfm.run(sfm.SfmConfig(check_gt=False), ns, tmp_path / "ns_sfm")
    finally:
        sfm.U.triangulate = real
    assert seen["ref"].num_reg_images() == len(scene)  # triangulated with the known poses, not mapped
    meta = tmp_path / "ns_sfm" / "scene.json"
    assert not meta.is_file() or "arbitrary" not in meta.read_text()
    _assert_same_cameras(scene, Scene.load(tmp_path / "ns_sfm"), same_paths=False)


def test_a_step_that_needs_images_names_where_a_transforms_json_keeps_its_frames(tmp_path):
    """`geocues sfm` on a nerfstudio scene with its frames in rgb/ said only "no images folder at
    SCENE/images" (after `geocues info` advised it)."""
    from geocues.scene import no_images_folder

    (tmp_path / "rgb").mkdir()
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [{"file_path": "rgb/00000.png"}]}))
    msg = str(no_images_folder(tmp_path / "images"))
    assert "transforms.json keeps its frames elsewhere (in rgb/)" in msg and f"link that folder as {tmp_path / 'images'}" in msg


def test_a_blender_transforms_json_is_named_with_what_to_give(tmp_path):
    """A Blender / instant-ngp file (camera_angle_x, no fl_x) said only "frame 0 has no 'fl_x'"."""
    (tmp_path / "images").mkdir()
    frame = {"file_path": "./images/00000", "transform_matrix": np.eye(4).tolist()}
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": [frame]}))
    with pytest.raises(ValueError, match=r"is a Blender / instant-ngp transforms.json \(camera_angle_x\), which is "
                                         r"not read: give nerfstudio's intrinsics fl_x = fl_y = w / \(2 tan"):
        Scene.load(tmp_path)
