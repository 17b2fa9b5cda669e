"""`evaluate make-room`: write a complete benchmark scene folder for a procedural room.

    OUT/images/00000.png ...            renders (8-bit sRGB, sensor noise)
    OUT/sparse/0/                       COLMAP model: known poses, PINHOLE intrinsics, and 3D points
                                        from really running pycolmap on the renders (geocues.sfm)
    OUT/gt/mesh.ply                     exact GT surface (normals face the free space)
    OUT/gt/triangle_material.npy        [F] int32 material index per triangle (names in scene.json)
    OUT/gt/depth/<stem>.npy             [H, W] float32 z-depth, metres
    OUT/gt/normal/<stem>.npy            [H, W, 3] float32 unit normals, camera frame, facing camera
    OUT/priors/depth/<stem>.npy         SIMULATED monocular depth (priors.py)
    OUT/priors/normal/<stem>.npy        SIMULATED monocular normals
    OUT/scene.json                      layout, seed, generator version, every simulation parameter
    OUT/preview.png                     contact sheet of six views
    OUT/make_room_report.json           seconds per stage, SfM figures (not deterministic)

The folder is built in a temporary sibling and renamed into place (nothing half-written). Every
random draw comes from numpy Generators spawned from the seed: one stream each for the layout, the
trajectory, the sensor noise and the priors, so e.g. changing ``n_views`` keeps the room.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from evaluation.rooms.layout import make_room_geometry
from evaluation.rooms.priors import PriorConfig, simulate_depth_prior, simulate_normal_prior
from evaluation.rooms.render import add_sensor_noise, pixel_directions, render_view
from evaluation.rooms.trajectory import TrajectoryConfig, make_trajectory
from geocues.extract_checks import check_finite

log = logging.getLogger(__name__)

GENERATOR_VERSION = "1.0"


@dataclass
class RoomConfig:
    """Options of `evaluate make-room`."""

    layout: Literal["textured", "bare"] = "textured"
    """textured: posters, rug, wood floor, shelves, furniture; bare: white walls, few objects."""
    seed: int = 0
    """Seed of every random draw (room, path, noise, priors); same seed, same scene."""
    width: int = 640
    """Image width in pixels."""
    height: int = 480
    """Image height in pixels."""
    n_views: int = 60
    """Number of views along the hand-held loop."""
    focal: float = 525.0
    """Focal length in pixels for a 640 px wide image (scaled with the width; fx = fy)."""
    supersample: int = 2
    """Anti-aliasing: S x S rays per pixel for the colour."""
    shadows: bool = True
    """Cast hard shadows from the point lights."""
    image_noise: float = 0.004
    """Standard deviation of the Gaussian sensor noise (display units, before 8-bit rounding)."""
    sfm: bool = True
    """Fill the model's 3D points by running pycolmap on the renders (geocues.sfm)."""
    keep_sfm_cache: bool = False
    """Keep the SfM database (OUT/cache/sfm) instead of deleting it after triangulation."""
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    """Hand-held camera loop."""
    priors: PriorConfig = field(default_factory=PriorConfig)
    """SIMULATED monocular priors."""

    def intrinsics(self) -> np.ndarray:
        """[3, 3] PINHOLE K, COLMAP pixel convention (principal point at the image centre)."""
        f = self.focal * self.width / 640.0
        return np.array([[f, 0.0, self.width / 2.0], [0.0, f, self.height / 2.0], [0.0, 0.0, 1.0]])


def _check(cfg: RoomConfig) -> None:
    if cfg.layout not in ("textured", "bare"):
        raise ValueError(f"layout must be 'textured' or 'bare', got {cfg.layout!r}")
    if cfg.width < 8 or cfg.height < 8:
        raise ValueError(f"image size must be at least 8 x 8, got {cfg.width} x {cfg.height}")
    if cfg.n_views < 2:
        raise ValueError(f"n_views must be >= 2, got {cfg.n_views}")
    cfg.priors.validate()
    if cfg.supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {cfg.supersample}")
    if cfg.seed < 0:
        raise ValueError(f"seed must be >= 0, got {cfg.seed}")
    # --image-noise nan/-1 gave noise-free images, --focal -525 a mirrored camera, nan a message about
    # GT depth; --trajectory.clearance nan was accepted
    if not (math.isfinite(cfg.focal) and cfg.focal > 0):
        raise ValueError(f"--focal must be a finite focal length > 0 (pixels at 640 px width), got {cfg.focal}")
    if not (math.isfinite(cfg.image_noise) and 0 <= cfg.image_noise <= 1):
        raise ValueError(f"--image-noise is a standard deviation of [0, 1] pixel values and must be in [0, 1], "
                         f"got {cfg.image_noise}")
    check_finite(cfg.trajectory, "trajectory.")


