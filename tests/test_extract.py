"""`geocues extract`: the stage chain, its files, cache, switches and hard cases.

The line stage is replaced by the exact room edges (``fake_line_cues``) so these tests measure the
chain, not line quality (the line stage has its own tests).
"""

from __future__ import annotations

import json
import logging
import time

import numpy as np
import pytest

import geocues.extract as ex
from geocues.cue_io import read_cues_ply, read_lines_npz
from geocues.types import CueType

from cues_synth import ROOM, distance_to_surface, fake_line_cues, make_room_scene
from test_planes import _wall_normals_ok


@pytest.fixture(autouse=True)
def fake_lines(monkeypatch):
    """Exact room edges as line cues; camera indices in ``drop`` see no line."""
    state = {"drop": ()}
    monkeypatch.setattr(ex, "_run_lines", lambda scene, cfg, cache: fake_line_cues(scene.cameras,
                                                                                   drop=state["drop"]))
    return state


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("extract")
    # 16 views, 22.5 degrees apart: every wall point is seen by ~3 views, as the multi-view plane
    # test (min_views = 3) needs
    out = {p: make_room_scene(root / p, n_views=16, priors=p) for p in ("all", "none", "some")}
    out["plain_floor"] = make_room_scene(root / "plain_floor", n_views=16, priors="all", plain_floor=True)
    return out


def _report(out):
    return json.loads((out / "report.json").read_text())


def _no_nan(out):
    cues = read_cues_ply(out / "cues.ply")
    assert np.all(np.isfinite(cues.xyz)) and np.all(np.isfinite(cues.normal))
    assert np.all(np.isfinite(cues.confidence))
    assert "NaN" not in (out / "report.json").read_text()
    return cues


