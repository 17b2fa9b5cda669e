"""`splat train` end to end on the tiny synthetic room: init from typed cues, train, evaluate, mesh.

The cues are exact (surface samples with their normals as PLANE, room edges as LINE, the scene's
noisy SfM points as SFM), so the test measures the trainer, not the cue stage.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from cues_synth import ROOM, distance_to_surface, make_room_scene, room_edges, room_mesh
from geocues.cue_io import CueCloud, write_cues_ply
from geocues.scene import Scene
from geocues.types import CueType
from splat.gaussians import load_ply


def surface_cues(root, n_plane: int = 3000, seed: int = 0) -> CueCloud:
    rng = np.random.default_rng(seed)
    V, T, _ = room_mesh()
    tri = V[T]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    face = rng.choice(len(T), n_plane, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n_plane)), rng.random(n_plane)
    w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)
    plane = (w[:, :, None] * tri[face]).sum(1)
    segs = room_edges()
    line = np.concatenate([a + np.linspace(0, 1, 40)[:, None] * (b - a) for a, b in segs])
    sfm = Scene.load(root).points.xyz
    return CueCloud.concat([
        CueCloud.make(plane, np.full((n_plane, 3), 0.7), CueType.PLANE, normal=nrm[face] / (2 * area[face, None])),
        CueCloud.make(line, np.full((len(line), 3), 0.5), CueType.LINE),
        CueCloud.make(sfm, np.full((len(sfm), 3), 0.5), CueType.SFM),
    ])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from splat.mesh import TSDFConfig
    from splat.strategy import IndoorStrategyConfig
    from splat.train import TrainConfig, run

    base = tmp_path_factory.mktemp("train")
    root = make_room_scene(base / "room", n_views=16, w=80, h=60, priors="all")
    cloud = surface_cues(root)
    write_cues_ply(base / "cues" / "cues.ply", cloud)
    cfg = TrainConfig(iters=200, checkpoints=(0.1, 1.0), log_every=10, sh_degree=1,
                      strategy=IndoorStrategyConfig(max_gaussians=20_000), tsdf=TSDFConfig(voxel_size=0.05))
    out = run(cfg, root, base / "cues", base / "out")
    return out, cloud


def test_train_writes_every_output(trained):
    out, cloud = trained
    for name in ("point_cloud.ply", "mesh.ply", "report.json", "train_log.jsonl"):
        assert (out / name).is_file(), name
    assert len(list((out / "test_renders").glob("*.png"))) == 2  # 16 views, every 8th is a test view
    report = json.loads((out / "report.json").read_text())
    assert report["gaussians_init"] == cloud.counts()
    params, cue_type = load_ply(out / "point_cloud.ply")
    assert len(cue_type) == sum(report["gaussians_final"].values()) == len(params["means"])
    assert np.isfinite(params["means"].numpy()).all()
    # G_S (plane) Gaussians are never cloned or split: only pruning changes their number
    assert report["gaussians_final"]["PLANE"] <= report["gaussians_init"]["PLANE"]
    assert len(cue_type) <= 20_000 == report["gaussian_budget"]  # the budget holds and is recorded
    assert set(report["timings"]) >= {"load_and_init_s", "train_s", "mesh_s", "total_s"}
    import torch

    from splat.composite import describe_backend

    assert report["rasterizer"] == describe_backend("auto", torch.device(report["device"]))  # which kernels ran
    # the 3DGS layout holds the same model (SIBR / other tools read it) in files of its own: a hard link
    # made an edit in place of RUN/point_cloud.ply change what SIBR loads too (interop audit)
    iters = report["config"]["iters"]
    other = out / "point_cloud" / f"iteration_{iters}" / "point_cloud.ply"
    assert other.read_bytes() == (out / "point_cloud.ply").read_bytes()
    assert (out / "cue_type.npy").read_bytes() == (other.parent / "cue_type.npy").read_bytes()
    for name in ("point_cloud.ply", "cue_type.npy"):
        assert not (out / name).samefile(other.parent / name) and (out / name).stat().st_nlink == 1


def test_training_reduces_the_loss_and_improves_test_views(trained):
    out, _ = trained
    rows = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in rows]
    assert all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:3])
    curve = json.loads((out / "report.json").read_text())["accuracy_vs_time"]
    assert [c["step"] for c in curve] == [20, 200]
    assert curve[1]["psnr"] > curve[0]["psnr"] + 1.0
    assert curve[1]["train_s"] > curve[0]["train_s"] > 0


def test_mesh_lies_on_the_room_surface(trained):
    import open3d as o3d

    out, _ = trained
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    v = np.asarray(mesh.vertices)
    assert len(v) > 500
    d = distance_to_surface(v)
    # 200 iterations at 80x60, 5 cm voxels: half the vertices within a voxel, 90% within two
    assert np.median(d) < 0.05 and np.mean(d < 0.1) > 0.9



def test_splat_mesh_refuses_again_without_training(trained, tmp_path, capsys):
    """`splat mesh RUN` with the run's TSDF settings rebuilds RUN/mesh.ply exactly; the expected
    depth and other thresholds give another mesh on the same surface; errors are one line."""
    import open3d as o3d

    from cli.splat_cli import main

    out, _ = trained
    same = tmp_path / "same.ply"
    assert main(["mesh", str(out), "-o", str(same), "--tsdf.voxel-size", "0.05"]) == 0
    a, b = (o3d.io.read_triangle_mesh(str(p)) for p in (out / "mesh.ply", same))

    def faces(m):  # triangles as sorted vertex-coordinate triples (the block order of Open3D varies)
        t = np.round(np.asarray(m.vertices)[np.asarray(m.triangles)], 5).reshape(-1, 9)
        return t[np.lexsort(t.T[::-1])]
    assert len(a.triangles) == len(b.triangles) and np.allclose(faces(a), faces(b), atol=1e-5)
    assert main(["mesh", str(out), "--tsdf.voxel-size", "0.05", "--tsdf.depth", "expected",
                 "--tsdf.weight-threshold", "1"]) == 0
    exp = out / "mesh_expected_w1_v0.05.ply"  # named by the options that differ from the default
    v = np.asarray(o3d.io.read_triangle_mesh(str(exp)).vertices)
    assert len(v) > 500 and not np.array_equal(v, np.asarray(a.vertices))
    d = distance_to_surface(v)
    assert np.median(d) < 0.05 and np.mean(d < 0.1) > 0.9
    capsys.readouterr()
    assert main(["mesh", str(out), "--tsdf.voxel-size", "0.05", "--tsdf.depth", "expected",
                 "--tsdf.weight-threshold", "1"]) == 1
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(["mesh", str(out), "--tsdf.depth", "mean"]) == 1
    assert "depth must be 'median' or 'expected'" in capsys.readouterr().err
    assert main(["mesh", str(tmp_path), "-o", str(tmp_path / "x.ply")]) == 1
    assert "report.json" in capsys.readouterr().err

def test_bad_inputs_name_the_problem(tmp_path):
    from splat.train import TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=4, w=40, h=30, priors="none", n_sfm=20)
    with pytest.raises(FileNotFoundError, match="geocues extract"):
        run(TrainConfig(iters=2), root, tmp_path / "nocues", tmp_path / "out")
    write_cues_ply(tmp_path / "cues.ply", surface_cues(root, n_plane=50))
    with pytest.raises(ValueError, match="unknown cue types"):
        run(TrainConfig(iters=2, cue_types=("WALL",)), root, tmp_path / "cues.ply", tmp_path / "out")


def test_a_scene_that_is_not_metric_is_named_by_the_training(tmp_path, caplog):
    """The TSDF's depth_max and voxels and the hole seeds are in metres: a model mapped from images
    alone (scene.json "scale": "arbitrary") gets the warning that names `geocues rescale`."""
    import logging

    from splat.train import TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=4, w=40, h=30, priors="none", n_sfm=20)
    write_cues_ply(tmp_path / "cues.ply", surface_cues(root, n_plane=50))
    with caplog.at_level(logging.WARNING):
        run(TrainConfig(iters=2, mesh=False), root, tmp_path / "cues.ply", tmp_path / "a")
    assert "geocues rescale" not in caplog.text
    (root / "scene.json").write_text(json.dumps({"scale": "arbitrary"}))
    with caplog.at_level(logging.WARNING):
        run(TrainConfig(iters=2, mesh=False), root, tmp_path / "cues.ply", tmp_path / "b")
    assert "mapped from images alone" in caplog.text and f"geocues rescale {root}" in caplog.text


def test_evaluate_cli_reports_mesh_and_held_out_views(trained, tmp_path, capsys):
    """`evaluate MESH SCENE --renders OUT/test_renders` gives the trainer's test PSNR (PNG-rounded)."""
    from cli.evaluate_cli import main

    import open3d as o3d

    out, _ = trained
    scene = out.parent / "room"
    V, T, _ = room_mesh()
    gt = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
    o3d.io.write_triangle_mesh(str(tmp_path / "gt.ply"), gt)
    assert main([str(out / "mesh.ply"), str(scene), "--gt", str(tmp_path / "gt.ply"),
                 "--renders", str(out / "test_renders"),
                 "--json", str(tmp_path / "m.json"), "--n-samples", "20000"]) == 0
    data = json.loads((tmp_path / "m.json").read_text())
    report = json.loads((out / "report.json").read_text())
    assert data["images"]["n_images"] == 2
    assert abs(data["images"]["psnr"] - report["test_metrics"]["psnr"]) < 0.1
    assert 0 < data["f_score"] <= 1 and "held-out views: 2" in capsys.readouterr().out
    with pytest.raises(ValueError, match="not test views"):
        from evaluation.image_metrics import evaluate_renders
        evaluate_renders(out / "test_renders", scene, test_every=5)


