"""`splat view`: a finished run in the browser, on viser (the library of nerfstudio's and gsplat's viewers).

One entry: ``run(cfg, run_dir, *, port=None, block=True) -> viser.ViserServer``. It serves, each layer
behind a GUI checkbox,

    splats    RUN/point_cloud.ply as Gaussians (at most ``max_splats``, a seeded random subset, so that
              the browser keeps up). viser takes one colour per Gaussian, not SH: each Gaussian's SH
              is evaluated once, toward it from the mean training-camera centre (``colors="centre"``,
              what a capture filmed from inside the room saw), or its degree-0 term (``"dc"``)
    mesh      RUN/mesh.ply (vertex colours where it has them)
    cues      the run's cue cloud (report.json "cues"), coloured by type as cues_by_type.ply:
              SfM blue, line red, plane green
    lines     the cue folder's lines3d.ply (an ``edge`` element), else lines3d.npz
    cameras   the scene's cameras (report.json "scene") as frustums, test views orange

Layers whose file is missing are left out with one warning; only a missing RUN or Gaussian PLY is an
error. The start view is a camera of the scene (``start_view``), world up is the mean of the cameras'
up vectors. ``splat view RUN --screenshot PNG`` saves the page as headless Chromium draws it
(:mod:`splat.browser_shot`) instead of serving.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from splat.run_paths import gaussians_ply, recorded_path

log = logging.getLogger(__name__)

TRAIN_COLOR, TEST_COLOR = (40, 40, 40), (255, 127, 14)


@dataclass(frozen=True)
class ViewConfig:
    """Options of `splat view`."""

    port: int = 8080
    """port to serve on (0: any free port; a busy port is skipped for the next free one)."""
    host: str = "127.0.0.1"
    """address to listen on (0.0.0.0 to open the viewer to other machines)."""
    max_splats: int = 300_000
    """send at most this many Gaussians to the browser (a seeded random subset of the run's)."""
    max_cues: int = 200_000
    """send at most this many cue points (a seeded random subset)."""
    show: tuple[str, ...] = ("splats", "lines", "cameras")
    """layers shown at the start (the others are one checkbox away): splats, mesh, cues, lines, cameras."""
    start_view: int = 0
    """scene camera the view starts from (and 'Reset view' returns to)."""
    scene: str | None = None
    """the scene folder (default: the one the run was trained on, from RUN/report.json)."""
    cues: str | None = None
    """the cue cloud, cues.ply or its folder (default: the run's, from RUN/report.json)."""
    seed: int = 0
    """seed of the subsets."""
    colors: Literal["centre", "dc"] = "centre"
    """splat colours (viser takes one per Gaussian): centre = the SH evaluated toward each Gaussian from
    the mean training-camera centre (needs the scene; else dc); dc = the degree-0 term alone."""

    def validate(self) -> None:
        unknown = sorted(set(self.show) - set(LAYERS))
        if unknown:
            raise ValueError(f"--show: unknown layers {unknown}; choose from {', '.join(LAYERS)}")
        if self.max_splats < 1 or self.max_cues < 1:
            raise ValueError(f"--max-splats and --max-cues must be >= 1 (got {self.max_splats}, {self.max_cues})")
        if not 0 <= self.port < 65536:
            raise ValueError(f"--port must be in 0..65535, got {self.port}")
        import socket

        try:  # viser waited forever on a host it cannot serve on (and outlived the first SIGTERM)
            with socket.socket(socket.AF_INET6 if ":" in self.host else socket.AF_INET) as probe:
                probe.bind((self.host, 0))
        except (OSError, UnicodeError) as exc:
            raise ValueError(f"--host {self.host!r} is no address of this machine to serve on ({exc}); "
                             "127.0.0.1 (this machine only) or 0.0.0.0 (every interface)") from None


LAYERS = ("splats", "mesh", "cues", "lines", "cameras")
LAST_GUI_TEXT = "Gaussians"  # in the last GUI element: a page that shows it has every scene message


@dataclass
class Splats:
    """Gaussians as viser takes them: centers [N, 3], covariances [N, 3, 3] (metres^2), rgbs [N, 3]
    and opacities [N, 1] in [0, 1]; ``total`` is the count in the file before subsampling."""

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray
    total: int


def _subset(n: int, k: int, seed: int) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False))


def load_splats(path: Path, max_splats: int, seed: int = 0, eye: np.ndarray | None = None) -> Splats:
    """RUN/point_cloud.ply -> :class:`Splats`: covariance R diag(exp(s)^2) R^T, opacity sigmoid(o),
    colour clipped to [0, 1]: the SH evaluated in the direction eye -> mean when ``eye`` [3] (a world
    point) is given, else the degree-0 term 0.5 + SH_C0 * sh0."""
    from splat.gaussians import load_ply

    params, _ = load_ply(path)
    return splats_from_params(params, max_splats, seed, eye)