def contact_sheet(images: list[np.ndarray], cols: int = 3, width: int = 320) -> np.ndarray:
    """Grid of uint8 RGB images, each resized to ``width`` px wide, [h, w, 3] uint8."""
    import cv2

    if not images:
        raise ValueError("contact_sheet needs at least one image")
    h = int(round(images[0].shape[0] * width / images[0].shape[1]))
    tiles = [cv2.resize(im, (width, h), interpolation=cv2.INTER_AREA) for im in images]
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[r:r + cols], axis=1) for r in range(0, len(tiles), cols)]
    return np.concatenate(rows, axis=0)


def _in_order(fn, items: list, workers: int):
    """``fn(item)`` for every item, computed in ``workers`` threads at most ``2 * workers`` ahead of
    the consumer, yielded in order (so memory stays bounded); the pool is shut down on any exit."""
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        pending: deque = deque()
        try:
            for item in items:
                pending.append(pool.submit(fn, item))
                if len(pending) >= 2 * workers:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()


def _run_sfm(scene_dir: Path, keep_cache: bool) -> dict:
    """Triangulate 3D points with known poses (geocues.sfm); {"run": False, ...} if unavailable."""
    try:
        from geocues import sfm
    except ImportError as exc:  # the SfM stage is optional for the generator
        log.warning("make-room: geocues.sfm is not available (%s); the model has no 3D points", exc)
        return {"run": False, "reason": f"geocues.sfm not importable: {exc}"}
    report = json.loads((sfm.run(sfm.SfmConfig(), scene_dir) / "sfm_report.json").read_text())
    if not keep_cache:
        shutil.rmtree(scene_dir / "cache", ignore_errors=True)
    return {"run": True, "report": report}