def test_anchored_depth_pulls_an_offset_surface_back(tmp_path):
    """Cues 8 cm inside the room: photometrically that is almost as good as the true surface and
    L_d (patch PCC) cannot see it. With the cue report's alignment of the priors (here exact:
    prior = 0.5 z + 0.3) L_a pulls the Gaussians back; without it they stay off the surface."""
    from splat.losses import LossConfig
    from splat.train import LearningRates, TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=12, w=64, h=48, priors="all")
    cloud = surface_cues(root, n_plane=2000)
    centre = np.asarray(ROOM, float) / 2
    inward = (centre - cloud.xyz) / np.linalg.norm(centre - cloud.xyz, axis=1, keepdims=True)
    cloud.xyz = cloud.xyz + 0.08 * inward
    cues = tmp_path / "cues"
    write_cues_ply(cues / "cues.ply", cloud)
    scene = Scene.load(root)
    rows = [{"index": c.index, "name": c.name,
             "alignment": {"index": c.index, "ok": True, "scale": 2.0, "shift": -0.6, "width": c.width,
                           "height": c.height, "residual_p90_m": 0.005}} for c in scene.cameras]
    (cues / "report.json").write_text(json.dumps({"per_image": rows}))

    def surface_distance(lambda_anchor: float) -> float:
        cfg = TrainConfig(iters=300, checkpoints=(1.0,), sh_degree=0, mesh=False, test_every=0,
                          lr=LearningRates(means=1.6e-3, means_final=1.6e-4),  # both runs: room to move
                          loss=LossConfig(lambda_anchor=lambda_anchor))
        out = run(cfg, root, cues, tmp_path / f"out_{lambda_anchor}")
        params, cue_type = load_ply(out / "point_cloud.ply")
        keep = (cue_type == CueType.PLANE.value).numpy()
        w = 1.0 / (1.0 + np.exp(-params["opacities"].numpy()[keep]))
        return float(np.average(distance_to_surface(params["means"].numpy()[keep]), weights=w))

    without, with_anchor = surface_distance(0.0), surface_distance(5.0)
    msg = f"PLANE Gaussians to the surface: {without:.4f} m without L_a, {with_anchor:.4f} m with"
    assert without > 0.06, msg  # the offset survives training without L_a (measured 0.073)
    assert with_anchor < 0.5 * without, msg  # measured 0.027


