"""Typed Gaussian initialisation from cues and the 3DGS PLY format (splat/gaussians.py)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from geocues.cue_io import CueCloud
from geocues.types import CueType
from splat.camera import Camera
from splat.gaussians import InitConfig, init_from_cues, load_ply, save_ply, scene_scale, tangent_scales
from splat.projection import quat_to_rotmat
from splat.rasterize import render
from splat.sh import sh_to_rgb


def grid_plane(n_side: int, step: float, z: float) -> np.ndarray:
    u, v = np.meshgrid(np.arange(n_side) * step, np.arange(n_side) * step)
    return np.stack([u.ravel() - 0.5 * step * n_side, v.ravel() - 0.5 * step * n_side,
                     np.full(u.size, z)], 1)


def mixed_cloud() -> CueCloud:
    rng = np.random.default_rng(0)
    plane = grid_plane(20, 0.05, 2.0)
    normal = np.tile([0.0, 0.0, -1.0], (len(plane), 1))
    sfm = rng.normal(size=(30, 3)) * 0.3 + [0.0, 0.0, 2.5]
    line = np.stack([np.linspace(-0.5, 0.5, 25), np.zeros(25), np.full(25, 1.9)], 1)
    return CueCloud.concat([
        CueCloud.make(plane, np.full((len(plane), 3), 200, np.uint8), CueType.PLANE, normal=normal),
        CueCloud.make(sfm, rng.integers(0, 255, (30, 3)).astype(np.uint8), CueType.SFM),
        CueCloud.make(line, np.full((25, 3), 0.25), CueType.LINE),
    ])


def test_init_types_scales_frames_and_colours():
    cues = mixed_cloud()
    params, cue_type = init_from_cues(cues, sh_degree=2, cfg=InitConfig(flat_ratio=0.1))
    n = len(cues)
    assert params["means"].shape == (n, 3) and params["shN"].shape == (n, 8, 3)
    assert cue_type.dtype == torch.int64 and cue_type.tolist() == cues.cue_type.tolist()
    plane = cue_type == CueType.PLANE
    # plane cues on a 5 cm grid: 3 nearest neighbours are at 5 cm; flat along the normal (z)
    s = params["scales"].exp()
    inner = plane & (params["means"][:, 0].abs() < 0.4) & (params["means"][:, 1].abs() < 0.4)
    torch.testing.assert_close(s[inner, 0], torch.full((int(inner.sum()),), 0.05), rtol=1e-4, atol=0)
    torch.testing.assert_close(s[plane, 2], 0.1 * s[plane, 0], rtol=1e-5, atol=0)
    third_axis = quat_to_rotmat(params["quats"][plane])[:, :, 2]
    torch.testing.assert_close(third_axis, torch.tensor([0.0, 0.0, -1.0]).expand_as(third_axis), rtol=0, atol=1e-6)
    # no normal: isotropic, identity rotation
    sfm = cue_type == CueType.SFM
    assert torch.allclose(s[sfm, 0], s[sfm, 2]) and torch.allclose(params["quats"][sfm, 0], torch.ones(30))
    # colour: the DC term reproduces the cue colour in any direction
    rgb = sh_to_rgb(params["sh0"], params["shN"], torch.randn(n, 3), 2)
    torch.testing.assert_close(rgb, torch.as_tensor(cues.rgb / 255.0, dtype=torch.float32), rtol=0, atol=1e-6)
    assert torch.allclose(torch.sigmoid(params["opacities"]), torch.tensor(0.1))


def test_init_bounds_duplicates_and_isolated_points():
    xyz = np.array([[0.0, 0.0, 1.0]] * 4 + [[50.0, 0.0, 1.0]])
    cues = CueCloud.make(xyz, np.zeros((5, 3), np.uint8), CueType.SFM)
    xyz = np.concatenate([xyz, grid_plane(10, 0.01, 1.0)])  # median neighbour distance 1 cm
    cues = CueCloud.make(xyz, np.zeros((len(xyz), 3), np.uint8), CueType.SFM)
    params, _ = init_from_cues(cues, 0, cfg=InitConfig(min_scale=1e-4, max_scale_mult=10.0))
    s = params["scales"].exp()
    assert torch.isfinite(params["scales"]).all()
    assert float(s.min()) == pytest.approx(1e-4, rel=1e-5) and float(s.max()) == pytest.approx(0.1, rel=1e-5)


def test_init_rejects_bad_input():
    with pytest.raises(ValueError, match="empty"):
        init_from_cues(CueCloud.empty(), 3)
    with pytest.raises(ValueError, match="sh_degree"):
        init_from_cues(mixed_cloud(), 4)


def test_tangent_scales_and_scene_scale():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 2.0, 0]])
    np.testing.assert_allclose(tangent_scales(pts, knn=1), [1.0, 1.0, 2.0])
    np.testing.assert_allclose(tangent_scales(pts, knn=5), np.sqrt([(1 + 4) / 2, (1 + 5) / 2, (4 + 5) / 2]))
    assert scene_scale(np.array([[0.0, 0, 0], [2.0, 0, 0]])) == pytest.approx(1.1)
    assert scene_scale(np.zeros((1, 3))) == 1.0
    # cameras turning on the spot in a 10 m wide room: the room sets the scale
    room = np.random.default_rng(0).uniform(-5, 5, (1000, 3))
    assert 2.0 < scene_scale(np.zeros((3, 3)), room) < 4.5


def test_initialised_plane_cues_render_their_plane():
    """Plane cues at z = 2 m seen head-on: the initial Gaussians already render depth 2 and normal -z."""
    cues = CueCloud.make(grid_plane(60, 0.02, 2.0), np.full((3600, 3), 128, np.uint8), CueType.PLANE,
                         normal=np.tile([0.0, 0.0, -1.0], (3600, 1)))
    # thin discs (flat_ratio 1e-3): at the default 0.1 the RaDe-GS normal here tilts by up to 3e-3 off-axis
    params, _ = init_from_cues(cues, 0, cfg=InitConfig(flat_ratio=1e-3, min_scale=1e-6))
    params["opacities"][:] = 4.0  # opaque, so that the centre pixels are covered
    K = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    out = render(params, Camera.from_Rt(K, np.eye(3), np.zeros(3), 32, 24), backend="torch")
    centre = out["alpha"] > 0.99
    assert int(centre.sum()) > 300
    torch.testing.assert_close(out["depth"][centre], torch.full((int(centre.sum()),), 2.0), rtol=0, atol=1e-4)
    assert float((out["normal"][centre] - torch.tensor([0.0, 0.0, -1.0])).abs().max()) < 1e-4


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_ply_round_trip_and_3dgs_layout(tmp_path, sh_degree):
    params, cue_type = init_from_cues(mixed_cloud(), sh_degree)
    params["shN"] = torch.randn_like(params["shN"])
    path = save_ply(tmp_path / "point_cloud.ply", params, cue_type)
    loaded, loaded_type = load_ply(path, sh_degree=sh_degree)
    for k in params:
        torch.testing.assert_close(loaded[k], params[k], rtol=0, atol=0, msg=k)
    assert loaded_type.tolist() == cue_type.tolist()
    # on disk: always degree 3 (45 f_rest), whatever the training degree; no cue_type inside
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert f"element vertex {len(cue_type)}" in header and header.count("f_rest_") == 45
    assert "cue_type" not in header and (tmp_path / "cue_type.npy").is_file()
    padded, _ = load_ply(path)  # without sh_degree: what the file holds, 15 rows, zeros above the degree
    k = params["shN"].shape[1]
    assert padded["shN"].shape == (len(cue_type), 15, 3)
    torch.testing.assert_close(padded["shN"][:, :k], params["shN"], rtol=0, atol=0)
    assert not padded["shN"][:, k:].any()
    # channel-major like 3DGS: f_rest_0 .. f_rest_14 are the red channel's 15 coefficients
    from plyfile import PlyData
    v = PlyData.read(str(path))["vertex"].data
    if k:
        np.testing.assert_array_equal(v[f"f_rest_{k - 1}"], params["shN"][:, k - 1, 0].numpy())
        np.testing.assert_array_equal(v["f_rest_15"], params["shN"][:, 0, 1].numpy())
        np.testing.assert_array_equal(v["f_rest_30"], params["shN"][:, 0, 2].numpy())
    if k < 15:
        assert not np.any(v[f"f_rest_{k}"]) and not np.any(v["f_rest_44"])


def test_load_ply_trims_only_zero_bands(tmp_path):
    params, cue_type = init_from_cues(mixed_cloud(), 3)
    params["shN"] = torch.randn_like(params["shN"])
    path = save_ply(tmp_path / "g.ply", params, cue_type)
    assert (tmp_path / "g.cue_type.npy").is_file()  # not point_cloud.ply: <stem>.cue_type.npy
    with pytest.raises(ValueError, match="non-zero SH coefficients above degree 1"):
        load_ply(path, sh_degree=1)
    params["shN"] = params["shN"][:, :0]  # degree 0 read at degree 2: zero-padded rows
    save_ply(path, params)
    loaded, loaded_type = load_ply(path, sh_degree=2)
    assert loaded["shN"].shape == (len(cue_type), 8, 3) and not loaded["shN"].any()
    assert loaded_type is None and not (tmp_path / "g.cue_type.npy").exists()  # stale sidecar removed


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_padded_shN_renders_like_the_trained_degree(tmp_path, backend):
    """Regression (issue 14): files are padded to degree 3; the renderer must give the same image
    from 15 rows (degree inferred, or told 1) as from the trained 3 rows with sh_degree=1."""
    from splat.composite import available_backends
    if backend not in available_backends():
        pytest.skip(f"backend {backend} unavailable")
    params, cue_type = init_from_cues(mixed_cloud(), 1)
    params["shN"] = 0.3 * torch.randn_like(params["shN"])
    params["opacities"][:] = 2.0
    padded, _ = load_ply(save_ply(tmp_path / "point_cloud.ply", params, cue_type))
    assert padded["shN"].shape[1] == 15
    R = Rotation.from_euler("x", 0.2).as_matrix()  # oblique view: the degree-1 band matters
    cam = Camera.from_Rt(np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]), R, np.zeros(3), 32, 24)
    ref = render(params, cam, sh_degree=1, backend=backend)["rgb"]
    flat = render({**params, "shN": torch.zeros_like(params["shN"])}, cam, sh_degree=1, backend=backend)["rgb"]
    assert float((ref - flat).abs().max()) > 1e-2  # the test can fail: the SH band changes the image
    for degree in (None, 1):
        torch.testing.assert_close(render(padded, cam, sh_degree=degree, backend=backend)["rgb"], ref,
                                   rtol=0, atol=1e-6)


def test_load_ply_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no Gaussian PLY"):
        load_ply(tmp_path / "missing.ply")
    from geocues.cue_io import write_cues_ply
    write_cues_ply(tmp_path / "cues.ply", mixed_cloud())
    with pytest.raises(ValueError, match="not a 3DGS Gaussian PLY"):
        load_ply(tmp_path / "cues.ply")


def test_load_ply_refuses_truncated_and_non_finite_files(tmp_path):
    """Bad-input table rows: a Gaussian PLY cut in its data or header, or with NaN values, is one
    ValueError naming the file (plyfile reads what it can otherwise; NaN would train or render NaN)."""
    n = 10
    g = torch.Generator().manual_seed(0)
    params = {"means": torch.randn(n, 3, generator=g), "quats": torch.randn(n, 4, generator=g),
              "scales": torch.randn(n, 3, generator=g), "opacities": torch.randn(n, generator=g),
              "sh0": torch.randn(n, 1, 3, generator=g), "shN": torch.zeros(n, 15, 3)}
    data = save_ply(tmp_path / "g.ply", params).read_bytes()
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    for name, blob in (("data", data[:-300]), ("header", data[:header_end - 30])):
        (tmp_path / f"cut_{name}.ply").write_bytes(blob)
        with pytest.raises(ValueError, match=rf"cut_{name}.ply is truncated or damaged"):
            load_ply(tmp_path / f"cut_{name}.ply")
    bad = bytearray(data)
    bad[header_end + 4 * 62 + 4:header_end + 4 * 62 + 8] = np.float32(np.nan).tobytes()  # row 1, y
    (tmp_path / "nan.ply").write_bytes(bytes(bad))
    with pytest.raises(ValueError, match=r"nan.ply holds non-finite values \(Gaussians per parameter: means 1\)"):
        load_ply(tmp_path / "nan.ply")


def test_thin_planes_leaves_room_in_the_budget():
    """--init.plane-share: only PLANE seeds are dropped, down to share x budget in all; off, within
    the budget or without one nothing changes; the same seed drops the same points."""
    from splat.init_gaussians import thin_planes

    rng = np.random.default_rng(0)
    n = {CueType.SFM: 100, CueType.LINE: 200, CueType.PLANE: 1000}
    cloud = CueCloud.concat([CueCloud.make(rng.uniform(0, 1, (k, 3)), np.zeros((k, 3), np.uint8), t)
                             for t, k in n.items()])
    out = thin_planes(cloud, 0.5, 1000, seed=3)
    assert len(out) == 500 and out.counts() == {"SFM": 100, "LINE": 200, "PLANE": 200}
    assert np.array_equal(out.xyz, thin_planes(cloud, 0.5, 1000, seed=3).xyz)
    assert not np.array_equal(out.xyz, thin_planes(cloud, 0.5, 1000, seed=4).xyz)
    assert thin_planes(cloud, 0.2, 1000).counts()["PLANE"] == 0  # SFM and LINE are never dropped
    for share, budget in ((0.0, 1000), (0.5, 0), (1.0, 2000)):
        assert thin_planes(cloud, share, budget) is cloud
    with pytest.raises(ValueError, match="plane-share"):
        thin_planes(cloud, 1.5, 1000)


def test_init_cloud_over_the_budget_warns_unless_thinned(tmp_path, caplog):
    """`splat train` with a cue cloud that fills the budget says so and names --init.plane-share;
    with it the cloud is thinned to share x budget."""
    import logging

    from geocues.cue_io import write_cues_ply
    from splat.init_gaussians import load_init_cloud
    from splat.train_config import TrainConfig

    rng = np.random.default_rng(0)
    cloud = CueCloud.concat([CueCloud.make(rng.uniform(0, 1, (k, 3)), np.zeros((k, 3), np.uint8), t)
                             for t, k in ((CueType.LINE, 300), (CueType.PLANE, 1000))])
    write_cues_ply(tmp_path / "cues.ply", cloud)
    cfg = TrainConfig()
    cfg.strategy.max_gaussians = 1400
    with caplog.at_level(logging.WARNING, logger="splat"):
        assert len(load_init_cloud(cfg, None, tmp_path / "cues.ply")) == 1300
    assert "--init.plane-share" in caplog.text and "93%" in caplog.text
    caplog.clear()
    cfg.init.plane_share = 0.5
    with caplog.at_level(logging.WARNING, logger="splat"):
        assert load_init_cloud(cfg, None, tmp_path / "cues.ply").counts()["PLANE"] == 400
    assert "plane-share" not in caplog.text
    cfg.init.plane_share, cfg.strategy.max_gaussians = 0.0, 1  # over the budget: no percentage of it
    with caplog.at_level(logging.WARNING, logger="splat"):
        assert len(load_init_cloud(cfg, None, tmp_path / "cues.ply")) == 1300
    assert "over --strategy.max-gaussians 1: training starts from all 1300 and densification adds none" in caplog.text
    assert "%" not in caplog.text
    caplog.clear()
    cfg.init.plane_share, cfg.strategy.max_gaussians = 0.0, 2000  # within 90 %: silent
    with caplog.at_level(logging.WARNING, logger="splat"):
        load_init_cloud(cfg, None, tmp_path / "cues.ply")
    assert caplog.text == ""


def test_auto_budget_follows_the_training_views(tmp_path, caplog):
    """--strategy.max-gaussians auto (the default; it was no limit, and a short run grew 6k cue
    Gaussians to 2.5 M on a 24-view room at 160x120) is 2 x the pixels of the largest training view
    at the training resolution, at least 100k; a number, 0 included, is kept as given."""
    from cues_synth import make_room_scene
    from geocues.cue_io import write_cues_ply
    from geocues.scene import Scene
    from splat.init_gaussians import load_init_cloud, with_budget
    from splat.strategy import IndoorStrategyConfig
    from splat.train_config import TrainConfig

    root = make_room_scene(tmp_path / "room", n_views=2, w=400, h=300)
    with caplog.at_level(logging.INFO, logger="splat"):
        assert with_budget(TrainConfig(), Scene.load(root)).strategy.max_gaussians == 240_000  # 2 x 400 x 300
    assert "Gaussian budget 240000 (--strategy.max-gaussians auto" in caplog.text and "400x300 px" in caplog.text
    assert with_budget(TrainConfig(), Scene.load(root, downscale=1.25)).strategy.max_gaussians == 154_000  # 320x240
    assert with_budget(TrainConfig(), Scene.load(root, downscale=4)).strategy.max_gaussians == 100_000  # the floor
    for given in (0, 123):
        cfg = TrainConfig(strategy=IndoorStrategyConfig(max_gaussians=given))
        assert with_budget(cfg, Scene.load(root)) is cfg
    from types import SimpleNamespace as NS  # views of several sizes: the largest training view sets it

    mixed = NS(cameras=[NS(width=640, height=480), NS(width=400, height=300), NS(width=320, height=240)],
               train_indices=[1, 2])  # the 640x480 view is held out
    assert with_budget(TrainConfig(), mixed).strategy.max_gaussians == 240_000
    # the cue cloud is held to the resolved budget
    rng = np.random.default_rng(0)
    n = 100_500
    write_cues_ply(tmp_path / "cues.ply", CueCloud.make(rng.uniform(0, 1, (n, 3)), np.zeros((n, 3), np.uint8),
                                                        CueType.LINE))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="splat"):
        load_init_cloud(TrainConfig(), Scene.load(root, downscale=4), tmp_path / "cues.ply")
    assert "over --strategy.max-gaussians 100000" in caplog.text
    with pytest.raises(ValueError, match="resolved from the training views"):
        load_init_cloud(TrainConfig(), None, tmp_path / "cues.ply")  # no scene to size it by


def test_init_ply_over_the_budget_warns(tmp_path, caplog):
    """--init-ply with more Gaussians than the budget (a 3DGS export of millions against the default)
    started and never grew, in silence; now it says so."""
    from splat.init_gaussians import initial_gaussians
    from splat.strategy import IndoorStrategyConfig
    from splat.train_config import TrainConfig

    rng = np.random.default_rng(0)
    params, cue_type = init_from_cues(CueCloud.make(rng.uniform(0, 1, (50, 3)), np.zeros((50, 3), np.uint8),
                                                    CueType.SFM), sh_degree=0)
    save_ply(tmp_path / "start.ply", params, cue_type)
    for budget, warned in ((40, True), (50, True), (51, False), (0, False)):
        caplog.clear()
        cfg = TrainConfig(init_ply=str(tmp_path / "start.ply"), sh_degree=0,
                          strategy=IndoorStrategyConfig(max_gaussians=budget))
        with caplog.at_level(logging.WARNING, logger="splat"):
            assert len(initial_gaussians(cfg, None, tmp_path / "unused.ply")[1]) == 50
        assert ("at or over --strategy.max-gaussians" in caplog.text) == warned, (budget, caplog.text)


def test_cues_of_another_scene_are_named(tmp_path, caplog):
    """Cue points that no view of the scene sees (cues of another scene, another frame) get one warning
    naming both folders; the scene's own cues none."""
    import logging

    from cues_synth import make_room_scene, render
    from geocues.cue_io import write_cues_ply
    from geocues.scene import Scene
    from splat.init_gaussians import load_init_cloud, seen_share
    from splat.train_config import TrainConfig

    scene = Scene.load(make_room_scene(tmp_path / "room", n_views=6, priors="none"))
    rng = np.random.default_rng(0)
    pts = []  # surface points the views see, as extracted cues are
    for cam in scene.cameras:
        depth = render(cam.K, cam.R, cam.t, cam.width, cam.height)[1]
        i, j = rng.integers(0, cam.height, 300), rng.integers(0, cam.width, 300)
        ok = depth[i, j] > 0
        X = cam.rays_at(i[ok], j[ok]) * depth[i[ok], j[ok], None]
        pts.append((X - cam.t) @ cam.R)  # camera to world
    inside = np.concatenate(pts)
    assert seen_share(inside, scene) == 1.0 and seen_share(inside + 50.0, scene) == 0.0
    for name, xyz, warned in (("own", inside, False), ("other", inside + 50.0, True)):
        write_cues_ply(tmp_path / name / "cues.ply", CueCloud.make(xyz, np.zeros((len(xyz), 3), np.uint8), CueType.LINE))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="splat"):
            load_init_cloud(TrainConfig(), scene, tmp_path / name / "cues.ply")
        assert ("extracted from another scene" in caplog.text) == warned, caplog.text
    assert str(tmp_path / "other" / "cues.ply") in caplog.text and str(scene.root) in caplog.text


