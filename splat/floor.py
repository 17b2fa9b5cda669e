"""The `floor` row: a TSDF of the exact GT depth of the training views (DESIGN.md, "evaluation").

The same views, resolution, TSDF voxel, truncation and cleaning as `splat train`'s mesh, so the
result is the best mesh this pipeline could make from those views; every accuracy figure is read
against it. GT depth comes from the benchmark rooms' ``SCENE/gt/depth/<stem>.npy`` (metres) or
any folder of ``<stem>.npy`` / ``<stem>.png`` maps (PNG values divided by ``png_scale``: 1000 for
millimetres, as ICL-NUIM ships them).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from geocues.scene import Scene
from splat.mesh import TSDFConfig, clean_mesh, fuse_views, write_mesh

log = logging.getLogger(__name__)


def find_gt_depth_dir(scene_dir: str | Path, gt_depth: str | Path | None = None) -> Path | None:
    """``gt_depth`` if given (it must exist), else ``SCENE/gt/depth`` if present, else None."""
    if gt_depth is not None:
        path = Path(gt_depth)
        if not path.is_dir():
            raise FileNotFoundError(f"no GT depth folder at {path}")
        return path
    path = Path(scene_dir) / "gt" / "depth"
    return path if path.is_dir() else None


def recorded_gt_depth(scene_dir: str | Path) -> tuple[Path, float] | None:
    """The exact depth a derived scene records in its scene.json (``evaluate simulate-priors`` writes
    ``priors.gt_depth`` and its PNG scale) when it is still there, with that scale; else None."""
    import json

    try:
        priors = json.loads((Path(scene_dir) / "scene.json").read_text()).get("priors") or {}
    except (OSError, ValueError, AttributeError):
        return None
    path = priors.get("gt_depth") if isinstance(priors, dict) else None
    if not isinstance(path, str) or not Path(path).is_dir():
        return None
    return Path(path), float(priors.get("gt_depth_png_scale", 1000.0))


def load_gt_depth(folder: Path, stem: str, shape: tuple[int, int], png_scale: float) -> np.ndarray:
    """Exact depth [H, W] float32 metres of image ``stem``, resized (nearest) to ``shape``."""
    import cv2

    npy, png = folder / f"{stem}.npy", folder / f"{stem}.png"
    if npy.is_file():
        depth = np.load(npy).astype(np.float32)
    elif png.is_file():
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ValueError(f"could not read the GT depth PNG {png}")
        depth = raw.astype(np.float32) / float(png_scale)
    else:
        raise FileNotFoundError(f"no GT depth for image {stem} in {folder} (expected {npy.name} or {png.name})")
    if depth.ndim != 2:
        raise ValueError(f"GT depth {folder / stem}: expected an [H, W] map, got shape {depth.shape}")
    if depth.shape != shape:
        depth = cv2.resize(depth, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)


DEPTH_RATIO_OK = (0.8, 1.25)
"""GT depth over the SfM points' depth at their pixels, median: outside this a PNG scale is wrong (ICL-NUIM's
TUM-format PNGs are 1/5000 m, the Open3D copy's 1/1000 m), not the points' noise (ICL: 1.00)."""


def depth_scale_warning(scene: Scene, folder: Path, png_scale: float, indices: list[int],
                        n_views: int = 10, min_samples: int = 20) -> str | None:
    """A sentence when the GT depth disagrees in scale with the scene's SfM points (median ratio of the GT
    depth at each point's pixel to the point's depth, over up to ``n_views`` views: the points of each
    view's tracks, else all in front); None when it agrees or too few points are seen."""
    visible = scene.points.visible_in
    ratios = []
    pngs = False
    for i in indices[:: max(1, len(indices) // n_views)][:n_views]:
        ids = visible.get(i)
        if ids is None or len(ids) == 0:  # no tracks (a nerfstudio scene's points): every point in front
            ids = np.arange(len(scene.points))
        cam = scene.cameras[i]
        uv, z = cam.project(scene.points.xyz[ids])
        front = (z > 0) & np.isfinite(uv).all(axis=1)
        px, z = np.floor(uv[front]).astype(np.int64), z[front]
        inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        depth = load_gt_depth(folder, cam.stem, (cam.height, cam.width), png_scale)
        d = depth[px[inside, 1], px[inside, 0]]
        ok = d > 0
        ratios.append(d[ok] / z[inside][ok])
        pngs = not (folder / f"{cam.stem}.npy").is_file()
    ratios = np.concatenate(ratios) if ratios else np.zeros(0)
    if len(ratios) < min_samples:
        return None
    r = float(np.median(ratios))
    if DEPTH_RATIO_OK[0] <= r <= DEPTH_RATIO_OK[1]:
        return None
    cause = (f"a wrong --gt-depth-png-scale ({png_scale:g} now, about {float(f'{png_scale * r:.2g}'):g} would match; ICL-NUIM's "
             "TUM-format PNGs are 5000 per metre) or " if pngs else "")
    return (f"the GT depth in {folder} is {r:.3g}x the depth of the scene's SfM points at their pixels (median of "
            f"{len(ratios)}): the floor row is fused at that scale. Is it {cause}a scene not in its GT's unit?")


def fuse_floor(scene_dir: str | Path, out_mesh: str | Path, *, gt_depth: str | Path | None = None,
               png_scale: float = 1000.0, downscale: float = 1.0, test_every: int = 8,
               mesh_every: int = 1, tsdf: TSDFConfig | None = None) -> Path:
    """Fuse the GT depth of every ``mesh_every``-th training view (as `splat train` fuses its
    rendered depth), clean the mesh and write it to ``out_mesh``. Returns the mesh path."""
    folder = find_gt_depth_dir(scene_dir, gt_depth)
    if folder is None:
        raise FileNotFoundError(f"the scene {scene_dir} has no gt/depth folder; pass the exact depth "
                                "maps' folder (--gt-depth DIR)")
    scene = Scene.load(scene_dir, downscale=downscale, test_every=test_every, check_priors=False)
    indices = scene.train_indices[::max(mesh_every, 1)]

    def views():
        for i in indices:
            cam = scene.cameras[i]
            depth = load_gt_depth(folder, cam.stem, (cam.height, cam.width), png_scale)
            yield depth, scene.load_image(i), cam.K, cam.world_to_camera

    if odd := depth_scale_warning(scene, folder, png_scale, indices):
        log.warning("%s", odd)
    tsdf = tsdf or TSDFConfig()
    log.info("floor: fusing the GT depth of %d training views from %s", len(indices), folder)
    return write_mesh(clean_mesh(fuse_views(views(), tsdf), tsdf), out_mesh)