def test_init_ply_continues_from_a_runs_gaussians(trained, tmp_path):
    """`--init-ply`: start from a PLY's Gaussians (types from its sidecar; none: all SFM)."""
    import shutil
    from dataclasses import replace

    from splat.train import TrainConfig, run

    out, _ = trained
    report = json.loads((out / "report.json").read_text())
    params, cue_type = load_ply(out / "point_cloud.ply")
    cfg = TrainConfig(iters=10, checkpoints=(1.0,), log_every=5, sh_degree=1, mesh=False,
                      init_ply=str(out / "point_cloud.ply"))
    again = json.loads((run(cfg, report["scene"], report["cues"], tmp_path / "again") / "report.json").read_text())
    assert again["gaussians_init"] == report["gaussians_final"]
    # 10 more iterations from a trained model keep its quality; a fresh init after 10 is far worse
    assert again["test_metrics"]["psnr"] > report["test_metrics"]["psnr"] - 1.0
    fresh = json.loads((run(replace(cfg, init_ply=None), report["scene"], report["cues"], tmp_path / "fresh")
                        / "report.json").read_text())
    assert fresh["test_metrics"]["psnr"] < again["test_metrics"]["psnr"] - 2.0, (fresh["test_metrics"], again["test_metrics"])
    bare = tmp_path / "bare.ply"  # a PLY from another tool: no cue_type sidecar
    shutil.copy(out / "point_cloud.ply", bare)
    cfg = TrainConfig(iters=2, checkpoints=(1.0,), sh_degree=1, mesh=False, init_ply=str(bare))
    typed = json.loads((run(cfg, report["scene"], report["cues"], tmp_path / "bare") / "report.json").read_text())
    assert typed["gaussians_init"] == {"SFM": len(params["means"]), "LINE": 0, "PLANE": 0}
    with pytest.raises(FileNotFoundError, match="no Gaussian PLY"):
        run(TrainConfig(iters=2, init_ply=str(tmp_path / "missing.ply")), report["scene"], report["cues"],
            tmp_path / "missing")


