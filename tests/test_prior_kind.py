"""Depth priors as monocular estimators write them: ``--prior-kind disparity`` (issue 14, point 5).

Depth-Anything and MiDaS write disparity (inverse depth up to scale and shift). Before the option,
such a prior failed every image's depth alignment ("degenerate fit") and the extract silently fell
back to prior-free planes. These tests cover: a disparity prior fitted as 1/z = s·p + b gives the
same aligned depth as its depth form; a disparity prior taken for depth is named in one warning;
the option parses; the alignment's kind travels through report.json.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

import geocues.extract as ex
from geocues.depth_align import DepthAlignConfig, DepthAlignment, align_depth_prior, fit_scale_shift, load_alignments
from geocues.scene import Scene

from cues_synth import fake_line_cues, make_room_scene, render

# p = A / z + B (disparity) and q = 0.5 z + 0.3 (depth): exact forms of the same surface
A, B = 2.0, 0.1


def _disparity(z: np.ndarray) -> np.ndarray:
    return np.where(z > 0, A / np.where(z > 0, z, 1.0) + B, 0.0).astype(np.float32)


def _depth_form(z: np.ndarray) -> np.ndarray:
    return np.where(z > 0, 0.5 * z + 0.3, 0.0).astype(np.float32)


def _write_priors(root, depths, form, depth_kind=None):
    (root / "priors" / "depth").mkdir(parents=True, exist_ok=True)
    for k, z in enumerate(depths):
        np.save(root / "priors" / "depth" / f"{k:05d}.npy", form(z))
    meta = {"priors": {"depth": "exact, for tests"}}
    if depth_kind is not None:
        meta["priors"]["depth_kind"] = depth_kind
    (root / "scene.json").write_text(json.dumps(meta))


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """Synthetic room (6 views) with disparity priors made from the exact depth; scene.json says so."""
    root = make_room_scene(tmp_path_factory.mktemp("kind") / "room", n_views=6, priors="none", n_sfm=300,
                           n_outliers=0)
    scene = Scene.load(root)
    depths = [render(c.K, c.R, c.t, c.width, c.height)[1] for c in scene.cameras]
    _write_priors(root, depths, _disparity, depth_kind="disparity")
    return Scene.load(root), depths


def _anchors(scene, depths, i, n=400, noise=0.0, hidden=0.0, seed=0):
    """World points on the surface seen by camera i; ``noise`` m of depth noise, a share ``hidden``
    of them pushed behind the surface (seen by another view, occluded in this one)."""
    cam = scene.cameras[i]
    rng = np.random.default_rng(seed)
    r, c = np.nonzero(depths[i] > 0)
    k = rng.choice(len(r), n, replace=False)
    z = depths[i][r[k], c[k]] + rng.normal(0.0, noise, n) if noise else depths[i][r[k], c[k]].astype(np.float64)
    z[: int(hidden * n)] += rng.uniform(0.3, 1.0, int(hidden * n))
    return (cam.pixel_rays()[r[k], c[k]] * z[:, None] - cam.t) @ cam.R


class TestDisparityFit:
    def test_exact_disparity_is_recovered(self):
        rng = np.random.default_rng(0)
        z = rng.uniform(1.0, 5.0, 300)
        s, b, used = fit_scale_shift(A / z + B, z, DepthAlignConfig(), rng, kind="disparity")
        assert s == pytest.approx(1 / A, rel=1e-6) and b == pytest.approx(-B / A, abs=1e-6) and used.all()

    def test_unknown_kind_is_named(self, room):
        scene, depths = room
        with pytest.raises(ValueError, match="unknown prior kind 'inverse'"):
            align_depth_prior(scene.cameras[0], _disparity(depths[0]), np.zeros((0, 3)), DepthAlignConfig(),
                              kind="inverse")

    @pytest.mark.parametrize("noise, hidden, tol", [(0.0, 0.0, 1e-3), (0.002, 0.2, 5e-3)])
    def test_same_aligned_depth_as_the_depth_form(self, room, noise, hidden, tol):
        """Tolerance: 1 mm with exact anchors; 5 mm with 2 mm anchor noise and 20 % of the anchors
        hidden behind the surface (both fits are robust, with residuals in metres)."""
        scene, depths = room
        assert scene.depth_kind == "disparity"
        for i, cam in enumerate(scene.cameras):
            X = _anchors(scene, depths, i, noise=noise, hidden=hidden, seed=i)
            prior = scene.depth_prior(i)  # the disparity map as stored
            disp = align_depth_prior(cam, prior, X, DepthAlignConfig(), kind="disparity")
            dep = align_depth_prior(cam, _depth_form(depths[i]), X, DepthAlignConfig())
            assert disp.ok and dep.ok, (disp.reason, dep.reason)
            assert disp.kind == "disparity" and dep.kind == "depth" and not disp.looks_like and not dep.looks_like
            m = depths[i] > 0
            a, b = disp.apply(prior)[m], dep.apply(_depth_form(depths[i]))[m]
            assert np.all(a > 0)
            assert np.max(np.abs(a - b)) < tol, (i, np.max(np.abs(a - b)))
            assert np.median(np.abs(a - depths[i][m])) < tol / 2

    def test_kind_travels_through_the_report(self, room, tmp_path):
        scene, depths = room
        cam = scene.cameras[1]
        prior = scene.depth_prior(1)
        al = align_depth_prior(cam, prior, _anchors(scene, depths, 1), DepthAlignConfig(warp_degree=1),
                               kind="disparity")
        assert al.ok
        rows = [{"name": cam.name, "alignment": al.to_dict()}]
        (tmp_path / "report.json").write_text(json.dumps({"per_image": rows}))
        back = load_alignments(tmp_path)[cam.name]
        assert back.kind == "disparity" and np.array_equal(back.apply(prior), al.apply(prior))
        half = prior[::2, ::2]  # a downscaled training run applies it to the resized prior
        assert np.abs(back.apply(half) - al.apply(prior)[::2, ::2]).max() < 0.02
        old = {k: v for k, v in al.to_dict().items() if k != "kind"}  # a report from before the kind
        assert DepthAlignment.from_dict(old).kind == "depth"
        with pytest.raises(ValueError, match="unknown prior kind 'inverse'"):
            DepthAlignment.from_dict({**al.to_dict(), "kind": "inverse"})


class TestSceneJson:
    def test_depth_kind(self, room):
        scene = Scene.load(room[0].root)  # its own copy: the metadata is changed below
        assert scene.depth_kind == "disparity"
        scene.metadata = {"priors": {"depth_kind": "inverse"}}
        with pytest.raises(ValueError, match=r"scene\.json: priors\.depth_kind must be 'depth' or 'disparity'"):
            _ = scene.depth_kind
        scene.metadata = {}
        assert scene.depth_kind == "depth"


@pytest.fixture()
def fake_lines(monkeypatch):
    monkeypatch.setattr(ex, "_run_lines", lambda scene, cfg, cache: fake_line_cues(scene.cameras))


class TestExtract:
    def test_disparity_taken_for_depth_is_named(self, room, tmp_path, fake_lines, caplog):
        """The bug: every image's fit failed and the extract fell back to prior-free planes silently."""
        scene, _ = room
        cfg = ex.ExtractConfig(prior_kind="depth")
        with caplog.at_level(logging.WARNING, logger="geocues"):
            out = ex.run(cfg, scene.root, tmp_path / "as_depth")
        rep = json.loads((out / "report.json").read_text())
        warnings = [r.getMessage() for r in caplog.records if "look like disparity" in r.getMessage()]
        assert len(warnings) == 1, [r.getMessage() for r in caplog.records]
        assert "--prior-kind disparity" in warnings[0] and '"depth_kind": "disparity"' in warnings[0]
        assert "overrides priors.depth_kind" in caplog.text  # the option beat scene.json, and said so
        assert warnings[0] in rep["notes"] and rep["prior_kind"] == "depth"
        als = [r["alignment"] for r in rep["per_image"] if "alignment" in r]
        assert als and all(a["looks_like"] == "disparity" and a["kind"] == "depth" for a in als)

    def test_disparity_prior_is_used(self, room, tmp_path, fake_lines, caplog):
        scene, _ = room
        with caplog.at_level(logging.WARNING, logger="geocues"):
            out = ex.run(None, scene.root, tmp_path / "as_disparity")  # kind from scene.json
        rep = json.loads((out / "report.json").read_text())
        assert "look like" not in caplog.text and rep["prior_kind"] == "disparity"
        als = [r["alignment"] for r in rep["per_image"]]
        assert all(a["ok"] and a["kind"] == "disparity" and a["residual_median_m"] < 0.01 for a in als)
        modes = rep["planes"]["plane_modes"]
        assert modes["prior_free"] == 0 and modes["prior"] > 0, modes

    def test_cues_of_another_prior_kind_than_the_scene_says_now_are_refused(self, room, tmp_path, fake_lines):
        """Extracted while scene.json said nothing (depth), trained after it declared disparity: the
        cues' alignments fit the other model and trained in silence (C-L1 21.0 against 17.7 cm)."""
        import shutil

        from splat.train_config import TrainConfig
        from splat.train_setup import cue_report_priors

        scene, _ = room
        as_scene = ex.run(None, scene.root, tmp_path / "from_scene")  # disparity, from scene.json
        chosen = ex.run(ex.ExtractConfig(prior_kind="disparity"), scene.root, tmp_path / "chosen")
        copy = tmp_path / "room_now_depth"
        shutil.copytree(scene.root, copy)
        (copy / "scene.json").write_text(json.dumps({"priors": {"depth": "exact, for tests"}}))  # kind: depth
        now = Scene.load(copy)
        with pytest.raises(ValueError, match="extracted with the depth priors read as disparity, but .* now says "
                                             "depth .* run `geocues extract"):
            cue_report_priors(TrainConfig(), now, as_scene / "cues.ply")
        assert cue_report_priors(TrainConfig(), now, chosen / "cues.ply")[1] == "disparity"  # chosen with --prior-kind
        assert cue_report_priors(TrainConfig(), scene, as_scene / "cues.ply")[1] == "disparity"

    def test_cli_option_parses(self, room, tmp_path, monkeypatch, capsys):
        from cli.geocues_cli import main

        seen = {}

        def fake_run(cfg, scene, out, *, overwrite=False):
            seen["cfg"] = cfg
            out.mkdir(parents=True, exist_ok=True)
            (out / "report.json").write_text(json.dumps({"counts": {}, "seconds": {}, "notes": []}))
            return out

        monkeypatch.setattr(ex, "run", fake_run)
        assert main(["extract", str(room[0].root), "-o", str(tmp_path / "c"), "--prior-kind", "disparity"]) == 0
        assert seen["cfg"].prior_kind == "disparity"
        assert main(["extract", str(room[0].root), "-o", str(tmp_path / "c")]) == 0
        assert seen["cfg"].prior_kind == "scene"
        with pytest.raises(SystemExit):
            main(["extract", str(room[0].root), "-o", str(tmp_path / "c"), "--prior-kind", "inverse"])
        assert "inverse" in capsys.readouterr().err

    def test_bad_kind_from_python_is_named(self, room, tmp_path):
        with pytest.raises(ValueError, match="prior_kind must be"):
            ex.run(ex.ExtractConfig(prior_kind="inverse"), room[0].root, tmp_path / "c")


