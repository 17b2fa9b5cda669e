"""`splat view`: the layers built from a finished run's files, the errors a user meets, the served
page as headless Chromium draws it (software WebGL), and Ctrl-C ending the server with one line."""

from __future__ import annotations

import json
import re
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from cues_synth import make_room_scene, room_edges, room_mesh
from geocues.cue_io import CUE_TYPE_COLORS, CueCloud, write_cues_ply, write_lines_ply
from geocues.scene import Scene
from geocues.types import CueType
from splat.browser_shot import find_chromium
from splat.gaussians import save_ply
from splat.sh import SH_C0
from splat.viewer import ViewConfig, load_lines, load_splats, run, stop, url_of

MAGENTA = np.array([1.0, 0.0, 1.0])  # every splat's colour: easy to count in a screenshot
needs_chromium = pytest.mark.skipif(find_chromium() is None,
                                    reason="no Chromium on PATH (Debian: apt-get install chromium; scripts/test.sh does)")


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory):
    """A finished-run folder: magenta Gaussians on the room's SfM points, the room mesh, a cue folder
    (cues.ply of every type, lines3d.ply) and report.json naming the scene and the cues."""
    import open3d as o3d

    base = tmp_path_factory.mktemp("view")
    root = make_room_scene(base / "room", n_views=8, w=64, h=48, priors="none")
    scene = Scene.load(root, test_every=4, check_priors=False)
    pts = torch.as_tensor(scene.points.xyz, dtype=torch.float32)
    n = len(pts)
    sh0 = torch.as_tensor((MAGENTA - 0.5) / SH_C0, dtype=torch.float32).repeat(n, 1, 1)
    params = {"means": pts, "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
              "scales": torch.full((n, 3), -2.5), "opacities": torch.full((n,), 4.0),
              "sh0": sh0, "shN": torch.zeros(n, 0, 3)}
    run_dir = base / "run"
    save_ply(run_dir / "point_cloud.ply", params)
    V, T, _ = room_mesh()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
    o3d.io.write_triangle_mesh(str(run_dir / "mesh.ply"), mesh)
    cues = base / "cues"
    xyz = scene.points.xyz
    cloud = CueCloud.concat([CueCloud.make(xyz[k::3], np.full((len(xyz[k::3]), 3), 0.5), t)
                             for k, t in enumerate(CueType)])
    write_cues_ply(cues / "cues.ply", cloud)
    write_lines_ply(cues / "lines3d.ply", room_edges(), np.tile(np.uint8([214, 39, 40]), (len(room_edges()), 1)))
    (run_dir / "report.json").write_text(json.dumps({"scene": str(root), "cues": str(cues / "cues.ply")}))
    return run_dir, scene, cloud


