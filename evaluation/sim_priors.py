"""SIMULATED monocular priors for a real scene that ships exact depth (e.g. ICL-NUIM's ``depth/``).

`evaluate simulate-priors SCENE -o OUT` writes a new scene folder OUT: SCENE's images, model and
ground truth linked (not copied), and ``priors/depth`` and ``priors/normal`` made from the exact
depth and the GT mesh's normals with the same simulated monocular errors as the benchmark rooms
(:mod:`evaluation.rooms.priors`: per-image scale and shift, edge blur, smooth warp, noise; blurred,
tilted, noisy normals). OUT/scene.json says ``"priors": {"simulated": true}`` with every parameter,
so no table can mistake them for priors a network produced. They are for measuring the rows of
`splat ablate` that need priors on a real scene; never a training signal of a result called
prior-free.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from evaluation.rooms.priors import PriorConfig, simulate_depth_prior, simulate_normal_prior

log = logging.getLogger("indoorgs")


@dataclass
class SimPriorsConfig:
    """Where the exact depth and the GT surface come from, and the simulated errors."""

    seed: int = 0
    """Seed of the per-image error draws (one generator per image, spawned from it)."""
    gt_depth: Path | None = None
    """Folder of exact depth maps <stem>.npy (metres) or <stem>.png (default: SCENE/gt/depth)."""
    gt_depth_png_scale: float = 1000.0
    """PNG depth units per metre (ICL-NUIM, TUM, ScanNet: 1000)."""
    gt_mesh: Path | None = None
    """GT mesh whose ray-cast normals become the normal priors (default: SCENE/gt/mesh.ply)."""
    priors: PriorConfig = field(default_factory=PriorConfig)
    """The simulated errors (as `evaluate make-room`)."""


def gt_normals_camera(mesh_scene, cam, dirs_cam: np.ndarray) -> np.ndarray:
    """Camera-frame unit normals [H, W, 3] of the GT surface seen by ``cam`` (facing the camera;
    0 where the ray misses), ray-cast along ``dirs_cam`` = ``cam.pixel_rays()``."""
    import open3d as o3d

    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    origin = -R.T @ t
    dirs_world = dirs_cam @ R  # rows: R^T d
    rays = np.concatenate([np.broadcast_to(origin, dirs_world.shape), dirs_world], -1).astype(np.float32)
    hit = mesh_scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6)))
    normal_world = hit["primitive_normals"].numpy().reshape(cam.height, cam.width, 3).astype(np.float64)
    missed = ~np.isfinite(hit["t_hit"].numpy().reshape(cam.height, cam.width))
    n = normal_world @ R.T  # rows: R n
    n = np.where((np.einsum("hwc,hwc->hw", n, dirs_cam) > 0)[..., None], -n, n)
    n[missed] = 0.0
    return n.astype(np.float32)


def simulate_scene_priors(scene_dir: str | Path, out: str | Path, cfg: SimPriorsConfig = SimPriorsConfig(),
                          overwrite: bool = False) -> Path:
    """Write OUT: SCENE linked, plus simulated ``priors/`` (see the module docstring); return OUT."""
    import open3d as o3d
    from tqdm import tqdm

    from geocues.atomic import atomic_dir, check_output_dir, check_replaceable
    from geocues.scene import Scene, gt_mesh_file
    from geocues.sfm import link_scene
    from splat.floor import find_gt_depth_dir, load_gt_depth

    scene_dir, out = Path(scene_dir).resolve(), Path(out)
    cfg.priors.validate()
    check_replaceable(out, "scene.json", "a scene `evaluate simulate-priors` wrote",
                      {"scene": scene_dir, "GT depth folder": cfg.gt_depth}, key="priors.simulated")
    if out.exists() and not overwrite:
        raise ValueError(f"{out} already exists; pass --overwrite to replace it")
    check_output_dir(out)
    scene = Scene.load(scene_dir, check_priors=False)
    depth_dir = find_gt_depth_dir(scene_dir, cfg.gt_depth)
    if depth_dir is None:
        raise FileNotFoundError(f"{scene_dir} has no gt/depth folder and no --gt-depth was given: "
                                "the priors are simulated from exact depth")
    mesh_path = Path(cfg.gt_mesh) if cfg.gt_mesh is not None else (gt_mesh_file(scene_dir) or scene_dir / "gt" / "mesh.ply")
    if not mesh_path.is_file():
        raise FileNotFoundError(f"no GT mesh at {mesh_path} (give --gt-mesh): the normal priors are its normals")
    mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.io.read_triangle_mesh(str(mesh_path)))
    if mesh.triangle.indices.shape[0] == 0:
        raise ValueError(f"{mesh_path} has no triangles")
    mesh_scene = o3d.t.geometry.RaycastingScene()
    mesh_scene.add_triangles(mesh)
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(len(scene.cameras))]
    per_image = {}
    with atomic_dir(out) as tmp:
        link_scene(scene_dir, tmp, ("images", "sparse", "gt"))  # a root reference_mesh.ply, a nerfstudio scene too
        (tmp / "scene.json").unlink(missing_ok=True)  # written below, with the priors' provenance
        (tmp / "priors" / "depth").mkdir(parents=True)
        (tmp / "priors" / "normal").mkdir(parents=True)
        for k, cam in enumerate(tqdm(scene.cameras, desc="simulate priors", unit="view")):
            depth = load_gt_depth(depth_dir, cam.stem, (cam.height, cam.width), cfg.gt_depth_png_scale)
            dirs = cam.pixel_rays()
            normal = gt_normals_camera(mesh_scene, cam, dirs)
            dprior, dpar = simulate_depth_prior(depth, rngs[k], cfg.priors)
            nprior, npar = simulate_normal_prior(normal, dirs, rngs[k], cfg.priors)
            np.save(tmp / "priors" / "depth" / f"{cam.stem}.npy", dprior)
            np.save(tmp / "priors" / "normal" / f"{cam.stem}.npy", nprior)
            per_image[cam.stem] = {"depth": dpar, "normal": npar}
        meta = json.loads((scene_dir / "scene.json").read_text()) if (scene_dir / "scene.json").is_file() else {}
        meta["priors"] = {"simulated": True, "from_scene": str(scene_dir), "gt_depth": str(Path(depth_dir).resolve()),
                          "gt_depth_png_scale": cfg.gt_depth_png_scale,  # the floor of `splat ablate` reads it
                          "gt_mesh": str(mesh_path.resolve()), "seed": cfg.seed,
                          "method": "exact depth + simulated monocular errors: depth = s * warp(blur(gt)) * "
                                    "(1 + noise) + b; normals = GT mesh normals + blur + smooth tilt + noise",
                          "config": cfg.priors.to_dict(), "per_image": per_image}
        if isinstance(meta.get("config"), dict) and "priors" in meta["config"]:  # a benchmark room's own
            meta["config"]["priors"] = cfg.priors.to_dict()  # settings: the priors here are these ones
        (tmp / "scene.json").write_text(json.dumps(meta, indent=1))
    log.info("simulate-priors %s: %d views from %s and %s (config %s)", out, len(scene.cameras), depth_dir,
             mesh_path, asdict(cfg.priors))
    return out
