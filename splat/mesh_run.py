"""`splat mesh`: fuse a finished run's Gaussians into a mesh again, with other TSDF settings.

One stage, one entry: ``run(cfg, run_dir, out=None, *, overwrite=False) -> Path`` (default OUT:
``RUN/mesh_<depth>_w<weight threshold>[_t<smoothing steps>].ply``). Meshing happens after training, so trying another
voxel size, weight threshold or rendered depth (``--tsdf.depth median|expected``) needs no new
training: the run's Gaussians (``RUN/point_cloud.ply``) are rendered from the run's training views
(or all views) at the run's resolution and fused as `splat train` does at its end.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

from geocues.atomic import check_output_file
from splat.mesh import TSDFConfig
from splat.tsdf_config import check_tsdf_resources

log = logging.getLogger(__name__)


@dataclass
class MeshRunConfig:
    """Options of `splat mesh`."""

    views: str = "train"
    """fuse the run's "train" views (as `splat train` does) or "all" views (test views too)."""
    mesh_every: int = 1
    """use every n-th of those views."""
    scene: str | None = None
    """the scene folder (default: the one the run was trained on, from RUN/report.json)."""
    tsdf: TSDFConfig = field(default_factory=TSDFConfig)

    def validate(self) -> None:
        if self.views not in ("train", "all"):
            raise ValueError(f"--views must be train or all, got {self.views!r}")
        if self.mesh_every < 1:
            raise ValueError(f"--mesh-every must be >= 1, got {self.mesh_every}")
        self.tsdf.validate()
        if self.tsdf.consistency_neighbours < 1:
            raise ValueError(f"--tsdf.consistency-neighbours must be >= 1, got {self.tsdf.consistency_neighbours}")


# TSDF options that change the surface, by their short tag in mesh file names (the remesh tables' names)
_TAGS = {"voxel_size": "v", "consistent_views": "c", "consistency_neighbours": "n", "max_depth_spread": "s",
         "sdf_trunc": "tr", "depth_max": "d", "min_component_diag": "m", "consistency_px": "px",
         "consistency_rel_depth": "rd"}


_CONSISTENCY = ("consistency_neighbours", "consistency_px", "consistency_rel_depth")  # act with consistent_views


def default_out(run_dir: Path, tsdf: TSDFConfig, views: str = "train", mesh_every: int = 1) -> Path:
    """RUN/mesh_DEPTH_wTHRESHOLD[...]: every surface-changing option that differs from the default
    tagged in the name (``_v0.05`` for --tsdf.voxel-size 0.05, ``_c2``, ``_s0.02``, ``_t30`` for the
    Taubin steps, ``_all`` for --views all, ``_e3`` for --mesh-every 3), so two different meshes never
    share a file name; the consistency check's settings only while it is on (else they change nothing)."""
    base = TSDFConfig()
    tags = "".join(f"_{tag}{getattr(tsdf, name):g}" for name, tag in _TAGS.items()
                   if getattr(tsdf, name) != getattr(base, name) and getattr(tsdf, name) is not None
                   and (tsdf.consistent_views is not None or name not in _CONSISTENCY))
    smooth = f"_t{tsdf.smooth_iters}" if tsdf.smooth_iters else ""
    chosen = ("_all" if views == "all" else "") + (f"_e{mesh_every}" if mesh_every != 1 else "")
    return run_dir / f"mesh_{tsdf.depth}_w{tsdf.weight_threshold:g}{tags}{smooth}{chosen}.ply"