class TestLayers:
    def test_splats_covariance_colour_opacity(self, tmp_path):
        from scipy.spatial.transform import Rotation

        rng = np.random.default_rng(0)
        n = 50
        q = rng.normal(size=(n, 4))
        log_s = rng.uniform(-4, -1, size=(n, 3))
        sh0 = rng.normal(size=(n, 1, 3))
        f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        save_ply(tmp_path / "point_cloud.ply", {
            "means": f32(rng.normal(size=(n, 3))), "quats": f32(q), "scales": f32(log_s),
            "opacities": f32(rng.normal(size=n)), "sh0": f32(sh0), "shN": torch.zeros(n, 0, 3)})
        s = load_splats(tmp_path / "point_cloud.ply", max_splats=n)
        assert s.centers.shape == (n, 3) and s.covariances.shape == (n, 3, 3), s.covariances.shape
        assert s.rgbs.shape == (n, 3) and s.opacities.shape == (n, 1) and s.total == n
        R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy is xyzw
        expected = R @ (np.exp(2 * log_s)[:, :, None] * R.transpose(0, 2, 1))
        np.testing.assert_allclose(s.covariances, expected, rtol=1e-4, atol=1e-9)
        np.testing.assert_allclose(s.rgbs, np.clip(0.5 + SH_C0 * sh0[:, 0], 0, 1), atol=1e-5)
        assert ((s.opacities > 0) & (s.opacities < 1)).all()
        sub = load_splats(tmp_path / "point_cloud.ply", max_splats=20)
        assert len(sub.centers) == 20 and sub.total == n
        assert np.isin(sub.centers[:, 0], s.centers[:, 0]).all()  # a subset, not new points

    def test_splat_colours_are_the_sh_toward_the_mean_training_camera(self, fake_run, monkeypatch):
        """viser takes one colour per Gaussian: with higher SH bands it is their value in the direction
        from the mean training-camera centre to the Gaussian (degree 1 written out here), not the DC."""
        import splat.viewer as viewer
        from splat.sh import SH_C1
        from splat.viewer import mean_train_centre, splats_from_params

        rng = np.random.default_rng(1)
        n = 40
        means = rng.uniform(-2, 2, (n, 3))
        sh0, shN = rng.normal(0, 0.5, (n, 1, 3)), rng.normal(0, 0.5, (n, 3, 3))
        f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        params = {"means": f32(means), "quats": f32(np.tile([1.0, 0, 0, 0], (n, 1))),
                  "scales": f32(np.full((n, 3), -3.0)), "opacities": f32(np.zeros(n)), "sh0": f32(sh0),
                  "shN": f32(shN)}
        eye = np.array([0.3, -0.2, 0.1])
        d = means - eye
        x, y, z = (d / np.linalg.norm(d, axis=1, keepdims=True)).T
        band1 = (-SH_C1 * y)[:, None] * shN[:, 0] + (SH_C1 * z)[:, None] * shN[:, 1] + (-SH_C1 * x)[:, None] * shN[:, 2]
        expected = np.clip(0.5 + SH_C0 * sh0[:, 0] + band1, 0, 1)
        np.testing.assert_allclose(splats_from_params(params, n, eye=eye).rgbs, expected, atol=1e-5)
        dc = np.clip(0.5 + SH_C0 * sh0[:, 0], 0, 1)
        np.testing.assert_allclose(splats_from_params(params, n).rgbs, dc, atol=1e-5)
        assert np.abs(expected - dc).max() > 0.1  # the test tells the two apart

        run_dir, scene, _ = fake_run  # `splat view` passes the mean training centre, --colors dc none
        seen = []
        real = viewer.load_splats
        monkeypatch.setattr(viewer, "load_splats", lambda *a: seen.append(a[3]) or real(*a))
        for colors in ("centre", "dc"):
            stop(run(ViewConfig(port=0, colors=colors), run_dir, block=False))
        as_viewed = Scene.load(scene.root, check_priors=False)  # the viewer's split
        train = [c.center for c in as_viewed.cameras if c.index in set(as_viewed.train_indices)]
        assert 0 < len(train) < len(as_viewed.cameras)
        np.testing.assert_allclose(mean_train_centre(as_viewed), np.mean(train, axis=0))
        np.testing.assert_allclose(seen[0], np.mean(train, axis=0))
        assert seen[1] is None

    def test_lines_from_ply_and_npz(self, fake_run, tmp_path):
        from geocues.cue_io import write_lines_npz

        run_dir, _, _ = fake_run
        seg, rgb = load_lines(Path(json.loads((run_dir / "report.json").read_text())["cues"]).parent)
        np.testing.assert_allclose(seg, room_edges(), atol=1e-5)
        assert (rgb == [214, 39, 40]).all()
        assert load_lines(tmp_path) is None
        segs = room_edges()[:3]
        write_lines_npz(tmp_path / "lines3d.npz", segs, np.full(3, 2), [np.array([0, 1])] * 3,
                        np.zeros((3, 3), np.uint8))
        np.testing.assert_allclose(load_lines(tmp_path)[0], segs, atol=1e-5)

    def test_every_layer_is_served(self, fake_run):
        run_dir, scene, _ = fake_run
        server = run(ViewConfig(port=0), run_dir, block=False)
        try:
            with urllib.request.urlopen(url_of(server), timeout=30) as r:
                assert r.status == 200 and b"<html" in r.read().lower()
        finally:
            stop(server)


    def test_a_busy_port_is_named(self, fake_run, caplog):
        """viser moves to the next free port in silence; a user forwarding that port must be told."""
        run_dir, _, _ = fake_run
        first = run(ViewConfig(port=0), run_dir, block=False)
        try:
            busy = first.get_port()
            second = run(ViewConfig(port=busy), run_dir, block=False)
            try:
                assert second.get_port() != busy
                assert f"port {busy} is busy: serving on {second.get_port()} instead" in caplog.text
            finally:
                stop(second)
        finally:
            stop(first)