class TestRun:
    def test_outputs_and_accuracy(self, scenes, tmp_path):
        out = ex.run(None, scenes["all"], tmp_path / "cues")
        for f in ("cues.ply", "lines3d.npz", "report.json", "depth_alignments.json", "plane_anchors.npz"):
            assert (out / f).is_file()
        cues = _no_nan(out)
        rep = _report(out)
        assert rep["counts"] == cues.counts() and all(v > 0 for v in rep["counts"].values())
        from geocues.camera_signature import camera_signature
        from geocues.scene import Scene

        assert rep["cameras"] == camera_signature(Scene.load(scenes["all"]))  # what splat train compares
        for stage in ("sfm", "lines", "texture", "depth_align", "planes", "total"):
            assert rep["seconds"][stage] >= 0
        aligned = [r for r in rep["per_image"] if r["alignment"]["ok"]]
        assert len(aligned) >= 12  # a view that sees one fronto-parallel edge has too narrow a depth range
        for r in rep["per_image"]:
            assert r["plane_mode"] == ("prior" if r["alignment"]["ok"] else "prior_free")
            assert r["alignment"]["ok"] or "too narrow" in r["alignment"]["reason"]
        assert all(r["alignment"]["residual_median_m"] < 0.01 for r in aligned)
        from geocues.depth_align import load_alignments

        assert sorted(load_alignments(out)) == sorted(r["name"] for r in aligned)  # train's input file
        assert rep["rejections"]["sfm"]["sor_outlier"] > 0
        plane = cues.of_type(CueType.PLANE)
        assert np.mean(distance_to_surface(plane.xyz) < 0.03) > 0.95
        assert np.all(np.abs(np.linalg.norm(plane.normal, axis=1) - 1) < 1e-4)
        lines = read_lines_npz(out / "lines3d.npz")
        assert len(lines["segments"]) == rep["n_lines"] > 0
        assert np.sum(cues.cue_type == CueType.LINE) == len(lines["points"])

    def test_second_run_is_skipped_and_cache_reused(self, scenes, tmp_path):
        out = tmp_path / "cues"
        ex.run(None, scenes["all"], out)
        first = _report(out)
        assert first["planes"]["texture_cache_hits"] == 0
        stamp = (out / "cues.ply").stat().st_mtime_ns
        ex.run(None, scenes["all"], out)  # same config: nothing redone
        assert (out / "cues.ply").stat().st_mtime_ns == stamp
        cfg = ex.ExtractConfig()
        cfg.plane.voxel_size = 0.03
        with pytest.raises(ValueError, match="overwrite"):
            ex.run(cfg, scenes["all"], out)
        ex.run(cfg, scenes["all"], out, overwrite=True)
        second = _report(out)
        assert second["planes"]["texture_cache_hits"] == 16
        assert second["counts"]["PLANE"] < first["counts"]["PLANE"]  # coarser voxels

    @pytest.mark.parametrize("off", ["sfm", "lines", "planes"])
    def test_each_stage_switches_off(self, scenes, tmp_path, off):
        cfg = ex.ExtractConfig(**{off: False})
        rep = _report(ex.run(cfg, scenes["all"], tmp_path / off))
        name = {"sfm": "SFM", "lines": "LINE", "planes": "PLANE"}[off]
        assert rep["counts"][name] == 0 and off not in rep["seconds"]
        assert sum(rep["counts"].values()) > 0

    def test_surface_fusion_run(self, scenes, tmp_path):
        """--plane.fuse-surfaces end to end: plane cues on the room's faces with their normals, the
        fusion's statistics in the report, no NaN; a plain run of that folder is another config."""
        cfg = ex.ExtractConfig()
        cfg.plane.fuse_surfaces = True
        out = ex.run(cfg, scenes["all"], tmp_path / "fused")
        rep = _report(out)
        stats = rep["planes"]["surface_fusion"]
        assert stats["surfaces_of_several_images"] >= 3 and stats["surfaces"] <= stats["surface_candidates"]
        plane = _no_nan(out).of_type(CueType.PLANE)
        assert len(plane) > 100 and np.mean(distance_to_surface(plane.xyz) < 0.01) > 0.95
        assert _wall_normals_ok(plane.xyz, plane.normal) > 0.9
        assert rep["seconds"]["planes_surfaces"] >= 0
        with pytest.raises(ValueError, match="overwrite"):
            ex.run(None, scenes["all"], out)

    def test_floor_lines_run(self, scenes, tmp_path, caplog):
        """--floor.lines end to end on the room with a plain floor: the floor from the first plane
        pass, wall and box feet kept as plane anchors, plane cues as accurate as before, no NaN; a
        plain run of that folder is another config, and off it leaves the key of folders made
        before the option. On the textured floor (no plane cues there): no floor, a note and a
        warning, the cues of a plain run."""
        cfg = ex.ExtractConfig()
        cfg.floor.lines = True
        out = ex.run(cfg, scenes["plain_floor"], tmp_path / "floor")
        rep = _report(out)
        fl = rep["floor_lines"]
        assert fl["floor"]["normal"][2] > 0.9999 and abs(fl["floor"]["height"]) < 0.005
        assert fl["kept"] > 0 and fl["samples"] > fl["kept"] and rep["seconds"]["floor_lines"] > 0
        assert any(n.startswith("floor lines:") for n in rep["notes"])
        plane = _no_nan(out).of_type(CueType.PLANE)
        assert len(plane) > 100 and np.mean(distance_to_surface(plane.xyz) < 0.03) > 0.95
        with pytest.raises(ValueError, match="overwrite"):
            ex.run(None, scenes["plain_floor"], out)
        assert "floor" not in ex._key_config(ex.ExtractConfig()) and "floor" in ex._key_config(cfg)
        assert "walls" not in ex._key_config(cfg)["floor"]  # --floor.walls off: older folders' key
        cfg.floor.walls = True  # the feet raised: walls and box sides as accurate, no NaN
        rep = _report(out := ex.run(cfg, scenes["plain_floor"], tmp_path / "walls"))
        assert rep["floor_lines"]["walls"]["samples"] > 0 and "wall_step" in ex._key_config(cfg)["floor"]
        assert any("--floor.walls" in n for n in rep["notes"])
        walls = _no_nan(out).of_type(CueType.PLANE)
        assert len(walls) >= len(plane) and np.mean(distance_to_surface(walls.xyz) < 0.03) > 0.95
        assert "wall_check" not in ex._key_config(cfg)["floor"]  # off: the key of --floor.walls folders
        cfg.floor.wall_check = True  # the aligned priors see the walls and box sides: raised, as accurate
        rep = _report(out := ex.run(cfg, scenes["plain_floor"], tmp_path / "checked"))
        check = rep["floor_lines"]["walls"]["check"]
        assert check["unchecked"] < fl["kept"] and check["dropped"] < fl["kept"]
        assert "wall_check" in ex._key_config(cfg)["floor"]
        checked = _no_nan(out).of_type(CueType.PLANE)
        assert len(checked) > len(plane) and np.mean(distance_to_surface(checked.xyz) < 0.03) > 0.95
        assert "ceiling" not in ex._key_config(cfg)["floor"] and "floor_grid" not in ex._key_config(cfg)["floor"]
        cfg.floor.ceiling = cfg.floor.floor_grid = True  # the ceiling: no view looks up, none placed, a note
        rep = _report(ex.run(cfg, scenes["plain_floor"], tmp_path / "no_ceiling"))
        assert "height" not in rep["floor_lines"]["ceiling"] and rep["floor_lines"]["floor_grid"]["samples"] > 0
        assert any("no ceiling placed" in n for n in rep["notes"])
        cfg.floor.ceiling = cfg.floor.floor_grid = False
        cfg.floor.wall_check = False
        cfg.priors = False  # prior-free planes are fitted to cues only, never to the raised rows
        free_walls = _report(ex.run(cfg, scenes["plain_floor"], tmp_path / "free_walls"))
        cfg.floor.walls = False
        free = _report(ex.run(cfg, scenes["plain_floor"], tmp_path / "free"))
        assert free_walls["floor_lines"]["walls"]["samples"] > 0 and free_walls["counts"] == free["counts"]
        cfg.priors = True
        with caplog.at_level(logging.WARNING, logger="geocues"):
            rep = _report(ex.run(cfg, scenes["all"], tmp_path / "textured_floor"))
        assert rep["floor_lines"]["floor"] is None
        assert any("no floor found" in n and "horizontal plane cues" in n for n in rep["notes"])
        assert "--floor.lines: no floor found" in caplog.text and "no floor lines, walls or level planes" in caplog.text
        plain = _report(ex.run(None, scenes["all"], tmp_path / "plain_run"))
        assert rep["counts"] == plain["counts"]

    def test_ceiling_and_floor_grid_run(self, tmp_path):
        """--floor.ceiling --floor.floor-grid end to end on the plain-floor room seen by views that
        alternately look down and up: the ceiling's height from the aligned priors, the walls raised
        up to it, more plane cues on the ceiling and the floor, as accurate, no NaN; off, the key of
        the --floor.wall-check folders."""
        scene = make_room_scene(tmp_path / "up", n_views=24, priors="all", plain_floor=True, pitch=(-0.35, 0.3))
        cfg = ex.ExtractConfig()
        cfg.floor.lines = cfg.floor.walls = cfg.floor.wall_check = True
        checked = _no_nan(ex.run(cfg, scene, tmp_path / "checked")).of_type(CueType.PLANE)
        assert "ceiling" not in ex._key_config(cfg)["floor"] and "floor_grid" not in ex._key_config(cfg)["floor"]
        cfg.floor.ceiling = cfg.floor.floor_grid = True
        rep = _report(out := ex.run(cfg, scene, tmp_path / "ceiling"))
        fl = rep["floor_lines"]
        assert fl["ceiling"]["height"] == pytest.approx(ROOM[2], abs=0.02) and fl["ceiling"]["samples"] > 0
        assert fl["walls"]["top"] == pytest.approx(fl["ceiling"]["height"], abs=1e-3) and fl["floor_grid"]["samples"] > 0
        assert {"ceiling", "floor_grid"} <= set(ex._key_config(cfg)["floor"])
        roof = _no_nan(out).of_type(CueType.PLANE)
        assert len(roof) > len(checked) and np.mean(distance_to_surface(roof.xyz) < 0.03) > 0.95
        assert (roof.xyz[:, 2] > ROOM[2] - 0.03).sum() > (checked.xyz[:, 2] > ROOM[2] - 0.03).sum()
        assert "level_snap" not in ex._key_config(cfg)["floor"]  # off: the key of the folders before it
        cfg.floor.level_snap = True  # weak regions on the ceiling's / floor's level plane cut onto it
        rep = _report(out := ex.run(cfg, scene, tmp_path / "snap"))
        assert rep["rejections"]["planes"]["on_a_level_plane"] > 0 and "level_snap" in ex._key_config(cfg)["floor"]
        snap = _no_nan(out).of_type(CueType.PLANE)
        on = lambda c, z: np.abs(c.xyz[:, 2] - z) < 0.03  # noqa: E731
        assert on(snap, ROOM[2]).sum() > 1.5 * on(roof, ROOM[2]).sum() and on(snap, 0.0).sum() > on(roof, 0.0).sum()  # 2x, 3x
        assert np.mean(distance_to_surface(snap.xyz) < 0.03) > 0.95
        assert "wall_snap" not in ex._key_config(cfg)["floor"]
        cfg.floor.wall_snap = True  # what the anchored planes leave of the walls, cut onto the walls' planes
        rep = _report(out := ex.run(cfg, scene, tmp_path / "walls"))
        planes = rep["floor_lines"]["walls"]["snap_planes"]
        assert planes["confirmed_by_cues"] >= 1 and "wall_snap" in ex._key_config(cfg)["floor"]
        assert rep["rejections"]["planes"].get("on_a_wall_plane", 0) > 0
        walls = _no_nan(out).of_type(CueType.PLANE)
        on_walls = lambda c: (np.abs(c.xyz[:, 1] - ROOM[1]) < 0.03) | (np.abs(c.xyz[:, 1]) < 0.03)  # noqa: E731
        assert on_walls(walls).sum() > 1.05 * on_walls(snap).sum()  # 35.8k against 32.9k points
        assert np.mean(distance_to_surface(walls.xyz) < 0.03) > 0.95

    def test_prior_free_run_of_a_scene_with_priors(self, scenes, tmp_path):
        out = ex.run(ex.ExtractConfig(priors=False), scenes["all"], tmp_path / "free")
        rep = _report(out)
        assert rep["planes"]["plane_modes"]["prior_free"] == 16
        assert any("priors ignored" in n for n in rep["notes"])
        plane = _no_nan(out).of_type(CueType.PLANE)
        assert len(plane) > 100 and np.mean(distance_to_surface(plane.xyz) < 0.03) > 0.9

    def test_bad_paths(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="missing"):
            ex.run(None, tmp_path / "missing", tmp_path / "out")


