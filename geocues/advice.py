"""What to run next on a scene: the commands `geocues info` prints under "next", from what the scene
holds (README, "Your own photos"). The first step that the scene still lacks comes first — a pinhole
camera, a metric unit, SfM points — then the chain to a mesh: with depth priors the paper's recipe,
without them `geocues mvs` and its recipe, or the prior-free run."""

from __future__ import annotations

import os
import shlex
from pathlib import Path

from geocues.scene import ARBITRARY_SCALE, Scene


FEW_VIEWS = 10  # Gaussian splatting of a room fits each surface to the views that see it


def few_views_warning(n_views: int, what: str = "images") -> str | None:
    """A sentence when ``n_views`` are too few to reconstruct a room, else None."""
    if n_views >= FEW_VIEWS:
        return None
    return (f"only {n_views} {what}: Gaussian splatting fits every surface to the views that see it, and with "
            f"under {FEW_VIEWS} the renders fit their photos while the geometry between them stays unconstrained; "
            "a room wants dozens of overlapping photos")


REGISTERED_SHARE = 0.8  # under this share of the photos in the model, every later step says so


def sfm_registered(metadata: dict) -> dict | None:
    """scene.json's ``sfm_registered`` ({"images": N, "photos": M}, written by `geocues sfm --mode map`, kept
    by undistort, rescale and mvs) when it holds two integers, else None (absent, or edited by hand)."""
    reg = metadata.get("sfm_registered") if isinstance(metadata, dict) else None
    if isinstance(reg, dict) and all(isinstance(reg.get(k), int) and not isinstance(reg.get(k), bool)
                                     for k in ("images", "photos")):
        return reg
    return None


def registration_warning(metadata: dict) -> str | None:
    """A sentence when `geocues sfm` put under :data:`REGISTERED_SHARE` of the photos it was given into the
    model (:func:`sfm_registered`), else None: the scene holds only those photos, so the reconstruction
    covers what they see, and a GT of the whole room counts the rest as missing."""
    reg = sfm_registered(metadata)
    if reg is None or reg["photos"] <= 0 or reg["images"] >= REGISTERED_SHARE * reg["photos"]:
        return None
    return (f"`geocues sfm` put only {reg['images']} of the {reg['photos']} photos into the model (scene.json "
            f"sfm_registered): the scene holds those, the reconstruction covers what they see, and scored against a "
            "GT of the whole room the rest counts as missing; more overlap between neighbouring photos (or texture "
            "in the room) brings more in")


FOV_RANGE_DEG = (10.0, 150.0)  # horizontal fields of view a room's photos can have (phones ~65, fisheye ~120)


def fov_warning(scene: Scene) -> str | None:
    """A sentence when a camera's horizontal field of view is outside :data:`FOV_RANGE_DEG` (a focal in
    the wrong unit or for another image size: fx 1e6 or 1 on 320-px images trained to an empty mesh)."""
    import math

    odd = []
    for cam in scene.cameras:
        fov = math.degrees(2 * math.atan(cam.width / (2 * cam.K[0, 0])))
        if not FOV_RANGE_DEG[0] <= fov <= FOV_RANGE_DEG[1]:
            odd.append((cam.name, fov, cam.K[0, 0], cam.width))
    if not odd:
        return None
    name, fov, fx, width = odd[0]
    return (f"{len(odd)} camera(s) have a horizontal field of view outside {FOV_RANGE_DEG[0]:g}-{FOV_RANGE_DEG[1]:g} "
            f"degrees ({name}: {fov:.3g} deg, fx {fx:.4g} px for {width} px wide): is the focal length in "
            "pixels of these images (not millimetres, not another resolution's)?")


def normal_axes_warning(scene: Scene) -> str | None:
    """A sentence when most of the scene's normal-prior pixels face away from their camera, else None.
    OpenGL camera axes are one cause and have a setting; negated, world-frame or [0, 1]-valued normals
    give the same symptom and have none (setting opengl for them hid the warning and kept them wrong)."""
    away = scene.normals_facing_away()
    if away is None or away <= 0.5:
        return None
    where = scene.root / "scene.json"
    if scene.normal_axes == "opengl":
        return (f"{100 * away:.0f}% of the normal-prior pixels face away from the camera although {where} says "
                "normal_axes opengl: the files hold normals in another convention (negated, in the world frame, "
                "or in [0, 1] instead of [-1, 1]); convert them to camera-frame normals facing the camera")
    return (f"{100 * away:.0f}% of the normal-prior pixels face away from the camera (OpenCV camera axes: x "
            "right, y down, z forward; visible surfaces face the camera). With OpenGL camera axes (y up, z back) "
            f"set {{\"priors\": {{\"normal_axes\": \"opengl\"}}}} in {where}; negated, world-frame or [0, 1]-valued "
            "normals look the same and have no setting: convert those files")