def test_cues_of_a_rescaled_copy_are_named_by_their_cameras(tmp_path, caplog):
    """Cues extracted from a rescaled copy of the scene (`geocues rescale`) project into its views at
    another scale, so the seen-share test misses them; the camera signature `geocues extract` records
    in the cues' report tells them: one warning naming the factor. The same cameras under another
    folder (`geocues sfm -o`, `mvs`, `undistort`) and an older cue folder without a signature: none."""
    import json
    import logging
    import shutil

    from cues_synth import make_room_scene
    from geocues.camera_signature import camera_signature, signature_mismatch
    from geocues.cue_io import write_cues_ply
    from geocues.rescale import RescaleConfig, run as rescale
    from geocues.scene import Scene
    from splat.init_gaussians import load_init_cloud
    from splat.train_config import TrainConfig

    root = make_room_scene(tmp_path / "room", n_views=6, priors="none")
    big = rescale(RescaleConfig(scale=10.0), root, tmp_path / "room_x10")
    same = tmp_path / "room_copy"
    shutil.copytree(root, same)
    scene, scene_big, scene_same = (Scene.load(p) for p in (root, big, same))
    assert signature_mismatch(camera_signature(scene), camera_signature(scene_same)) is None
    why = signature_mismatch(camera_signature(scene_big), camera_signature(scene))
    assert why is not None and "x0.1" in why

    xyz = scene_big.points.xyz  # the copy's points: 10x the scene's, in front of its views all the same
    for name, signed_by, warned in (("x10", scene_big, True), ("copy", scene_same, False), ("old", None, False)):
        write_cues_ply(tmp_path / name / "cues.ply", CueCloud.make(xyz, np.zeros((len(xyz), 3), np.uint8), CueType.SFM))
        report = {"scene": "somewhere"} | ({"cameras": camera_signature(signed_by)} if signed_by else {})
        (tmp_path / name / "report.json").write_text(json.dumps(report))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="splat"):
            load_init_cloud(TrainConfig(), scene, tmp_path / name / "cues.ply")
        assert ("extracted from another scene" in caplog.text) == warned, (name, caplog.text)