def test_triangulation_angles():
    """Largest ray angle per SfM point from its track; inf when fewer than two cameras see it."""
    from types import SimpleNamespace

    from geocues.scene import Points3D

    cams = [SimpleNamespace(center=np.array(c, float)) for c in ([0, 0, 0], [1, 0, 0], [0.1, 0, 0])]
    pts = Points3D(np.arange(2), np.array([[0.5, 0, 0.5], [0, 0, 10.0]]), np.zeros((2, 3), np.uint8),
                   np.zeros(2), np.zeros(2, np.int32), {0: np.array([0, 1]), 1: np.array([0])})
    scene = SimpleNamespace(points=pts, cameras=cams)
    ang = ex.triangulation_angles(scene, np.array([0, 1]))
    assert ang[0] == pytest.approx(90.0) and np.isinf(ang[1])
    pts.visible_in[2] = np.array([1])  # camera 2, 10 cm beside camera 0, also sees point 1
    assert ex.triangulation_angles(scene, np.array([1]))[0] == pytest.approx(np.degrees(np.arctan2(0.1, 10.0)))


class TestHardCases:
    def test_empty_sfm_model(self, tmp_path):
        scene = make_room_scene(tmp_path / "room", n_views=16, priors="all", n_sfm=0)
        out = ex.run(None, scene, tmp_path / "cues")
        cues, rep = _no_nan(out), _report(out)
        assert rep["counts"]["SFM"] == 0 and rep["counts"]["PLANE"] > 0 and len(cues) == rep["n_points"]
        assert any("no 3D points" in n for n in rep["notes"])

    def test_no_priors_at_all(self, scenes, tmp_path):
        out = ex.run(None, scenes["none"], tmp_path / "cues")
        rep = _report(out)
        _no_nan(out)
        assert rep["planes"]["images_with_prior"] == 0
        assert any("no depth priors" in n for n in rep["notes"])
        assert rep["counts"]["PLANE"] > 0

    def test_priors_for_some_images(self, scenes, tmp_path):
        out = ex.run(None, scenes["some"], tmp_path / "cues")
        rep = _report(out)
        _no_nan(out)
        for r in rep["per_image"]:
            if r["index"] % 2:
                assert r["plane_mode"] == "prior_free" and "alignment" not in r
            else:
                assert r["plane_mode"] == ("prior" if r["alignment"]["ok"] else "prior_free")
        assert any("depth priors for 8 of 16 images" in n for n in rep["notes"])

    def test_images_with_no_lines(self, scenes, tmp_path, fake_lines):
        fake_lines["drop"] = (1, 3)
        out = ex.run(None, scenes["all"], tmp_path / "cues")
        rep = _report(out)
        _no_nan(out)
        assert any("2 of 16 images support no 3D line" in n for n in rep["notes"])

    def test_no_lines_no_sfm_no_priors(self, scenes, tmp_path):
        """Nothing to anchor planes: every region is rejected with a reason, no crash."""
        out = ex.run(ex.ExtractConfig(sfm=False, lines=False), scenes["none"], tmp_path / "cues")
        rep = _report(out)
        assert rep["counts"] == {"SFM": 0, "LINE": 0, "PLANE": 0}
        assert rep["rejections"]["planes"].get("too_few_anchors", 0) > 0