def _sibling(root: Path, suffix: str) -> str:
    """ROOT_suffix beside ``root`` (in the working folder when root's folder is not writable, e.g. a
    shared dataset), quoted for a shell."""
    parent = root.parent if os.access(root.parent, os.W_OK) else Path()
    return shlex.quote(str(parent / f"{root.name}_{suffix}"))


def photos_only_summary(root: Path) -> list[str] | None:
    """What `geocues info` prints for a folder of photos without a camera model (the first step of
    README's "Your own photos"), or None when ``root`` is not one."""
    from geocues.colmap_io import find_model_dir
    from geocues.photos import list_images

    root = Path(root)
    images = root / "images"
    if not images.is_dir() or (root / "transforms.json").is_file():
        return None
    try:
        find_model_dir(root)
        return None  # a model: the scene summary
    except (FileNotFoundError, ValueError):
        pass
    names = list_images(images)
    if not names or (root / "cache" / "sfm").is_dir():  # an unfinished sfm: its error says what to do
        return None
    if (root / "sparse").is_dir() and any((root / "sparse").glob("*/cameras.*")):
        return None  # a model in sparse/1 (COLMAP's mapper leaves them there): the error says to move it
    out = _sibling(root, "map")
    return [f"scene      {root}",
            f"photos     {len(names)} in {images} (no camera model yet: `geocues sfm` estimates poses, "
            "intrinsics and points from the photos alone)",
            f"next       # poses, intrinsics and points (README, \"Your own photos\")\n{'':<11}"
            f"geocues sfm {shlex.quote(str(root))} -o {out}",
            f"{'':<11}# then follow its advice\n{'':<11}geocues info {out}"]


def next_steps(scene: Scene, not_metric: bool) -> list[tuple[str, str]]:
    """(command, why) pairs, in the order to run them. ``not_metric``: the scene does not look metric
    (:func:`geocues.rescale.metric_warning` said so)."""
    from geocues.rescale import priors_in_scene_unit

    root = Path(scene.root)
    q = shlex.quote(str(root))
    if scene.distorted_models:
        out = _sibling(root, "pinhole")
        return [(f"geocues undistort {q} -o {out}", "the other commands read pinhole cameras only"),
                (f"geocues info {out}", "then follow its advice")]
    if not_metric and ("rescaled" not in scene.metadata or scene.metadata.get("scale") == ARBITRARY_SCALE):
        # a rescaled copy's warning names its original (unless it was mapped again since)
        out = _sibling(root, "metric")
        metric_priors = scene.has_depth_priors and scene.depth_kind == "depth" and not priors_in_scene_unit(scene)
        how = "--from-priors" if metric_priors else "--median-depth 2"
        return [(f"geocues rescale {q} -o {out} {how}",
                 "every length here is in metres" + ("" if how == "--from-priors" else
                                                     " (2 m: a guess of how far the photos were taken from the walls)")),
                (f"geocues info {out}", "then follow its advice")]
    if len(scene.points) == 0:
        out = _sibling(root, "sfm")
        return [(f"geocues sfm {q} -o {out}", "the cues start from SfM points"),
                (f"geocues info {out}", "then follow its advice")]
    cues, run = _sibling(root, "cues"), _sibling(root, "run")
    if scene.has_depth_priors and priors_in_scene_unit(scene):
        return [(f"geocues extract {q} -o {cues} --preset mvs", "cues for the recipe of `geocues mvs` depth"),
                (f"splat train {q} -c {cues} -o {run} --preset mvs --iters 3000 --downscale 2", "train, then a mesh"),
                (f"splat view {run}", "look at it (or splat render)")]
    if scene.has_depth_priors:
        return [(f"geocues extract {q} -o {cues}", "lines, SfM and plane-like cues (paper §4.1); for a room with a "
                 "level floor and ceiling and vertical walls, `--preset room` here and in splat train gave the "
                 "best meshes measured"),
                (f"splat train {q} -c {cues} -o {run} --iters 3000 --downscale 2",
                 "IndoorGS with the depth and normal priors (§4.2-4.3), then a mesh"),
                (f"splat view {run}", "look at it (or splat render)")]
    mvs = _sibling(root, "mvs")
    return [(f"geocues mvs {q} -o {mvs}", "no depth priors: depth from the photos themselves (the best mesh "
             "measured without priors; or bring priors of your own in priors/)"),
            (f"geocues extract {mvs} -o {cues} --preset mvs", "cues for that recipe"),
            (f"splat train {mvs} -c {cues} -o {run} --preset mvs --iters 3000 --downscale 2", "train, then a mesh"),
            (f"splat view {run}", "look at it (or splat render)")]