def test_live_view_serves_and_refreshes_during_training(trained, tmp_path, monkeypatch):
    """`splat train --view`: a viser page during the run, refreshed every --view-every iterations,
    stopped when the run ends."""
    import urllib.request

    import splat.viewer as viewer
    from splat.train import TrainConfig, run

    out, _ = trained
    report = json.loads((out / "report.json").read_text())
    seen = []
    real = viewer.LiveView.update

    def update(self, params, step, loss):
        real(self, params, step, loss)
        with urllib.request.urlopen(viewer.url_of(self.server), timeout=30) as r:
            seen.append((step, r.status, self.status.content))

    monkeypatch.setattr(viewer.LiveView, "update", update)
    stopped = []
    monkeypatch.setattr(viewer.LiveView, "close", lambda self: stopped.append(1) or viewer.stop(self.server))
    cfg = TrainConfig(iters=10, checkpoints=(1.0,), sh_degree=1, mesh=False, view=True, view_port=0, view_every=5)
    run(cfg, report["scene"], report["cues"], tmp_path / "live")
    assert [(s, code) for s, code, _ in seen] == [(5, 200), (10, 200)]
    assert seen[-1][2].startswith("step 10 · loss") and "Gaussians" in seen[-1][2]
    assert stopped == [1]


def test_multiview_consistency_pulls_an_offset_textured_floor_back(tmp_path, caplog):
    """Cues 8 cm inside the room and no priors at all: nothing but the photos can tell where the
    surface is. L_mv (the rendered plane warps patches into a neighbouring photo) pulls the Gaussians
    of the textured floor back towards it; without it they stay off the surface."""
    from splat.losses import LossConfig
    from splat.train import LearningRates, TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=12, w=128, h=96, priors="none")
    cloud = surface_cues(root, n_plane=2000)
    centre = np.asarray(ROOM, float) / 2
    inward = (centre - cloud.xyz) / np.linalg.norm(centre - cloud.xyz, axis=1, keepdims=True)
    on_floor = cloud.xyz[:, 2] < 1e-3
    cloud.xyz = cloud.xyz + 0.08 * inward
    cues = tmp_path / "cues"
    write_cues_ply(cues / "cues.ply", cloud)

    def floor_distance(lambda_mv: float) -> float:
        cfg = TrainConfig(iters=300, checkpoints=(1.0,), sh_degree=0, mesh=False, test_every=0,
                          lr=LearningRates(means=1.6e-3, means_final=1.6e-4),  # both runs: room to move
                          loss=LossConfig(lambda_mv=lambda_mv, mv_from_iter=0))
        out = run(cfg, root, cues, tmp_path / f"out_{lambda_mv}")
        params, cue_type = load_ply(out / "point_cloud.ply")
        means = params["means"].numpy()
        keep = (cue_type == CueType.PLANE.value).numpy() & (means[:, 2] < 0.3)  # the floor's Gaussians
        w = 1.0 / (1.0 + np.exp(-params["opacities"].numpy()[keep]))
        return float(np.average(distance_to_surface(means[keep]), weights=w))

    assert on_floor.sum() > 100
    without, with_mv = floor_distance(0.0), floor_distance(0.5)
    hints = [r for r in caplog.records if "has no depth priors" in r.getMessage()]
    assert len(hints) == 1 and "--preset mvs" in hints[0].getMessage()  # photos only: the way to priors, once
    msg = f"floor Gaussians to the surface: {without:.4f} m without L_mv, {with_mv:.4f} m with"
    assert without > 0.04, msg  # measured 0.049 (0.047 after 600 iterations)
    assert with_mv < 0.8 * without, msg  # measured 0.035 (λ_mv = 2: 0.034)