class TestCli:
    def test_extract_command(self, scenes, tmp_path, capsys):
        from cli.geocues_cli import main

        t0 = time.perf_counter()
        rc = main(["extract", str(scenes["all"]), "-o", str(tmp_path / "cues"), "--no-sfm",
                   "--plane.voxel-size", "0.04"])
        assert rc == 0 and time.perf_counter() - t0 < 60
        rep = _report(tmp_path / "cues")
        assert rep["counts"]["SFM"] == 0 and rep["config"]["plane"]["voxel_size"] == 0.04
        assert '"counts"' in capsys.readouterr().out

    def test_bad_scene_is_one_line(self, tmp_path, capsys):
        from cli.geocues_cli import main

        assert main(["extract", str(tmp_path / "nope"), "-o", str(tmp_path / "o")]) == 1
        assert "nope" in capsys.readouterr().err

    def test_room_preset_and_later_options_win(self, tmp_path, monkeypatch, capsys):
        """`--preset room` is the measured room recipe (docs/training.md); options after it win; a
        wrong name is one line naming the choices."""
        from cli.geocues_cli import main
        from geocues.presets import extract_preset_config

        seen = []

        def fake_run(cfg, scene, out, overwrite=False):
            seen.append(cfg)
            out.mkdir()
            (out / "report.json").write_text(json.dumps({"counts": {}, "seconds": {}, "notes": []}))
            return out

        monkeypatch.setattr(ex, "run", fake_run)
        assert main(["extract", "S", "-o", str(tmp_path / "c"), "--preset", "room", "--floor.no-ceiling"]) == 0
        f = seen[0].floor
        assert f.lines and f.walls and f.wall_check and f.wall_front_gap == 0.3 and f.floor_grid and f.level_snap
        assert f.wall_snap
        assert not f.ceiling  # given after the preset
        assert extract_preset_config("room").floor.ceiling
        assert extract_preset_config("paper") == ex.ExtractConfig()  # the default is the paper's cues
        mvs = extract_preset_config("mvs")  # the photos-only recipe measured on ICL (docs/training.md)
        assert mvs.plane.fill_holes and not mvs.floor.lines  # floor lines cost held-out PSNR there
        assert main(["extract", "S", "-o", str(tmp_path / "c"), "--preset", "rooms"]) == 1
        assert "unknown preset 'rooms'; choose from paper, room, mvs" in capsys.readouterr().err