def splats_from_params(params, max_splats: int, seed: int = 0, eye: np.ndarray | None = None) -> Splats:
    """Gaussian parameters (splat.gaussians contract, any device) -> :class:`Splats` (colours as
    :func:`load_splats`)."""
    import torch

    from splat.projection import quat_to_rotmat
    from splat.sh import SH_C0, sh_degree_of, sh_to_rgb

    params = {k: v.detach().cpu() for k, v in params.items()}
    n = len(params["means"])
    keep = _subset(n, max_splats, seed)
    if len(keep) < n:
        log.debug("sending %d of the %d Gaussians (--max-splats)", len(keep), n)
    rows = torch.from_numpy(keep)
    p = {k: v[rows].double().numpy() for k, v in params.items()}
    R = quat_to_rotmat(params["quats"][rows].double()).numpy()  # [K, 3, 3]
    s2 = np.exp(2.0 * p["scales"])  # [K, 3] variances along the local axes
    cov = np.einsum("nij,nj,nkj->nik", R, s2, R)
    if eye is not None and params["shN"].shape[1] > 0:  # one fixed view direction per Gaussian
        dirs = p["means"] - np.asarray(eye, np.float64)[None]
        dirs = dirs / np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
        rgb = np.clip(sh_to_rgb(torch.from_numpy(p["sh0"]), torch.from_numpy(p["shN"]), torch.from_numpy(dirs),
                                sh_degree_of(params["shN"])).numpy(), 0.0, 1.0)
    else:
        rgb = np.clip(0.5 + SH_C0 * p["sh0"][:, 0], 0.0, 1.0)
    opacity = 1.0 / (1.0 + np.exp(-p["opacities"]))
    return Splats(p["means"].astype(np.float32), cov.astype(np.float32), rgb.astype(np.float32),
                  opacity.astype(np.float32)[:, None], n)


def load_mesh(path: Path):
    """A triangle mesh PLY -> trimesh.Trimesh (vertex colours kept; no processing)."""
    import trimesh

    mesh = trimesh.load(str(path), process=False, force="mesh")
    if len(mesh.faces) == 0:
        raise ValueError(f"{path} holds no triangles")
    return mesh