@pytest.mark.parametrize("kept", [(), ("mv",)])
def test_priors_until_stops_the_prior_terms(tmp_path, kept):
    """--priors-until 0.5: L_d and L_mv are in the loss of the first half's steps, no prior term (L_d,
    L_a, L_n, L_mv) but those of --priors-kept is in any step of the second half, and L_rgb, L_s and
    L_nc go on."""
    from splat.losses import LossConfig
    from splat.train import TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=12, w=64, h=48, priors="all")
    cues = tmp_path / "cues"
    write_cues_ply(cues / "cues.ply", surface_cues(root, n_plane=800))
    cfg = TrainConfig(iters=40, checkpoints=(1.0,), sh_degree=0, mesh=False, test_every=0, log_every=1,
                      priors_until=0.5, priors_kept=kept, loss=LossConfig(lambda_mv=0.1, mv_from_iter=0, nc_from_iter=0))
    out = run(cfg, root, cues, tmp_path / "out")
    rows = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    rows = [r for r in rows if "loss" in r]
    early, late = [r for r in rows if r["step"] < 20], [r for r in rows if r["step"] >= 20]
    assert len(early) == 20 and len(late) == 20
    assert all({"depth", "mv", "nc", "flat"} <= set(r) for r in early)
    assert not any(({"depth", "normal", "anchor", "mv"} - set(kept)) & set(r) for r in late)
    assert all({"rgb", "nc", "flat", *kept} <= set(r) for r in late)