class TestErrors:
    def test_bad_run_folders_are_named(self, tmp_path):
        with pytest.raises(FileNotFoundError, match=re.escape(f"no run folder at {tmp_path / 'nope'}")):
            run(ViewConfig(port=0), tmp_path / "nope", block=False)
        with pytest.raises(FileNotFoundError, match="holds no point_cloud.ply"):
            run(ViewConfig(port=0), tmp_path, block=False)
        with pytest.raises(ValueError, match="unknown layers"):
            run(ViewConfig(port=0, show=("splats", "walls")), tmp_path, block=False)
        for host in ("999.1.1.1", "10.99.99.99"):  # viser waited forever on it, outliving a SIGTERM
            with pytest.raises(ValueError, match=f"--host '{host}' is no address of this machine to serve on"):
                ViewConfig(port=0, host=host).validate()
        ViewConfig(port=0, host="localhost").validate()

    def test_screenshot_size_and_name_are_checked_first(self, tmp_path, capsys):
        """--size 0 0 hung until killed, --size -5 100 was a DevTools traceback, a .jpg name got PNG data."""
        from cli.splat_cli import main

        for args, said in ((["--size", "0", "0"], "--size must be two whole pixels in 16..16384, got 0 0"),
                           (["--size", "-5", "100"], "--size must be two whole pixels"),
                           (["--screenshot", str(tmp_path / "s.jpg")], "the screenshot is a PNG; name it .png")):
            shot = [] if "--screenshot" in args else ["--screenshot", str(tmp_path / "s.png")]
            assert main(["view", str(tmp_path), "--port", "0", *shot, *args]) == 1
            assert said in capsys.readouterr().err

    def test_a_scene_or_cues_given_that_do_not_exist_are_errors(self, fake_run, tmp_path):
        run_dir, _, _ = fake_run
        with pytest.raises(FileNotFoundError, match=re.escape(f"--scene {tmp_path / 'nope'}: no such scene folder")):
            run(ViewConfig(port=0, scene=str(tmp_path / "nope")), run_dir, block=False)
        with pytest.raises(FileNotFoundError, match=re.escape(f"--cues {tmp_path / 'c'}: no such cue cloud")):
            run(ViewConfig(port=0, cues=str(tmp_path / "c")), run_dir, block=False)

    def test_cli_prints_one_line(self, tmp_path, capsys):
        from cli.splat_cli import main

        assert main(["view", str(tmp_path / "nope"), "--port", "0"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"splat view: error: no run folder at {tmp_path / 'nope'}"], err

    def test_missing_scene_and_cues_leave_their_layers_out(self, fake_run, tmp_path, caplog):
        import shutil

        run_dir, _, _ = fake_run
        lone = tmp_path / "run"
        lone.mkdir()
        shutil.copy(run_dir / "point_cloud.ply", lone)
        (lone / "report.json").write_text(json.dumps({"scene": str(tmp_path / "gone"), "cues": None}))
        from splat.viewer import _resolve

        files = _resolve(lone, ViewConfig())
        assert files["scene"] is None and files["cues"] is None and files["mesh"] is None
        assert "does not exist" in caplog.text and "no mesh.ply" in caplog.text
        (lone / "mesh.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n\x00")
        stop(run(ViewConfig(port=0), lone, block=False))  # splats alone; the damaged mesh is named
        assert f"could not read the mesh {lone / 'mesh.ply'}" in caplog.text


def _near(img: np.ndarray, rgb, tol: int = 40) -> np.ndarray:
    return (np.abs(img[..., :3].astype(int) - np.asarray(rgb)).max(-1) <= tol)


@needs_chromium
def test_browser_draws_the_splats(fake_run, tmp_path, monkeypatch):
    """The page served by `splat view` as Chromium draws it with software WebGL: the magenta splats
    fill part of the canvas; with only the cue layer on, the cue-type colours show instead. Nothing
    is left in the temporary folder (Chromium's org.chromium.Chromium.* scratch folders were)."""
    from cli.splat_cli import main

    run_dir, _, _ = fake_run
    tmp_root = Path(tempfile.mkdtemp(prefix="igs"))  # short: Chromium makes a unix socket in it
    monkeypatch.setenv("TMPDIR", str(tmp_root))
    monkeypatch.setattr(tempfile, "tempdir", None)  # gettempdir() reads TMPDIR again
    png = tmp_path / "view.png"
    assert main(["view", str(run_dir), "--screenshot", str(png), "--size", "640", "480", "--port", "0"]) == 0
    img = iio.imread(png)
    assert img.shape[:2] == (480, 640), img.shape
    canvas = img[:, :400]  # the GUI panel is on the right
    assert canvas.std() > 10, "blank page"
    magenta = _near(canvas, 255 * MAGENTA).mean()
    assert magenta > 0.02, f"only {magenta:.1%} of the canvas is the splats' magenta"

    png2 = tmp_path / "cues.png"
    assert main(["view", str(run_dir), "--screenshot", str(png2), "--size", "640", "480", "--port", "0",
                 "--show", "cues"]) == 0
    canvas = iio.imread(png2)[:, :400]
    assert _near(canvas, 255 * MAGENTA).mean() < 0.001, "splats shown though unchecked"
    for t in CueType:
        share = _near(canvas, CUE_TYPE_COLORS[t]).mean()
        assert share > 1e-4, f"no {t.name} cue colour {CUE_TYPE_COLORS[t]} in the picture ({share:.2%})"
    left = sorted(tmp_root.iterdir())
    shutil.rmtree(tmp_root)
    assert not left, f"left in the temporary folder: {left}"


def test_ctrl_c_ends_with_one_line(fake_run):
    """`splat view RUN` prints its URL, serves the page and on SIGINT exits 0 with one line, no traceback."""
    run_dir, _, _ = fake_run
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # Ctrl-C as a terminal delivers it: a test run started in the background (`cmd &` without job
    # control) ignores SIGINT, and a child would inherit that and never see the signal
    proc = subprocess.Popen([sys.executable, "-m", "cli.splat_cli", "view", str(run_dir), "--port", "0", "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            cwd=Path(__file__).resolve().parents[1],
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        first = proc.stdout.readline()
        assert " at http://127.0.0.1:" in first, first
        url = first.split(" at ")[1].split()[0]
        with urllib.request.urlopen(url, timeout=30) as r:
            assert r.status == 200
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert out.strip().splitlines() == ["viewer stopped"], out
    assert "Traceback" not in err, err


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_while_loading_stops_the_viewer_even_where_a_library_swallows_it(monkeypatch, tmp_path, capsys,
                                                                                 sig, code):
    """A SIGINT during start-up ends the command (exit 130, one line; SIGTERM 143), even when the code it
    lands in swallows the KeyboardInterrupt (as viser's start-up did: the viewer served on until a second
    Ctrl-C)."""
    import splat.viewer as viewer
    from cli.splat_cli import main

    calls = []

    def loading_that_swallows(cfg, run_dir, *, port=None, block=True):
        try:
            os.kill(os.getpid(), sig)
            time.sleep(0.2)
        except KeyboardInterrupt:
            pass  # a library's start-up
        return "server"

    monkeypatch.setattr(viewer, "run", loading_that_swallows)
    monkeypatch.setattr(viewer, "serve", lambda server: calls.append("served"))
    monkeypatch.setattr(viewer, "stop", lambda server: calls.append(f"stopped {server}"))
    monkeypatch.setattr(viewer, "url_of", lambda server: "http://127.0.0.1:1")
    before = signal.getsignal(signal.SIGINT)
    assert main(["view", str(tmp_path), "--port", "0"]) == code
    assert calls == ["stopped server"]
    assert capsys.readouterr().out.strip() == "viewer stopped while loading"
    assert signal.getsignal(signal.SIGINT) is before  # the handlers are back


def test_a_second_ctrl_c_stops_a_slow_load(monkeypatch, tmp_path, capsys):
    import splat.viewer as viewer
    from cli.splat_cli import main

    def slow_load(cfg, run_dir, *, port=None, block=True):
        os.kill(os.getpid(), signal.SIGINT)  # recorded
        time.sleep(0.1)
        os.kill(os.getpid(), signal.SIGINT)  # raises: the user insists
        time.sleep(5)
        raise AssertionError("the second Ctrl-C did not stop the load")

    monkeypatch.setattr(viewer, "run", slow_load)
    before = signal.getsignal(signal.SIGINT)
    assert main(["view", str(tmp_path), "--port", "0"]) == 130
    assert capsys.readouterr().out.strip() == "viewer stopped while loading"
    assert signal.getsignal(signal.SIGINT) is before
