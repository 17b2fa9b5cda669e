"""`splat mesh`: fuse a finished run's Gaussians into a mesh again, with other TSDF settings.

One stage, one entry: ``run(cfg, run_dir, out=None, *, overwrite=False) -> Path`` (default OUT:
``RUN/mesh_<depth>_w<weight threshold>.ply``). Meshing happens after training, so trying another
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


def default_out(run_dir: Path, tsdf: TSDFConfig) -> Path:
    return run_dir / f"mesh_{tsdf.depth}_w{tsdf.weight_threshold:g}.ply"


def fuse_cameras(params, cameras: list, sh_degree: int, tsdf, *, backend: str = "auto",
                 background=(0.0, 0.0, 0.0), device="cpu", progress: bool = False):
    """Render each scene camera (``geocues.scene.Camera``: K, R, t, size) and fuse the rendered depth
    where alpha > 0.5 — the median or the expected depth, ``tsdf.depth`` — with the colours into a
    TSDF; return the cleaned mesh."""
    import numpy as np
    import torch

    from splat.camera import Camera
    from splat.mesh import clean_mesh, fuse_views
    from splat.rasterize import render

    bg = torch.tensor(background, dtype=torch.float32, device=device)
    key = "median_depth" if tsdf.depth == "median" else "depth"

    @torch.no_grad()
    def gen():
        for cam in cameras:
            out = render(params, Camera.from_scene_camera(cam, device), sh_degree=sh_degree, backend=backend,
                         background=bg)
            depth = torch.where(out["alpha"] > 0.5, out[key], torch.zeros_like(out[key]))
            yield (depth.cpu().numpy().astype(np.float32), out["rgb"].clamp(0, 1).cpu().numpy().astype(np.float32),
                   cam.K, cam.world_to_camera)
    return clean_mesh(fuse_views(gen(), tsdf, progress=progress), tsdf)


def run(cfg: MeshRunConfig, run_dir: str | Path, out: str | Path | None = None, *,
        overwrite: bool = False) -> Path:
    """Fuse ``run_dir``'s Gaussians with ``cfg.tsdf``; write the mesh to ``out``; return its path."""
    from splat.mesh import write_mesh
    from splat.render_run import load_run

    cfg.validate()
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else default_out(run_dir, cfg.tsdf)
    if out.suffix.lower() != ".ply":
        raise ValueError(f"the mesh is written as PLY: name a .ply file, got {out}")
    check_output_file(out, overwrite)
    scene, params, train_cfg = load_run(run_dir, cfg.scene)
    idx = list(scene.train_indices) if cfg.views == "train" else list(range(len(scene.cameras)))
    cams = [scene.cameras[k] for k in idx[::cfg.mesh_every]]
    log.info("splat mesh: %d views of %s, %s", len(cams), run_dir, asdict(cfg.tsdf))
    mesh = fuse_cameras(params, cams, train_cfg.get("sh_degree", 3), cfg.tsdf,
                        background=tuple(train_cfg.get("background", (0.0, 0.0, 0.0))), progress=True)
    return write_mesh(mesh, out)  # atomic
