"""Outputs the standard 3DGS tools open (issue 14): the exact 62-float reference PLY and its
cue_type.npy sidecar, other writers' PLYs read back, the reference run folder (splat/export.py),
and the cue files to look at (lines3d.ply, cues_by_type.ply)."""

from __future__ import annotations

import json
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement
from scipy.spatial.transform import Rotation

from geocues.cue_io import CUE_TYPE_COLORS, CueCloud, write_cues_by_type_ply, write_lines_ply
from geocues.scene import Camera, Scene
from geocues.types import CueType
from splat.export import write_3dgs_run
from splat.gaussians import PLY_FIELDS, cue_type_path, load_ply, save_ply

REFERENCE_FIELDS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                    + [f"f_rest_{i}" for i in range(45)]
                    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def random_params(n: int, sh_degree: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {"means": torch.randn(n, 3, generator=g), "quats": torch.randn(n, 4, generator=g),
            "scales": torch.randn(n, 3, generator=g), "opacities": torch.randn(n, generator=g),
            "sh0": torch.randn(n, 1, 3, generator=g), "shN": torch.randn(n, (sh_degree + 1) ** 2 - 1, 3, generator=g)}


def fixed_stride_read(path: Path) -> tuple[list[str], np.ndarray]:
    """What SIBR-like readers do: trust the header's float list and read 248-byte records."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    elements = [ln for ln in lines if ln.startswith("element ")]
    assert len(elements) == 1 and elements[0].startswith("element vertex "), elements
    n = int(elements[0].split()[2])
    props = [ln.split() for ln in lines if ln.startswith("property ")]
    assert all(p[1] == "float" for p in props), props
    body = raw[end:]
    assert len(body) == n * 248, (len(body), n)
    return [p[2] for p in props], np.frombuffer(body, dtype="<f4").reshape(n, 62)


class TestSavePly:
    def test_exact_reference_layout_and_stride(self, tmp_path):
        params, cue_type = random_params(7, 3), torch.tensor([0, 1, 2, 2, 1, 0, 2])
        path = save_ply(tmp_path / "point_cloud.ply", params, cue_type)
        names, rows = fixed_stride_read(path)
        assert names == REFERENCE_FIELDS == PLY_FIELDS
        np.testing.assert_array_equal(rows[:, 0:3], params["means"].numpy())
        assert not rows[:, 3:6].any()  # normals zero, as the reference writes them
        np.testing.assert_array_equal(rows[:, 6:9], params["sh0"][:, 0].numpy())
        # f_rest_{c * 15 + k} = shN[:, k, c] (the reference's channel-major order)
        for c in range(3):
            np.testing.assert_array_equal(rows[:, 9 + 15 * c: 24 + 15 * c], params["shN"][:, :, c].numpy())
        np.testing.assert_array_equal(rows[:, 54], params["opacities"].numpy())
        np.testing.assert_array_equal(rows[:, 55:58], params["scales"].numpy())
        np.testing.assert_array_equal(rows[:, 58:62], params["quats"].numpy())
        v = PlyData.read(str(path))["vertex"]
        assert [p.name for p in v.properties] == REFERENCE_FIELDS and len(v.data) == 7
        side = tmp_path / "cue_type.npy"
        assert cue_type_path(path) == side
        stored = np.load(side)
        assert stored.dtype == np.uint8 and stored.tolist() == cue_type.tolist()

    def test_sh_degree_1_padded_on_disk_equal_after_load(self, tmp_path):
        params = random_params(5, 1)
        path = save_ply(tmp_path / "model.ply", params, torch.zeros(5, dtype=torch.long))
        assert cue_type_path(path) == tmp_path / "model.cue_type.npy" and cue_type_path(path).is_file()
        names, rows = fixed_stride_read(path)
        assert len(names) == 62
        f_rest = rows[:, 9:54].reshape(5, 3, 15)
        np.testing.assert_array_equal(f_rest[:, :, :3], params["shN"].numpy().transpose(0, 2, 1))
        assert not f_rest[:, :, 3:].any()
        loaded, types = load_ply(path, sh_degree=1)
        for k in params:
            torch.testing.assert_close(loaded[k], params[k], rtol=0, atol=0, msg=k)
        assert types.tolist() == [0] * 5

    @pytest.mark.parametrize("key", ["means", "scales", "shN"])
    def test_non_finite_refused(self, tmp_path, key):
        params = random_params(4, 2)
        params[key].view(-1)[1] = float("nan") if key != "scales" else float("inf")
        with pytest.raises(ValueError, match=rf"bad\.ply.*params\['{key}'\].*non-finite"):
            save_ply(tmp_path / "bad.ply", params)
        assert not any(tmp_path.iterdir())  # nothing written, no temporary left


def write_vertex_ply(path: Path, columns: dict[str, np.ndarray]) -> Path:
    n = len(next(iter(columns.values())))
    rec = np.empty(n, dtype=[(k, "u1" if k == "cue_type" else "<f4") for k in columns])
    for k, a in columns.items():
        rec[k] = a
    PlyData([PlyElement.describe(rec, "vertex")], text=False).write(str(path))
    return path


def columns_of(params: dict[str, torch.Tensor], normals: bool) -> dict[str, np.ndarray]:
    """The columns another writer stores: x y z [nx ny nz] f_dc f_rest (channel-major) opacity scale rot."""
    p = {k: v.numpy() for k, v in params.items()}
    cols = {a: p["means"][:, i] for i, a in enumerate("xyz")}
    if normals:
        cols.update({f"n{a}": np.full(len(p["means"]), 0.5, np.float32) for a in "xyz"})
    cols.update({f"f_dc_{c}": p["sh0"][:, 0, c] for c in range(3)})
    k = p["shN"].shape[1]
    cols.update({f"f_rest_{c * k + j}": p["shN"][:, j, c] for c in range(3) for j in range(k)})
    cols["opacity"] = p["opacities"]
    cols.update({f"scale_{i}": p["scales"][:, i] for i in range(3)})
    cols.update({f"rot_{i}": p["quats"][:, i] for i in range(4)})
    return cols


class TestLoadPly:
    @pytest.mark.parametrize("sh_degree", [0, 1, 3])
    def test_gsplat_export(self, tmp_path, sh_degree):
        params = random_params(6, sh_degree)
        path = write_vertex_ply(tmp_path / "splats.ply", columns_of(params, normals=False))
        loaded, types = load_ply(path)
        assert types is None
        for k in params:
            torch.testing.assert_close(loaded[k], params[k], rtol=0, atol=0, msg=k)
        at3, _ = load_ply(path, sh_degree=3)
        assert at3["shN"].shape == (6, 15, 3)
        torch.testing.assert_close(at3["shN"][:, : params["shN"].shape[1]], params["shN"], rtol=0, atol=0)

    def test_reference_layout_and_old_cue_type_property(self, tmp_path):
        params = random_params(5, 3, seed=3)
        cols = columns_of(params, normals=True)
        assert list(cols) == REFERENCE_FIELDS
        loaded, types = load_ply(write_vertex_ply(tmp_path / "point_cloud.ply", cols))
        assert types is None
        for k in params:
            torch.testing.assert_close(loaded[k], params[k], rtol=0, atol=0, msg=k)
        old = write_vertex_ply(tmp_path / "old.ply", {**cols, "cue_type": np.array([2, 0, 1, 1, 0])})
        assert load_ply(old)[1].tolist() == [2, 0, 1, 1, 0]

    def test_bad_files_name_the_file(self, tmp_path):
        cols = columns_of(random_params(3, 1), normals=False)
        no_x = write_vertex_ply(tmp_path / "no_x.ply", {k: v for k, v in cols.items() if k != "x"})
        with pytest.raises(ValueError, match=r"no_x\.ply.*\['x'\]"):
            load_ply(no_x)
        odd = write_vertex_ply(tmp_path / "odd.ply", {k: v for k, v in cols.items() if k != "f_rest_8"})
        with pytest.raises(ValueError, match=r"odd\.ply: 8 f_rest"):
            load_ply(odd)
        (tmp_path / "junk.ply").write_bytes(b"not a ply\n")
        with pytest.raises(ValueError, match=r"junk\.ply"):
            load_ply(tmp_path / "junk.ply")
        good = write_vertex_ply(tmp_path / "point_cloud.ply", cols)
        np.save(tmp_path / "cue_type.npy", np.zeros(2, np.uint8))  # wrong length
        with pytest.raises(ValueError, match=r"cue_type\.npy holds 2 cue types for the 3"):
            load_ply(good)


def tiny_scene(root: Path) -> Scene:
    cams = []
    for i in range(3):
        R = Rotation.from_euler("yx", [0.4 * i, 0.1]).as_matrix()
        t = np.array([0.1 * i, -0.2, 1.0 + i])
        K = np.array([[50.0 + i, 0, 16], [0, 52.0, 12], [0, 0, 1]])
        cams.append(Camera(index=i, image_id=i + 1, name=f"{i:05d}.png", image_path=root / "images" / f"{i:05d}.png",
                           width=32, height=24, K=K, R=R, t=t))
    return Scene(root, cams, None, {}, test_every=8, downscale=2.0, model_dir=root / "sparse" / "0")


def test_write_3dgs_run(tmp_path):
    scene = tiny_scene(tmp_path / "scene")
    for cam in scene.cameras[1:]:  # photos of 65x48 trained at --downscale 2 (32x24)
        cam.source_width, cam.source_height = 65, 48
    params, cue_type = random_params(4, 1), torch.tensor([0, 1, 2, 0])
    run = tmp_path / "out.partial"  # train.py writes into the staging folder, published as out/
    ply = write_3dgs_run(run, params, cue_type, scene, {"downscale": 2.0, "test_every": 8,
                                                         "background": (1.0, 1.0, 1.0)}, 300)
    assert ply == run / "point_cloud" / "iteration_300" / "point_cloud.ply"
    assert len(fixed_stride_read(ply)[0]) == 62
    loaded, types = load_ply(ply, sh_degree=1)
    torch.testing.assert_close(loaded["shN"], params["shN"], rtol=0, atol=0)
    assert types.tolist() == [0, 1, 2, 0] and (ply.parent / "cue_type.npy").is_file()

    args = eval((run / "cfg_args").read_text(), {"Namespace": Namespace})  # what the reference does
    assert list(vars(args)) == ["sh_degree", "source_path", "model_path", "images", "depths", "resolution",
                                "white_background", "train_test_exp", "data_device", "eval"]
    assert args.sh_degree == 3 and args.images == "images" and args.resolution == 2
    assert args.source_path == str((tmp_path / "scene").resolve())
    assert args.model_path == str((tmp_path / "out").resolve())
    assert args.white_background is True and args.eval is True

    cams = json.loads((run / "cameras.json").read_text())
    assert [c["id"] for c in cams] == [0, 1, 2] and [c["img_name"] for c in cams] == ["00000", "00001", "00002"]
    for entry, cam in zip(cams, scene.cameras):
        np.testing.assert_allclose(entry["position"], cam.center, atol=1e-12)
        np.testing.assert_allclose(np.array(entry["rotation"]), cam.R.T, atol=1e-12)  # camera-to-world
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = entry["rotation"], entry["position"]
        np.testing.assert_allclose(np.linalg.inv(c2w), cam.world_to_camera, atol=1e-12)
        # the photos' own size, as the reference writes it from the COLMAP model whatever its -r (a run at
        # --downscale 2 wrote half of it, and SIBR / tools pairing the file with the photos read it so)
        sx, sy = cam.source_size[0] / 32, cam.source_size[1] / 24
        assert (entry["width"], entry["height"]) == cam.source_size == ((32, 24) if cam.index == 0 else (65, 48))
        assert (entry["fx"], entry["fy"]) == (cam.K[0, 0] * sx, cam.K[1, 1] * sy)
        assert (entry["cx"], entry["cy"]) == (cam.K[0, 2] * sx, cam.K[1, 2] * sy)  # extra keys the reference ignores
    assert not (run / "input.ply").exists()  # a scene without SfM points has no proxy to write


def test_cameras_json_of_a_downscaled_scene_is_the_photos_own_camera(tmp_path):
    """A scene loaded at --downscale 2 (odd photo sizes: 67x51 -> 34x26, each side rounded) writes the
    cameras of the scene loaded at its own size, to rounding, as the reference writes its COLMAP model."""
    from cues_synth import make_room_scene
    from splat.export import camera_to_json

    root = make_room_scene(tmp_path / "room", n_views=3, w=67, h=51)
    half, full = Scene.load(root, downscale=2.0), Scene.load(root)
    assert (half.cameras[0].width, half.cameras[0].height) == (34, 26)
    for i, (h, f) in enumerate(zip(half.cameras, full.cameras)):
        e = camera_to_json(i, h)
        assert (e["width"], e["height"]) == (f.width, f.height) == h.source_size == (67, 51)
        np.testing.assert_allclose([e["fx"], e["fy"], e["cx"], e["cy"]],
                                   [f.K[0, 0], f.K[1, 1], f.K[0, 2], f.K[1, 2]], rtol=1e-12)


def test_the_reference_format_s_limits_are_named_and_input_ply_written(tmp_path, caplog):
    """What SIBR / the reference render.py read differently from the run is warned about when written:
    an off-centre principal point (they project through the centre: a cropped scene rendered from
    cameras.json shifted by 8 px), --test-every other than their llffhold 8 (their test views would
    be training views), a grey background (white_background=False: black); input.ply holds the
    scene's SfM points in storePly's layout (SIBR's proxy mesh)."""
    import logging

    from geocues.scene import Points3D
    from splat.render_run import cameras_from_json

    scene = tiny_scene(tmp_path / "scene")
    rng = np.random.default_rng(0)
    xyz, rgb = rng.normal(size=(5, 3)), rng.integers(0, 256, (5, 3), dtype=np.uint8)
    scene.points = Points3D(np.arange(5), xyz, rgb, np.zeros(5), np.full(5, 3))
    params = random_params(4, 1)
    centred = {"downscale": 2.0, "test_every": 8, "background": (0.0, 0.0, 0.0)}
    with caplog.at_level(logging.WARNING, logger="splat"):
        write_3dgs_run(tmp_path / "a", params, None, scene, centred, 10)
    assert caplog.text == ""  # K's centre is (16, 12) of 32x24: nothing to say
    v = PlyData.read(str(tmp_path / "a" / "input.ply"))["vertex"]
    assert [p.name for p in v.properties] == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), xyz, atol=1e-6)
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), rgb)
    scene.cameras[1].K[0, 2] += 8.0  # a cropped photo
    with caplog.at_level(logging.WARNING, logger="splat"):
        write_3dgs_run(tmp_path / "b", params, None, scene, {**centred, "test_every": 5,
                                                             "background": (0.5, 0.5, 0.5)}, 10)
    assert "principal point is up to 8.0 px off the image centre" in caplog.text
    assert "held out every 5th view (--test-every 5)" in caplog.text and "every 8th (llffhold)" in caplog.text
    assert "background (0.5, 0.5, 0.5) is neither black nor white" in caplog.text
    assert "where the reference render.py does not look" not in caplog.text  # SCENE/sparse/0
    caplog.clear()
    scene.model_dir = tmp_path / "scene" / "transforms.json"
    with caplog.at_level(logging.WARNING, logger="splat"):
        write_3dgs_run(tmp_path / "c", params, None, scene, centred, 10)
    assert "the scene is a nerfstudio transforms.json: the reference render.py" in caplog.text
    scene.model_dir = tmp_path / "scene" / "colmap" / "sparse"
    with caplog.at_level(logging.WARNING, logger="splat"):
        write_3dgs_run(tmp_path / "d", params, None, scene, centred, 10)
    assert "colmap/sparse, where the reference render.py does not look (source_path/sparse/0" in caplog.text
    back = cameras_from_json(tmp_path / "b" / "cameras.json")  # `splat render --views` keeps the offset
    np.testing.assert_allclose(back[1].K, scene.cameras[1].K)
    entries = json.loads((tmp_path / "b" / "cameras.json").read_text())
    for e in entries:
        del e["cx"], e["cy"]
    (tmp_path / "ref.json").write_text(json.dumps(entries))  # a reference-written file: the centre
    assert cameras_from_json(tmp_path / "ref.json")[1].K[0, 2] == 16.0