def test_training_views_get_depth_from_a_disparity_prior(room):
    """L_d compares rendered depth with the prior by correlation, which is blind to scale and shift
    but not to inversion: from a disparity prior the trainer takes the aligned depth, or 1/p."""
    from geocues.depth_align import DepthAlignment
    from splat.views import ViewSet

    scene, depths = room
    al = DepthAlignment(index=0, ok=True, kind="disparity", scale=1 / A, shift=-B / A)  # exact inverse
    views = ViewSet(scene, [0, 1], alignments={scene.cameras[0].name: al}, prior_kind="disparity")
    valid = depths[0] > 0
    got = views[0].depth_prior.numpy()
    np.testing.assert_allclose(got[valid], depths[0][valid], rtol=2e-3)  # float16 storage
    np.testing.assert_allclose(views[0].depth_anchor.numpy()[valid], depths[0][valid], rtol=2e-3)
    p, valid1 = _disparity(depths[1]), depths[1] > 0
    np.testing.assert_allclose(views[1].depth_prior.numpy()[valid1], (1 / p)[valid1], rtol=2e-3)
    assert views[1].depth_anchor is None
    raw = ViewSet(scene, [0])  # kind depth: the prior as stored
    np.testing.assert_allclose(raw[0].depth_prior.numpy()[valid], _disparity(depths[0])[valid], rtol=2e-3)
