"""A training run in the folder layout of the 3DGS reference code (graphdeco-inria/gaussian-splatting),
so that SIBR's viewer and the reference ``render.py`` / ``metrics.py`` open it as one of theirs:

    RUN/point_cloud/iteration_<N>/point_cloud.ply   the Gaussians, exact reference layout (62 floats)
    RUN/point_cloud/iteration_<N>/cue_type.npy      this project's Gaussian types (readers ignore it)
    RUN/cfg_args                                    repr of the argparse Namespace of ModelParams
    RUN/cameras.json                                the reference ``camera_to_JSON`` of every camera
                                                    (refined where the run refined them), with the
                                                    principal point as extra keys ``cx``, ``cy``
    RUN/input.ply                                   the scene's SfM points (the reference copies its
                                                    points3D.ply there; SIBR's proxy mesh)

``cfg_args`` always says ``sh_degree=3``: the PLY is padded to degree 3 and the reference loader
asserts that its ``f_rest`` count matches that degree. What the reference's format cannot say is
warned about when written: a scene they cannot load, an off-centre principal point (its readers project through the image
centre), held-out views other than every 8th (its ``llffhold``), a background neither white nor
black. Every file is written atomically.
"""

from __future__ import annotations

import json
import logging
from argparse import Namespace
from pathlib import Path

import numpy as np
from torch import Tensor

from geocues.atomic import atomic_path
from geocues.scene import Scene
from splat.gaussians import save_ply

log = logging.getLogger(__name__)


def model_path_of(run_dir: Path) -> Path:
    """Where the run will live once published: a staging folder ``OUT.partial`` becomes ``OUT``."""
    run_dir = Path(run_dir).resolve()
    return run_dir.with_name(run_dir.name[: -len(".partial")]) if run_dir.name.endswith(".partial") else run_dir


def reference_cfg_args(scene: Scene, cfg_dict: dict, model_path: Path) -> Namespace:
    """The reference's ModelParams as its train.py writes them (field order of current upstream
    ``arguments/__init__.py``; older versions lack ``depths`` and ``train_test_exp`` and ignore them).

    ``resolution``: the reference's -1 (its own rule: at most 1600 px wide) unless this run used
    one of its integer factors 1, 2, 4, 8; ``eval``: whether held-out views exist (the reference
    holds out every 8th image, ``llffhold``, as this project's default ``test_every``).
    """
    downscale = float(cfg_dict.get("downscale", 1.0))
    background = tuple(float(c) for c in cfg_dict.get("background", (0.0, 0.0, 0.0)))
    return Namespace(
        sh_degree=3,  # the PLY is padded to degree 3 whatever the training degree
        source_path=str(Path(scene.root).resolve()),
        model_path=str(model_path),
        images="images",
        depths="",
        resolution=int(downscale) if downscale in (1.0, 2.0, 4.0, 8.0) else -1,
        white_background=background == (1.0, 1.0, 1.0),
        train_test_exp=False,
        data_device="cuda",
        eval=int(cfg_dict.get("test_every", 8)) > 0,
    )


def camera_to_json(index: int, cam, refined: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> dict:
    """One entry of the reference ``cameras.json`` (``utils/camera_utils.py::camera_to_JSON``):
    position and rotation are camera-to-world (rotation columns = camera axes in the world),
    ``img_name`` is the file name up to its first dot (as the reference's COLMAP reader),
    width/height/fx/fy in pixels of the photos' own size, as the reference writes them from the COLMAP
    model whatever its ``-r`` (SIBR and tools pairing the file with the photos read them so), not the
    training resolution. cam: a geocues.scene.Camera; refined: its (K, R, t) after the run's camera
    refinement, written instead of the scene's."""
    K, R, t = refined if refined is not None else (cam.K, cam.R, cam.t)
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    width, height = cam.source_size
    K = np.diag([width / cam.width, height / cam.height, 1.0]) @ np.asarray(K, np.float64)  # exact: pixel centres
    return {
        "id": index,
        "img_name": Path(cam.name).name.split(".")[0],
        "width": int(width),
        "height": int(height),
        "position": (-R.T @ t).tolist(),
        "rotation": [row.tolist() for row in R.T],
        "fy": float(K[1, 1]),
        "fx": float(K[0, 0]),
        "cx": float(K[0, 2]),  # not in the reference's format (its readers ignore it): `splat render --views`
        "cy": float(K[1, 2]),  # reads it, so that an off-centre principal point is kept
    }


def reference_limits(cams: list[dict], cfg_dict: dict, scene: Scene | None = None) -> list[str]:
    """What the reference tools will read differently from this run (sentences for a warning): a
    scene they cannot load from ``source_path``, an off-centre principal point, another held-out
    split than every 8th image, another background."""
    out = []
    model = Path(scene.model_dir) if scene is not None and scene.model_dir is not None else None
    if model is not None and model.suffix == ".json":
        out.append(f"the scene is a nerfstudio {model.name}: the reference render.py loads a COLMAP model from "
                   "cfg_args' source_path/sparse/0 (or a Blender transforms_train.json) and cannot load it")
    elif model is not None and model.resolve() != (Path(scene.root) / "sparse" / "0").resolve():
        out.append(f"the scene's COLMAP model is in {model}, where the reference render.py does not look "
                   "(source_path/sparse/0 of cfg_args)")
    off = max((max(abs(c["cx"] - c["width"] / 2), abs(c["cy"] - c["height"] / 2)) for c in cams), default=0.0)
    if off > 0.5:
        out.append(f"the principal point is up to {off:.1f} px off the image centre, where SIBR and the reference "
                   "render.py put it (cameras.json has no cx/cy in their format): their renders of this run are "
                   "shifted by as much; `splat render` reads the cx/cy this project adds")
    test_every = int(cfg_dict.get("test_every", 8))
    if test_every != 8:
        held = "no view" if test_every == 0 else f"every {test_every}th view"
        out.append(f"this run held out {held} (--test-every {test_every}); the reference render.py / "
                   "metrics.py hold out every 8th (llffhold): their test scores would include views this run "
                   "trained on")
    background = tuple(float(c) for c in cfg_dict.get("background", (0.0, 0.0, 0.0)))
    if background not in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)):
        out.append(f"the background {background} is neither black nor white, the only ones the reference "
                   "knows (cfg_args white_background=False): its renders show black behind thin areas")
    return out