def test_lines3d_ply_opens_in_open3d(tmp_path):
    import open3d as o3d

    rng = np.random.default_rng(1)
    segments, colors = rng.normal(size=(9, 2, 3)), rng.random((9, 3))
    path = write_lines_ply(tmp_path / "lines3d.ply", segments, colors)
    ls = o3d.io.read_line_set(str(path))
    assert len(ls.lines) == 9
    pts, lines = np.asarray(ls.points), np.asarray(ls.lines)
    np.testing.assert_allclose(pts[lines], segments, atol=1e-6)
    np.testing.assert_allclose(np.asarray(ls.colors), np.round(colors * 255) / 255, atol=1e-6)
    edge = PlyData.read(str(path))["edge"]
    assert [p.name for p in edge.properties] == ["vertex1", "vertex2", "red", "green", "blue"]
    plain = write_lines_ply(tmp_path / "plain.ply", segments)
    assert [p.name for p in PlyData.read(str(plain))["edge"].properties] == ["vertex1", "vertex2"]


def test_cues_by_type_ply_has_one_colour_per_type(tmp_path):
    rng = np.random.default_rng(2)
    cloud = CueCloud.concat([CueCloud.make(rng.normal(size=(n, 3)), rng.random((n, 3)), t)
                             for n, t in ((5, CueType.SFM), (7, CueType.LINE), (4, CueType.PLANE))])
    v = PlyData.read(str(write_cues_by_type_ply(tmp_path / "cues_by_type.ply", cloud)))["vertex"].data
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    assert len(np.unique(rgb, axis=0)) == 3
    for t in CueType:
        sel = cloud.cue_type == t.value
        assert (rgb[sel] == CUE_TYPE_COLORS[t]).all(), t.name
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), cloud.xyz, atol=1e-6)