def load_cues(path: Path, max_cues: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A cue PLY -> (xyz [K, 3] float32, rgb [K, 3] uint8 by cue type, CUE_TYPE_COLORS)."""
    from geocues.cue_io import CUE_TYPE_COLORS, read_cues_ply

    cloud = read_cues_ply(path)
    keep = _subset(len(cloud), max_cues, seed)
    palette = np.full((256, 3), 128, np.uint8)
    for t, rgb in CUE_TYPE_COLORS.items():
        palette[int(t)] = rgb
    log.info("cues %s: %s", path, cloud.counts())
    return cloud.xyz[keep].astype(np.float32), palette[cloud.cue_type[keep]]


def load_lines(cue_dir: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """CUES/lines3d.ply (vertex + edge elements) or else CUES/lines3d.npz -> (segments [L, 2, 3]
    float32, colours [L, 3] uint8), or None when neither exists."""
    ply, npz = cue_dir / "lines3d.ply", cue_dir / "lines3d.npz"
    if ply.is_file():
        from plyfile import PlyData

        data = PlyData.read(str(ply))
        names = [el.name for el in data.elements]
        if "edge" not in names or "vertex" not in names:
            raise ValueError(f"{ply} is no line set: elements {names}, expected vertex and edge")
        v, e = data["vertex"].data, data["edge"].data
        xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)
        seg = xyz[np.stack([e["vertex1"], e["vertex2"]], 1)]
        has_rgb = all(c in (e.dtype.names or ()) for c in ("red", "green", "blue"))
        rgb = (np.stack([e["red"], e["green"], e["blue"]], 1).astype(np.uint8) if has_rgb
               else np.tile(np.uint8([214, 39, 40]), (len(seg), 1)))
        return seg, rgb
    if npz.is_file():
        from geocues.cue_io import read_lines_npz

        z = read_lines_npz(npz)
        return z["segments"].astype(np.float32), np.asarray(z["colors"], np.uint8)
    return None


def _resolve(run_dir: Path, cfg: ViewConfig) -> dict[str, Path | None]:
    """The files of each layer (None where absent, with one warning). Raises on a bad RUN."""
    if not run_dir.is_dir():
        raise FileNotFoundError(f"no run folder at {run_dir}")
    ply = gaussians_ply(run_dir)
    report_path = run_dir / "report.json"
    report = {}
    if report_path.is_file():
        try:
            report = json.loads(report_path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{report_path} is not valid JSON: {e}") from e
    elif cfg.scene is None or cfg.cues is None:
        log.warning("%s holds no report.json: no scene or cues to show unless --scene/--cues are given", run_dir)
    if cfg.scene and not Path(cfg.scene).is_dir():  # given, not recorded: an error, not a layer left out
        raise FileNotFoundError(f"--scene {cfg.scene}: no such scene folder")
    if cfg.cues and not Path(cfg.cues).exists():
        raise FileNotFoundError(f"--cues {cfg.cues}: no such cue cloud or folder")
    scene = Path(cfg.scene) if cfg.scene else recorded_path(run_dir, report, "scene")
    cues = Path(cfg.cues) if cfg.cues else recorded_path(run_dir, report, "cues")
    if cues is not None and cues.is_dir():
        cues = cues / "cues.ply"
    files = {"splats": ply, "mesh": run_dir / "mesh.ply", "cues": cues, "scene": scene,
             "lines": cues.parent if cues is not None else None}
    if scene is not None and not scene.is_dir():
        log.warning("the run's scene folder %s does not exist: no cameras (pass --scene SCENE)", scene)
        files["scene"] = None
    if cues is not None and not cues.is_file():
        log.warning("no cue cloud at %s: no cues or lines (pass --cues CUES)", cues)
        files["cues"] = files["lines"] = None
    if not files["mesh"].is_file():
        log.warning("%s holds no mesh.ply: no mesh layer", run_dir)
        files["mesh"] = None
    return files


def mean_train_centre(scene) -> np.ndarray:
    """[3] the mean centre of the scene's training cameras (all cameras when none is held out)."""
    idx = list(scene.train_indices) or list(range(len(scene.cameras)))
    return np.mean([scene.cameras[i].center for i in idx], axis=0)


def _camera_pose(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) -> (wxyz of camera-to-world, centre). viser's frustums use the OpenCV
    camera frame (+z forward, +y down), as COLMAP does, so no axis flip is needed."""
    import viser.transforms as vtf

    return vtf.SO3.from_matrix(R.T).wxyz, -R.T @ t


def _add_cameras(server, scene) -> tuple:
    """Frustums of every camera (test views orange); returns their handles."""
    test = set(scene.test_indices)
    centers = np.array([c.center for c in scene.cameras])
    spread = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if len(centers) > 1 else 1.0
    size = max(0.03 * spread, 0.02)
    handles = []
    for c in scene.cameras:
        wxyz, pos = _camera_pose(c.R, c.t)
        fov = 2.0 * np.arctan(c.height / (2.0 * c.K[1, 1]))
        handles.append(server.scene.add_camera_frustum(
            f"/cameras/{c.stem}", fov=float(fov), aspect=c.width / c.height, scale=size,
            thickness=1.5, thickness_units="screen", color=TEST_COLOR if c.index in test else TRAIN_COLOR,
            wxyz=wxyz, position=pos))
    return tuple(handles)


def _start_camera(server, scene, k: int, splats: Splats) -> None:
    """World up from the cameras, the start view at camera ``k`` looking at the median splat depth."""
    if not 0 <= k < len(scene.cameras):
        raise ValueError(f"--start-view {k}: the scene {scene.root} has {len(scene.cameras)} cameras")
    up = -np.mean([c.R[1] for c in scene.cameras], axis=0)  # camera +y is down in the OpenCV frame
    up = up / max(np.linalg.norm(up), 1e-12)
    server.scene.set_up_direction(up)
    cam = scene.cameras[k]
    z = (splats.centers.astype(np.float64) @ cam.R.T + cam.t)[:, 2]
    depth = float(np.median(z[z > 0])) if np.any(z > 0) else 1.0
    # a step behind the camera: its own frustum in view, not around the eye
    server.initial_camera.position = cam.center - 0.3 * depth * cam.R[2]
    server.initial_camera.look_at = cam.center + depth * cam.R[2]
    server.initial_camera.up = -cam.R[1]
    server.initial_camera.fov = float(2.0 * np.arctan(cam.height / (2.0 * cam.K[1, 1])))


def build(server, cfg: ViewConfig, files: dict[str, Path | None]) -> dict[str, tuple]:
    """Add every layer to ``server`` with a checkbox each; returns {layer: handles}."""
    t0 = time.perf_counter()
    scene = None
    if files["scene"] is not None:
        from geocues.scene import Scene

        scene = Scene.load(files["scene"], check_priors=False)
    eye = mean_train_centre(scene) if scene is not None and cfg.colors == "centre" else None
    if eye is None and cfg.colors == "centre":
        log.info("no scene cameras: splat colours are the SH degree-0 term")
    splats = load_splats(files["splats"], cfg.max_splats, cfg.seed, eye)
    extent = np.percentile(splats.centers, 98, axis=0) - np.percentile(splats.centers, 2, axis=0)
    size = float(np.linalg.norm(extent)) or 1.0
    layers: dict[str, tuple] = {"splats": (server.scene.add_gaussian_splats(
        "/splats", splats.centers, splats.covariances, splats.rgbs, splats.opacities),)}
    if files["mesh"] is not None:
        try:
            layers["mesh"] = (server.scene.add_mesh_trimesh("/mesh", load_mesh(files["mesh"])),)
        except Exception as e:  # trimesh raises several types for a damaged file
            log.warning("could not read the mesh %s (%s): no mesh layer", files["mesh"], e)
    if files["cues"] is not None:
        xyz, rgb = load_cues(files["cues"], cfg.max_cues, cfg.seed)
        layers["cues"] = (server.scene.add_point_cloud("/cues", xyz, rgb, point_size=0.003 * size),)
    lines = load_lines(files["lines"]) if files["lines"] is not None else None
    if lines is not None:
        seg, rgb = lines
        layers["lines"] = (server.scene.add_line_segments(
            "/lines", seg, np.repeat(rgb[:, None], 2, axis=1), thickness=2.0, thickness_units="screen"),)
    if scene is not None:
        layers["cameras"] = _add_cameras(server, scene)
        _start_camera(server, scene, cfg.start_view, splats)
    else:  # no cameras: look at the middle of the Gaussians from outside their box
        mid = np.median(splats.centers, axis=0).astype(np.float64)
        server.initial_camera.look_at = mid
        server.initial_camera.position = mid + 0.8 * size * np.array([0.6, -0.6, 0.5])
    for name, handles in layers.items():
        for h in handles:
            h.visible = name in cfg.show
        box = server.gui.add_checkbox(name, initial_value=name in cfg.show)
        box.on_update(lambda _, hs=handles, b=box: [setattr(h, "visible", b.value) for h in hs])
    server.gui.add_markdown(f"{len(splats.rgbs):,} of {splats.total:,} {LAST_GUI_TEXT}")  # sent last
    log.info("viewer layers %s ready in %.1f s", list(layers), time.perf_counter() - t0)
    return layers


def url_of(server) -> str:
    host = server.get_host()
    return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{server.get_port()}"


def stop(server) -> None:
    """Stop the server quietly (viser prints 'Server stopped' from its thread)."""
    with contextlib.redirect_stdout(io.StringIO()):
        server.stop()


def run(cfg: ViewConfig, run_dir: str | Path, *, port: int | None = None, block: bool = True):
    """Serve the run ``run_dir`` at http://HOST:PORT (``port`` overrides ``cfg.port``). With ``block``
    it serves until Ctrl-C, then stops the server; either way it returns the viser server (stop it
    with :func:`stop`). Raises FileNotFoundError / ValueError naming the path for a bad RUN."""
    import viser

    cfg.validate()
    run_dir = Path(run_dir)
    files = _resolve(run_dir, cfg)
    log.info("view %s: %s", run_dir, cfg)
    wanted = cfg.port if port is None else port
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner even with verbose=False
        server = viser.ViserServer(host=cfg.host, port=wanted, verbose=False)
    try:
        if wanted and server.get_port() != wanted:  # viser moves on to the next free port without a word
            log.warning("port %d is busy: serving on %d instead (forward that one over SSH)", wanted,
                        server.get_port())
        server.gui.configure_theme(show_share_button=False)
        server.gui.main_panel.dock_right()
        build(server, cfg, files)
    except BaseException:
        stop(server)
        raise
    log.info("serving %s at %s", run_dir, url_of(server))
    if block:
        serve(server)
    return server


def serve(server) -> None:
    """Serve until Ctrl-C (KeyboardInterrupt), then stop the server."""
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        stop(server)


class LiveView:
    """`splat train --view`: the Gaussians of a running training in the browser, refreshed every
    ``every`` iterations (the step, loss and counts beside them); the cameras as in `splat view`."""

    def __init__(self, scene, port: int = 8080, host: str = "127.0.0.1", max_splats: int = 100_000):
        import viser

        with contextlib.redirect_stdout(io.StringIO()):
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.max_splats = max_splats
        self.eye = mean_train_centre(scene)  # colours as `splat view` shows them
        self.server.gui.configure_theme(show_share_button=False)
        self.status = self.server.gui.add_markdown("starting")
        _add_cameras(self.server, scene)
        log.info("live view of the training at %s", url_of(self.server))

    def update(self, params, step: int, loss: float) -> None:
        s = splats_from_params(params, self.max_splats, seed=step, eye=self.eye)
        # the same name replaces the node in every connected browser
        self.server.scene.add_gaussian_splats("/splats", s.centers, s.covariances, s.rgbs, s.opacities)
        self.status.content = f"step {step:,} · loss {loss:.4f} · {s.total:,} Gaussians"

    def close(self) -> None:
        stop(self.server)
