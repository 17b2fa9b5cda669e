"""`splat render`: look at a finished run — per-view panels and a video along the camera path.

One stage, one entry: ``run(cfg, run_dir, out=None, *, overwrite=False) -> Path`` (default OUT:
``RUN/renders``). For every chosen view it writes

    OUT/rgb/<name>.png      the render
    OUT/depth/<name>.png    median depth, colour-mapped (turbo, black where nothing was rendered; the
                            range is the 1st–99th percentile of the view, or of GT depth where that
                            exists, so the two compare; the panel's strip names it in metres)
    OUT/normal/<name>.png   rendered normals, camera frame, (1 - n) / 2 as in the contact sheets
    OUT/alpha/<name>.png    accumulated opacity, grey
    OUT/panels/<name>.png   GT | render | depth | normals | alpha, then GT depth, depth prior and normal
                            prior where the scene has them, each under a strip naming it (the
                            render's with its PSNR against GT)

and with ``video`` an MP4 (H.264 through imageio-ffmpeg, render | depth side by side, the depth in one
range for the whole video: the chosen views' 1st–99th percentile) along the chosen views in capture
order: positions interpolated linearly, rotations by slerp, the first view's
intrinsics. ``views`` is ``test``, ``train``, ``all`` or a ``cameras.json`` in the 3DGS reference
format (what `splat train` writes into every run; ``cx, cy`` at the image centre there).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geocues.atomic import atomic_dir, check_output_dir, check_replaceable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RenderConfig:
    """Options of `splat render`."""

    views: str = "test"
    """test, train, all, or a cameras.json file (3DGS reference format) of views to render."""
    video: bool = False
    """also write OUT/video.mp4 along the views in capture order."""
    frames: int = 120
    """frames of the video (spread evenly along the path)."""
    fps: int = 24
    """frames per second of the video."""
    scene: str | None = None
    """the scene folder (default: the one the run was trained on, from RUN/report.json)."""

    def validate(self) -> None:
        if self.views not in ("test", "train", "all") and not self.views.endswith(".json"):
            raise ValueError(f"--views must be test, train, all or a cameras.json file, got {self.views!r}")
        if self.frames < 2 or self.fps < 1:
            raise ValueError(f"--frames must be >= 2 and --fps >= 1 (got {self.frames}, {self.fps})")


@dataclass
class ViewCam:
    """A camera to render: name, K [3, 3], world-to-camera R [3, 3], t [3], size, scene index or None."""

    name: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    index: int | None = None


def cameras_from_json(path: Path, scale: float = 1.0) -> list[ViewCam]:
    """Views of a reference ``cameras.json`` (camera-to-world ``position`` / ``rotation``, fx, fy,
    width, height; the principal point ``cx``, ``cy`` where given, else the image centre as in the
    reference), sizes multiplied by ``scale``. Errors name the file and the entry."""
    try:
        entries = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read the camera file {path}: {exc}") from exc
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: expected a non-empty list of cameras (3DGS cameras.json format)")
    cams = []
    for k, e in enumerate(entries):
        try:
            Rc2w, C = np.asarray(e["rotation"], np.float64), np.asarray(e["position"], np.float64)
            w, h = round(e["width"] * scale), round(e["height"] * scale)
            fx, fy = float(e["fx"]) * scale, float(e["fy"]) * scale
            # the principal point this project adds (cx, cy; the reference's format has none: the centre)
            cx, cy = (float(e["cx"]) * scale, float(e["cy"]) * scale) if "cx" in e and "cy" in e else (w / 2, h / 2)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: camera {k} lacks or has a bad field ({exc!r}); needs position, "
                             f"rotation, fx, fy, width, height") from exc
        if not all(isinstance(e[side], (int, float)) and float(e[side]).is_integer() for side in ("width", "height")):
            raise ValueError(f"{path}: camera {k} has width/height {e['width']!r} x {e['height']!r}: whole pixels")
        if Rc2w.shape != (3, 3) or C.shape != (3,) or not (np.isfinite(Rc2w).all() and np.isfinite(C).all()):
            raise ValueError(f"{path}: camera {k} has a bad rotation (3x3) or position (3)")
        if not np.isfinite([fx, fy, cx, cy]).all():
            raise ValueError(f"{path}: camera {k} has a non-finite fx, fy, cx or cy")
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        R = Rc2w.T
        name = str(e.get("img_name", f"cam{k:04d}"))
        if not name or name in (".", "..") or any(c in name for c in "/\\\0"):  # outputs are OUT/<kind>/<name>.png
            raise ValueError(f"{path}: camera {k} has img_name {name!r}: a file name without '/' or '\\' "
                             "(the renders are named after it)")
        cams.append(ViewCam(name, K, R, -R @ C, int(w), int(h)))
    seen: dict[str, int] = {}
    for k, c in enumerate(cams):
        if c.name in seen:  # one render would overwrite the other
            raise ValueError(f"{path}: cameras {seen[c.name]} and {k} share the img_name {c.name!r}; give each its own")
        seen[c.name] = k
    return cams


def camera_path(cams: list[ViewCam], n_frames: int) -> list[ViewCam]:
    """``n_frames`` cameras along ``cams``: centres linear, rotations slerp, the first intrinsics."""
    from scipy.spatial.transform import Rotation, Slerp

    if len(cams) == 1:
        return [cams[0]] * n_frames
    keys = np.arange(len(cams), dtype=np.float64)
    rots = Rotation.from_matrix(np.stack([c.R.T for c in cams]))  # camera-to-world
    centres = np.stack([-c.R.T @ c.t for c in cams])
    s = np.linspace(0.0, keys[-1], n_frames)
    Rc2w = Slerp(keys, rots)(s).as_matrix()
    C = np.stack([np.interp(s, keys, centres[:, j]) for j in range(3)], 1)
    first = cams[0]
    return [ViewCam(f"frame{k:05d}", first.K, Rc2w[k].T, -Rc2w[k].T @ C[k], first.width, first.height)
            for k in range(n_frames)]


def colorize_depth(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """[H, W] metres -> [H, W, 3] uint8 (turbo), black where depth <= 0."""
    from matplotlib import colormaps

    x = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = (colormaps["turbo"](x)[..., :3] * 255).astype(np.uint8)
    rgb[~(depth > 0)] = 0
    return rgb


def depth_range(*maps: np.ndarray | None) -> tuple[float, float]:
    valid = np.concatenate([m[m > 0].ravel() for m in maps if m is not None] or [np.zeros(0)])
    if valid.size == 0:
        return 0.0, 1.0
    return float(np.percentile(valid, 1)), float(np.percentile(valid, 99))


def titled(img: np.ndarray, title: str) -> np.ndarray:
    """``img`` (uint8 [H, W, 3]) under an 18-px black strip with ``title`` in white (OpenCV's Hershey
    font), so a panel's columns name themselves."""
    import cv2

    strip = np.zeros((18, img.shape[1], 3), np.uint8)
    cv2.putText(strip, title, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([strip, img], axis=0)


def _u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _normal_u8(n: np.ndarray) -> np.ndarray:
    out = _u8((1 - n) / 2)
    out[~(np.abs(n).sum(-1) > 0)] = 0
    return out


def load_run(run_dir: Path, scene_override: str | Path | None = None):
    """(scene at the run's resolution and split, Gaussians, training config dict) of a finished
    `splat train` folder; the scene from RUN/report.json (splat/run_paths.py) unless ``scene_override``."""
    from geocues.scene import Scene
    from splat.gaussians import load_ply
    from splat.run_paths import gaussians_ply, recorded_path

    report_path = run_dir / "report.json"
    if not report_path.is_file():
        raise FileNotFoundError(f"{run_dir} holds no report.json (not a finished `splat train` folder)")
    report = json.loads(report_path.read_text())
    cfg = report.get("config", {})
    scene_dir = Path(scene_override) if scene_override else recorded_path(run_dir, report, "scene")
    if scene_dir is None or not scene_dir.is_dir():
        where = "given" if scene_override else f"recorded in {report_path}"
        raise FileNotFoundError(f"the run's scene folder {scene_dir} ({where}) does not exist; pass --scene SCENE")
    scene = Scene.load(scene_dir, downscale=cfg.get("downscale", 1.0), test_every=cfg.get("test_every", 8),
                       check_priors=False)
    params, _ = load_ply(gaussians_ply(run_dir), sh_degree=cfg.get("sh_degree"))
    return scene, params, cfg


def _chosen(cfg: RenderConfig, scene, run_dir: Path) -> list[ViewCam]:
    """The views to render; a scene's views with the run's camera refinement (RUN/camera_refinement.npz:
    training views their pose correction, every view the shared focal factor) when it has one."""
    if cfg.views.endswith(".json"):
        return cameras_from_json(Path(cfg.views))
    idx = {"test": scene.test_indices, "train": scene.train_indices, "all": list(range(len(scene)))}[cfg.views]
    if not idx:
        raise ValueError(f"the scene {scene.root} has no {cfg.views} views (test views need test_every > 0)")
    from splat.camera_opt import load_refinement, refine_Rt

    npz = run_dir / "camera_refinement.npz"
    corrections, focal = load_refinement(npz) if npz.is_file() else ({}, 1.0)
    views = []
    for i in idx:
        c = scene.cameras[i]
        K, R, t = refine_Rt(c.K, c.R, c.t, corrections.get(c.name), focal)
        views.append(ViewCam(Path(c.name).stem, K, R, t, c.width, c.height, i))
    return views


def run(cfg: RenderConfig, run_dir: str | Path, out: str | Path | None = None, *,
        overwrite: bool = False) -> Path:
    """Render the views of a finished run (module docstring); returns OUT."""
    import torch
    from tqdm.auto import tqdm

    from evaluation.image_metrics import psnr
    from splat.camera import Camera
    from splat.rasterize import render

    cfg.validate()
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"no run folder at {run_dir}")
    if cfg.views.endswith(".json") and not Path(cfg.views).is_file():  # before the scene is loaded
        raise FileNotFoundError(f"--views {cfg.views}: no such camera file")
    out = Path(out) if out is not None else run_dir / "renders"
    if out.exists() and not out.is_dir():  # was a raw "[Errno 20] Not a directory"
        raise ValueError(f"-o {out} is a file; the renders go into a folder")
    check_replaceable(out, "views.json", "a `splat render` output", {"run": run_dir})
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"{out} already holds renders; pass --overwrite to replace them")
    check_output_dir(out)
    scene, params, tcfg = load_run(run_dir, cfg.scene)
    views = _chosen(cfg, scene, run_dir)
    bg = torch.tensor(tcfg.get("background", (0.0, 0.0, 0.0)), dtype=torch.float32)
    gt_depth_dir = scene.root / "gt" / "depth"

    def draw(v: ViewCam) -> dict:
        with torch.no_grad():
            r = render(params, Camera.from_Rt(v.K, v.R, v.t, v.width, v.height), background=bg)
        return {k: r[k].numpy() for k in ("rgb", "median_depth", "normal", "alpha")}

    import imageio.v3 as iio

    pooled = []  # every view's depths, subsampled: the video's one colour range
    empty: list[str] = []  # views that see no Gaussian
    if not cfg.video and (cfg.frames, cfg.fps) != (RenderConfig.frames, RenderConfig.fps):
        log.warning("--frames / --fps shape the video: without --video they do nothing")
    with atomic_dir(out) as tmp:
        for sub in ("rgb", "depth", "normal", "alpha", "panels"):
            (tmp / sub).mkdir(parents=True)
        for v in tqdm(views, desc="splat render", unit="view"):
            r = draw(v)
            pooled.append(r["median_depth"][::4, ::4])
            gt_img = gt_d = prior_d = prior_n = None
            if v.index is not None:
                gt_img = scene.load_image(v.index)
                prior_d, prior_n = scene.depth_prior(v.index), scene.normal_prior(v.index)
                if gt_depth_dir.is_dir():
                    from splat.floor import load_gt_depth

                    try:
                        gt_d = load_gt_depth(gt_depth_dir, scene.cameras[v.index].stem, r["median_depth"].shape, 1000.0)
                    except FileNotFoundError:
                        gt_d = None
            if float(r["alpha"].max()) < 0.01:  # black images with a 0.00-1.00 m depth strip, said nowhere
                empty.append(v.name)
            lo, hi = depth_range(gt_d if gt_d is not None else r["median_depth"])
            tiles = {"rgb": _u8(r["rgb"]), "depth": colorize_depth(r["median_depth"], lo, hi),
                     "normal": _normal_u8(r["normal"]), "alpha": np.repeat(_u8(r["alpha"])[..., None], 3, -1)}
            for sub, img in tiles.items():
                iio.imwrite(tmp / sub / f"{v.name}.png", img)
            render_title = "render"
            if gt_img is not None and gt_img.shape == r["rgb"].shape:
                db = psnr(torch.from_numpy(np.clip(r["rgb"], 0, 1)), torch.from_numpy(gt_img))
                render_title += f"  {db:.2f} dB"
            panel = ([titled(_u8(gt_img), "GT")] if gt_img is not None else []) + [
                titled(img, t) for img, t in zip(tiles.values(),
                                                 (render_title, f"depth {lo:.2f}-{hi:.2f} m", "normals", "alpha"))]
            if gt_d is not None:
                panel.append(titled(colorize_depth(gt_d, lo, hi), "GT depth (same range)"))
            if prior_d is not None:
                plo, phi = depth_range(prior_d)
                panel.append(titled(colorize_depth(prior_d, plo, phi), f"depth prior {plo:.2f}-{phi:.2f}"))
            if prior_n is not None:
                panel.append(titled(_normal_u8(prior_n), "normal prior"))
            iio.imwrite(tmp / "panels" / f"{v.name}.png", np.concatenate(panel, axis=1))
        if cfg.video:
            _write_video(tmp / "video.mp4", camera_path(views, cfg.frames), draw, cfg.fps, depth_range(*pooled))
        (tmp / "views.json").write_text(json.dumps({"run": str(run_dir.resolve()), "views": cfg.views,
                                                    "names": [v.name for v in views],
                                                    "video_frames": cfg.frames if cfg.video else 0}, indent=1))
    log.info("rendered %d views of %s into %s", len(views), run_dir, out)
    if empty:
        log.warning("%d of %d views see no Gaussian (%s%s): their images are the background; are the cameras "
                    "in the run's frame?", len(empty), len(views), ", ".join(empty[:3]), ", ..." if len(empty) > 3 else "")
    return out


def _write_video(path: Path, path_cams: list[ViewCam], draw, fps: int, depth_lo_hi: tuple[float, float]) -> None:
    """H.264 MP4 of render | depth per frame (imageio-ffmpeg; sizes padded to even numbers), the depth
    in one colour range for the whole video (``depth_lo_hi``, metres: the chosen views' 1st-99th
    percentile, which the path between them stays within; a range from the first frame alone
    saturated a third of the frames of a room), named in a strip above it."""
    import imageio.v2 as iio2
    from tqdm.auto import tqdm

    writer = iio2.get_writer(str(path), fps=fps, codec="libx264", quality=8, macro_block_size=1,
                             ffmpeg_log_level="error", pixelformat="yuv420p")
    lo, hi = depth_lo_hi
    try:
        for v in tqdm(path_cams, desc="splat render video", unit="frame"):
            r = draw(v)
            frame = np.concatenate([titled(_u8(r["rgb"]), "render"),
                                    titled(colorize_depth(r["median_depth"], lo, hi), f"depth {lo:.2f}-{hi:.2f} m")],
                                   axis=1)
            h, w = frame.shape[:2]
            writer.append_data(np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0))))
    finally:
        writer.close()