def write_input_ply(path: Path, scene: Scene) -> Path | None:
    """The scene's SfM points as the reference's ``storePly`` writes them (x y z nx ny nz red green
    blue, normals 0): SIBR loads ``RUN/input.ply`` as its proxy mesh. None when the scene has none."""
    from plyfile import PlyData, PlyElement

    pts = scene.points
    if pts is None or len(pts.xyz) == 0:
        return None
    dtype = [(n, "f4") for n in ("x", "y", "z", "nx", "ny", "nz")] + [(n, "u1") for n in ("red", "green", "blue")]
    rows = np.zeros(len(pts.xyz), dtype)
    for k, n in enumerate("xyz"):
        rows[n] = pts.xyz[:, k]
    for k, n in enumerate(("red", "green", "blue")):
        rows[n] = pts.rgb[:, k]
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rows, "vertex")]).write(str(tmp))
    return path


def write_3dgs_run(run_dir: str | Path, params: dict[str, Tensor], cue_type: Tensor | None, scene: Scene,
                   cfg_dict: dict, iteration: int, refinement: str | Path | None = None) -> Path:
    """Write the reference 3DGS run files into ``run_dir`` (see the module docstring).

    params: the Gaussians (splat.gaussians contract); cue_type: [N] or None; scene: the trained
    scene (its cameras go to cameras.json, its root to ``source_path``); cfg_dict: the training
    config as a dict (``downscale``, ``background``, ``test_every`` are read); iteration: N of
    ``point_cloud/iteration_N``; refinement: the run's camera_refinement.npz (`--pose-opt`,
    `--focal-opt`), whose cameras the Gaussians were fitted to: cameras.json holds them (the
    training views' corrected poses, every view's refined focal), as `splat render` draws them.
    Returns the PLY path.
    """
    run_dir = Path(run_dir)
    if int(iteration) < 0:
        raise ValueError(f"iteration must be >= 0, got {iteration}")
    ply = save_ply(run_dir / "point_cloud" / f"iteration_{int(iteration)}" / "point_cloud.ply", params, cue_type)
    args = reference_cfg_args(scene, cfg_dict, model_path_of(run_dir))
    with atomic_path(run_dir / "cfg_args") as tmp:
        tmp.write_text(repr(args))
    if refinement is not None:
        from splat.camera_opt import load_refinement, refine_Rt

        corrections, focal = load_refinement(refinement)
        refined = [refine_Rt(c.K, c.R, c.t, corrections.get(c.name), focal) for c in scene.cameras]
    else:
        refined = [None] * len(scene.cameras)
    cams = [camera_to_json(i, cam, r) for i, (cam, r) in enumerate(zip(scene.cameras, refined))]
    with atomic_path(run_dir / "cameras.json") as tmp:
        tmp.write_text(json.dumps(cams, allow_nan=False))
    write_input_ply(run_dir / "input.ply", scene)
    for sentence in reference_limits(cams, cfg_dict, scene):
        log.warning("3DGS tools reading %s: %s", model_path_of(run_dir), sentence)
    log.info("wrote the 3DGS reference layout of %s (iteration %d, %d cameras)", run_dir, iteration, len(cams))
    return ply