def fuse_cameras(params, cameras: list, sh_degree: int, tsdf, *, backend: str = "auto",
                 background=(0.0, 0.0, 0.0), device="cpu", progress: bool = False):
    """Render each scene camera (``geocues.scene.Camera``: K, R, t, size) and fuse the rendered depth
    where alpha > 0.5 — the median or the expected depth, ``tsdf.depth`` — with the colours into a
    TSDF; return the cleaned mesh. With ``tsdf.max_depth_spread`` a pixel whose expected and median
    depths differ by more than that fraction of the depth is left out. With ``tsdf.consistent_views``
    every view is rendered first and a depth is fused only where enough neighbouring renders agree
    (:func:`consistent_depths`)."""
    import numpy as np
    import torch

    from splat.camera import Camera
    from splat.mesh import clean_mesh, fuse_views
    from splat.rasterize import render

    bg = torch.tensor(background, dtype=torch.float32, device=device)
    key = "median_depth" if tsdf.depth == "median" else "depth"

    @torch.no_grad()
    def rendered(cam):
        out = render(params, Camera.from_scene_camera(cam, device), sh_degree=sh_degree, backend=backend,
                     background=bg)
        keep = out["alpha"] > 0.5
        if tsdf.max_depth_spread is not None:  # mixed pixels: the blend and the median part ways
            keep &= (out["depth"] - out["median_depth"]).abs() <= tsdf.max_depth_spread * out["depth"]
        depth = torch.where(keep, out[key], torch.zeros_like(out[key]))
        return (depth.cpu().numpy().astype(np.float32), out["rgb"].clamp(0, 1).cpu().numpy().astype(np.float32))

    if tsdf.consistent_views is None:
        views = ((*rendered(cam), cam.K, cam.world_to_camera) for cam in cameras)
    else:
        renders = [rendered(cam) for cam in cameras]
        depths = consistent_depths(cameras, [d for d, _ in renders], tsdf)
        views = [(d, rgb, cam.K, cam.world_to_camera) for d, (_, rgb), cam in zip(depths, renders, cameras)]
    return clean_mesh(fuse_views(views, tsdf, progress=progress), tsdf)


def consistent_depths(cameras: list, depths: list, tsdf) -> list:
    """``depths`` (z-depth [H, W] of each of ``cameras``, 0 = none) with 0 where fewer than
    ``tsdf.consistent_views`` of the ``tsdf.consistency_neighbours`` neighbouring views agree: the
    forward-backward check of `geocues mvs` (geocues.mvs.consistency_filter), neighbours chosen as
    it chooses them at the view's median depth."""
    import numpy as np

    from geocues.mvs import MvsConfig, consistency_filter, select_neighbours

    cfg = MvsConfig(n_neighbours=tsdf.consistency_neighbours, min_consistent=tsdf.consistent_views,
                    max_reproj_px=tsdf.consistency_px, max_rel_depth=tsdf.consistency_rel_depth)
    neighbours = {}
    for i, d in enumerate(depths):
        valid = d[d > 0]
        neighbours[i] = select_neighbours(cameras, i, cfg, float(np.median(valid))) if valid.size else []
    kept = consistency_filter(cameras, dict(enumerate(depths)), neighbours, cfg)
    before, after = sum(int((d > 0).sum()) for d in depths), sum(int((d > 0).sum()) for d in kept.values())
    log.info("TSDF: %d of %d rendered depths (%.1f %%) agree with >= %d of %d neighbouring views",
             after, before, 100.0 * after / max(before, 1), tsdf.consistent_views, tsdf.consistency_neighbours)
    return [kept[i] for i in range(len(depths))]


def run(cfg: MeshRunConfig, run_dir: str | Path, out: str | Path | None = None, *,
        overwrite: bool = False) -> Path:
    """Fuse ``run_dir``'s Gaussians with ``cfg.tsdf``; write the mesh to ``out``; return its path."""
    from splat.mesh import write_mesh
    from splat.render_run import load_run

    cfg.validate()
    check_tsdf_resources(cfg.tsdf)  # Open3D's traceback after the rendering otherwise
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else default_out(run_dir, cfg.tsdf, cfg.views, cfg.mesh_every)
    if out.suffix.lower() != ".ply":
        raise ValueError(f"the mesh is written as PLY: name a .ply file, got {out}")
    own = {run_dir / n for n in ("point_cloud.ply", "input.ply", "mesh.ply")}
    if out.resolve() in {p.resolve() for p in own} or run_dir.resolve() / "point_cloud" in out.resolve().parents \
            or run_dir.resolve() / "checkpoints" in out.resolve().parents:
        raise ValueError(f"{out} is one of the run's own files: name another -o (the default names the mesh "
                         "after its settings)")
    check_output_file(out, overwrite)
    scene, params, train_cfg = load_run(run_dir, cfg.scene)
    idx = list(scene.train_indices) if cfg.views == "train" else list(range(len(scene.cameras)))
    cams = [scene.cameras[k] for k in idx[::cfg.mesh_every]]
    log.info("splat mesh: %d views of %s, %s", len(cams), run_dir, asdict(cfg.tsdf))
    mesh = fuse_cameras(params, cams, train_cfg.get("sh_degree", 3), cfg.tsdf,
                        background=tuple(train_cfg.get("background", (0.0, 0.0, 0.0))), progress=True)
    return write_mesh(mesh, out)  # atomic