def make_room(out: str | Path, cfg: RoomConfig = RoomConfig(), overwrite: bool = False) -> Path:
    """Generate, render and write the room scene folder ``out``; return its path."""
    import cv2

    from geocues.atomic import atomic_dir, check_output_dir, check_replaceable
    from geocues.colmap_io import RawImage, write_model

    out = Path(out)
    _check(cfg)
    check_replaceable(out, "make_room_report.json", "a benchmark room of `evaluate make-room`")
    if out.exists() and not overwrite:
        raise ValueError(f"{out} already exists; pass --overwrite to replace it")
    check_output_dir(out)
    log.info("make-room %s: config %s", out, asdict(cfg))
    t_start = time.perf_counter()
    seconds: dict[str, float] = {}
    ss_layout, ss_traj, ss_noise, ss_priors = np.random.SeedSequence(cfg.seed).spawn(4)
    room = make_room_geometry(cfg.layout, np.random.default_rng(ss_layout))
    scene = room.mesh.raycasting_scene()
    poses = make_trajectory(room.size, room.mesh.boxes, cfg.n_views, np.random.default_rng(ss_traj),
                            cfg.trajectory)
    K = cfg.intrinsics()
    noise_rng = np.random.default_rng(ss_noise)
    prior_rngs = [np.random.default_rng(s) for s in ss_priors.spawn(cfg.n_views)]
    rays = pixel_directions(K, cfg.width, cfg.height, np.array([[0.5, 0.5]]))[:, :, 0]  # [H, W, 3]

    with atomic_dir(out) as tmp:
        for sub in ("images", "gt/depth", "gt/normal", "priors/depth", "priors/normal"):
            (tmp / sub).mkdir(parents=True)
        room.mesh.write_ply(tmp / "gt" / "mesh.ply")
        np.save(tmp / "gt" / "triangle_material.npy", room.mesh.tri_material)
        raw_images, per_image, preview = [], {}, []
        pick = set(np.linspace(0, cfg.n_views - 1, 6).round().astype(int).tolist())
        t0 = time.perf_counter()
        # Views are rendered in threads (ray casting and numpy release the GIL), in order; the
        # random draws (noise, priors) stay in this loop, so the scene does not depend on the threads.
        def render(pose):
            return render_view(room, scene, K, pose[0], pose[1], cfg.width, cfg.height,
                               cfg.supersample, cfg.shadows)

        views = _in_order(render, poses, workers=min(os.cpu_count() or 1, 8))
        for k, ((R, t), view) in enumerate(tqdm(zip(poses, views), total=len(poses),
                                                desc=f"render {cfg.layout} room", unit="view")):
            stem = f"{k:05d}"
            rgb = add_sensor_noise(view.image, noise_rng, cfg.image_noise)
            if not cv2.imwrite(str(tmp / "images" / f"{stem}.png"), rgb[:, :, ::-1]):
                raise OSError(f"could not write {tmp / 'images' / f'{stem}.png'}")
            np.save(tmp / "gt" / "depth" / f"{stem}.npy", view.depth)
            np.save(tmp / "gt" / "normal" / f"{stem}.npy", view.normal)
            dprior, dpar = simulate_depth_prior(view.depth, prior_rngs[k], cfg.priors)
            nprior, npar = simulate_normal_prior(view.normal, rays, prior_rngs[k], cfg.priors)
            np.save(tmp / "priors" / "depth" / f"{stem}.npy", dprior)
            np.save(tmp / "priors" / "normal" / f"{stem}.npy", nprior)
            per_image[stem] = {"depth": dpar, "normal": npar}
            raw_images.append(RawImage(image_id=k + 1, camera_id=1, name=f"{stem}.png", model="PINHOLE",
                                       width=cfg.width, height=cfg.height, K=K, R=R, t=t))
            if k in pick:
                preview.append(rgb)
        seconds["render_and_priors"] = time.perf_counter() - t0
        cv2.imwrite(str(tmp / "preview.png"), contact_sheet(preview)[:, :, ::-1])
        write_model(tmp / "sparse" / "0", raw_images)
        meta = {
            "name": f"room_{cfg.layout}_s{cfg.seed}",
            "generator": {"name": "evaluation.rooms", "version": GENERATOR_VERSION},
            "layout": cfg.layout, "seed": cfg.seed, "config": asdict(cfg),
            "room": room.summary(),
            "camera": {"model": "PINHOLE", "width": cfg.width, "height": cfg.height,
                       "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]},
            "render": {"engine": "open3d.t.geometry.RaycastingScene",
                       "shading": "albedo * (ambient + sum_l P_l max(0, n.l) / (1 + d_l^2) * visible_l)"
                                  ", 8-bit sRGB (gamma 2.2), Gaussian sensor noise",
                       "simulated": ["procedural albedo", "ambient + Lambert point lights",
                                     "hard ray-cast shadows" if cfg.shadows else "no shadows",
                                     f"{cfg.supersample}x{cfg.supersample} supersampling",
                                     "sensor noise"],
                       "not_simulated": ["global illumination", "reflections", "specularity",
                                         "motion blur", "lens distortion", "exposure changes"]},
            "gt": {"mesh": "gt/mesh.ply", "triangle_material": "gt/triangle_material.npy",
                   "depth": "gt/depth/<stem>.npy: z-depth, metres, exact at pixel centres",
                   "normal": "gt/normal/<stem>.npy: camera frame, facing the camera"},
            "priors": {"simulated": True,
                       "method": "GT + simulated monocular errors: depth = s * warp(blur(gt)) * "
                                 "(1 + noise) + b; normals = blur + smooth tilt + noise",
                       "config": cfg.priors.to_dict(), "per_image": per_image},
        }
        (tmp / "scene.json").write_text(json.dumps(meta, indent=1))
        t0 = time.perf_counter()
        sfm_info = _run_sfm(tmp, cfg.keep_sfm_cache) if cfg.sfm else {"run": False,
                                                                      "reason": "sfm=False"}
        seconds["sfm"] = time.perf_counter() - t0
        seconds["total"] = time.perf_counter() - t_start
        report = {"scene": str(out), "seconds": seconds, "sfm": sfm_info,
                  "n_views": cfg.n_views, "size": [cfg.width, cfg.height]}
        (tmp / "make_room_report.json").write_text(json.dumps(report, indent=1, default=str))
        for name in ("make_room_report.json", "sfm_report.json"):  # paths as they will be
            f = tmp / name
            if f.is_file():
                f.write_text(f.read_text().replace(str(tmp), str(out)))
    log.info("make-room %s: %d views in %.1f s (render %.1f s, sfm %.1f s)", out, cfg.n_views,
             seconds["total"], seconds["render_and_priors"], seconds["sfm"])
    return out
