"""Metric scale: every threshold of this toolkit is in metres (a 2 cm plane tolerance, a 5 cm F-score,
voxels of 2 cm), but an images-only SfM has an arbitrary scale. This module measures how far a scene
is from metric and writes a rescaled copy (`geocues rescale`).

``scene_extent`` is the size of the scene in its own units (the 5th–95th percentile box of the SfM
points, or of the camera centres without points). A room measures 2–30 m and its photos look at
surfaces 0.5–5 m away; ``metric_warning`` says so when a scene is far outside 0.5–200 units, when its
views' median depth is outside 0.2–8 units (an images-only SfM normalised by COLMAP often spans a
plausible 10 units while every length is 3–6× a metre), or when ``geocues sfm --mode map`` marked
it (scene.json ``"scale": "arbitrary"``; ``geocues rescale`` removes the mark and records
``"rescaled"``, after which the user's unit stands: no warning sends them back to rescale). ``scale_from_priors``
estimates the factor from metric depth priors (a depth sensor, or a metric monocular network a user
brings): the median over views of median(prior depth at the SfM points) / median(SfM point depth),
robust to outliers and holes; ``--median-depth M`` guesses it from how far the photos were taken.
"""

from __future__ import annotations

import json
import logging
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geocues.atomic import atomic_dir, check_output_dir, check_replaceable
from geocues.colmap_io import find_model_dir, load_reconstruction
from geocues.nerfstudio_io import find_transforms, transforms_reconstruction
from geocues.scene import ARBITRARY_SCALE, Scene, rescale_hint
from geocues.sfm import link_scene

log = logging.getLogger(__name__)

ROOM_RANGE = (0.5, 200.0)  # plausible extents (metres) of an indoor capture, with a wide margin
DEPTH_RANGE = (0.2, 8.0)  # plausible median view depths (metres) of an indoor capture


def scene_extent(scene: Scene) -> float:
    """Largest side (scene units) of the 5th–95th percentile box of the SfM points (else the cameras,
    plus nothing: a capture whose cameras stand still has extent ~0)."""
    pts = scene.points.xyz if len(scene.points) >= 10 else np.stack([c.center for c in scene.cameras])
    lo, hi = np.percentile(pts, 5, axis=0), np.percentile(pts, 95, axis=0)
    return float((hi - lo).max())


def median_view_depth(scene: Scene, max_points: int = 20000) -> float | None:
    """Median over views of the median depth (scene units) of the SfM points each view sees (its
    track's points, or, in a model without tracks, those of up to ``max_points`` that project into
    it); None without 10 points."""
    if len(scene.points) < 10:
        return None
    xyz, sub = scene.points.xyz, None
    meds = []
    for i, cam in enumerate(scene.cameras):
        idx = scene.points.visible_in.get(i)
        if idx is not None and len(idx):
            z = xyz[idx] @ cam.R[2] + cam.t[2]
        else:
            if sub is None:
                sub = xyz[np.linspace(0, len(xyz) - 1, min(len(xyz), max_points)).astype(int)]
            uv, z = cam.project(sub)
            z = z[(z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)]
        if (z > 0).sum() >= 10:
            meds.append(float(np.median(z[z > 0])))
    return float(np.median(meds)) if meds else None


def metric_warning(scene: Scene) -> str | None:
    """A sentence when the scene does not look metric (see the module docstring), else None."""
    ext = scene_extent(scene)
    fix = f"every threshold here is in metres; {rescale_hint(scene.root)}"
    if scene.metadata.get("scale") == ARBITRARY_SCALE:
        return (f"the scene was mapped from images alone (`geocues sfm --mode map`), so its unit is arbitrary "
                f"(it spans {ext:.3g} units): {fix}")
    if len(scene.points) < 10:
        return None
    done = scene.metadata.get("rescaled")
    if isinstance(done, dict):  # the user's factor: rescaling this copy again by the same rule changes nothing
        how = (f"--median-depth {done['median_depth']:g}" if done.get("median_depth") is not None else
               "--from-priors" if done.get("from_priors_views") else f"--scale {done.get('scale', float('nan')):.6g}")
        fix = (f"`geocues rescale` ({how}) made it so; if the room is not that size, rescale "
               f"{shlex.quote(str(done.get('from', 'the original')))} again with the factor you know (--scale S, "
               "metres per unit of that scene) or another guess (--median-depth M)")
    if not ROOM_RANGE[0] <= ext <= ROOM_RANGE[1]:
        return f"the scene spans {ext:.3g} {'m' if done else 'units'}, not the 0.5-200 m of an indoor capture: {fix}"
    depth = median_view_depth(scene)
    if depth is not None and not DEPTH_RANGE[0] <= depth <= DEPTH_RANGE[1]:
        return (f"the views' median depth is {depth:.3g} {'m' if done else 'units'}, not the 0.2-8 m of photos of a "
                f"room (the scene spans {ext:.3g}): {fix}")
    return None


def _scaled_depth_priors(scene_dir: Path, out_dir: Path, scale: float) -> None:
    """OUT/priors as a folder of its own: the depth priors (.npy) times ``scale``, the rest linked."""
    src = Path(scene_dir).resolve() / "priors"
    (out_dir / "priors").unlink()  # link_scene's link
    (out_dir / "priors" / "depth").mkdir(parents=True)
    for sub in src.iterdir():
        if sub.name != "depth":
            (out_dir / "priors" / sub.name).symlink_to(sub)
    for f in sorted((src / "depth").glob("*.npy")):
        np.save(out_dir / "priors" / "depth" / f.name, np.load(f) * np.float32(scale))


def priors_in_scene_unit(scene: Scene) -> bool:
    """Whether the scene's depth priors are in its own unit (`geocues mvs` wrote them from its photos)
    rather than metres: they say nothing about its scale."""
    priors = scene.metadata.get("priors")
    return isinstance(priors, dict) and priors.get("source") == "geocues mvs"


def scale_from_priors(scene: Scene, min_points: int = 20) -> tuple[float, int]:
    """(metric / scene-unit factor, views used) from the depth priors at the SfM points each view sees
    (its track's points where the model has tracks: points behind a wall project into the view too,
    and pulled an exact prior's factor 1.3 % low). The priors must be metric depth, not disparity."""
    if scene.has_depth_priors and scene.depth_kind != "depth":
        raise ValueError(f"--from-priors needs metric depth priors; {scene.root}'s are {scene.depth_kind} "
                         "(scene.json priors.depth_kind), which has no unit: give --scale or --median-depth")
    ratios = []
    for i, cam in enumerate(scene.cameras):
        d = scene.depth_prior(i)
        if d is None:
            continue
        seen = scene.points.visible_in.get(i)
        uv, z = cam.project(scene.points.xyz[seen] if seen is not None and len(seen) >= min_points else scene.points.xyz)
        uv, z = uv[z > 0], z[z > 0]
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (col >= 0) & (col < d.shape[1]) & (row >= 0) & (row < d.shape[0])
        z, p = z[inside], d[row[inside], col[inside]]
        ok = p > 0
        if ok.sum() >= min_points:
            ratios.append(float(np.median(p[ok]) / np.median(z[ok])))
    if not ratios:
        raise ValueError(f"--from-priors: no view of {scene.root} has a depth prior at {min_points}+ of its SfM points")
    return float(np.median(ratios)), len(ratios)


@dataclass
class RescaleConfig:
    """Options of `geocues rescale`: one factor, given or estimated."""

    scale: float | None = None
    """Metres per scene unit."""
    from_priors: bool = False
    """Estimate the factor from the depth priors (median ratio at the SfM points)."""
    median_depth: float | None = None
    """A guess when nothing is known: the metres between the camera and what the photos show (the
    views' median SfM depth becomes this; 2 m for a room photographed from its middle). A guess 20 %
    off makes every metric threshold 20 % off, not 6x."""

    def validate(self) -> None:
        if (self.scale is not None) + self.from_priors + (self.median_depth is not None) != 1:
            raise ValueError("give one of --scale S, --from-priors or --median-depth M")
        for name, v in (("--scale", self.scale), ("--median-depth", self.median_depth)):
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v}")


def run(cfg: RescaleConfig, scene_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``out_dir``: the scene with camera translations and SfM points multiplied by the factor
    (``cfg.scale``, estimated ``cfg.from_priors``, or guessed from ``cfg.median_depth``), through
    pycolmap so tracks, 2D points and camera models stay whole; images, priors and GT linked (priors
    and GT are already metric; `geocues mvs` depth, in the scene's unit, is written scaled). OUT is
    built in a temporary sibling and renamed into place. Returns
    ``out_dir``."""
    cfg.validate()
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    if out_dir.exists() and out_dir.resolve() == scene_dir.resolve():
        raise ValueError("geocues rescale writes a new scene folder: pass an OUT other than SCENE")
    check_replaceable(out_dir, "scene.json", "a scene `geocues rescale` wrote", {"scene": scene_dir}, key="rescaled")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise ValueError(f"{out_dir} already exists; pass --overwrite to replace it")
    check_output_dir(out_dir)
    scene = Scene.load(scene_dir, check_priors=False)
    scale, used = cfg.scale, None
    unscaled = scene_extent(scene)
    if cfg.from_priors:
        if priors_in_scene_unit(scene):
            raise ValueError(f"--from-priors: the depth priors of {scene_dir} were written by `geocues mvs` from the "
                             "scene's own photos, in its own unit: they cannot tell its scale; give --scale (metres per "
                             "unit) or --median-depth (how far the photos were taken): the priors are scaled with it")
        scale, used = scale_from_priors(scene)
        if isinstance(scene.metadata.get("priors"), dict) and scene.metadata["priors"].get("simulated"):
            log.warning("--from-priors: the priors of %s are SIMULATED (a random scale error per image, "
                        "scene.json priors.simulated): the factor %.4g measures their simulated error, not the "
                        "scene's unit", scene_dir, scale)
        extent = unscaled * scale
        if not 0.5 <= extent <= 100.0:  # a room is neither 12 cm nor 5 km across
            log.warning("--from-priors: the factor %.6g makes the scene %.3g m across: are the priors in "
                        "metres? (millimetres: scene.json priors.depth_png_scale 1000 for PNG, or divide the "
                        ".npy files; 8-bit PNG depth cannot hold metric depth)", scale, extent)
    if cfg.median_depth is not None:
        depth = median_view_depth(scene)
        if depth is None:
            raise ValueError(f"--median-depth: {scene_dir} has fewer than 10 SfM points in its views (run `geocues sfm`)")
        scale = cfg.median_depth / depth
    extent = unscaled * scale  # (cameras that stand still, no points: extent 0, any factor keeps it 0)
    if not (np.isfinite(extent) and (unscaled == 0 or 1e-6 <= extent <= 1e7)):  # float32 breaks far before 1e300
        raise ValueError(f"the factor {scale:.6g} makes {scene_dir} {extent:.3g} m across: no scene is; check "
                         "--scale (metres per unit of the scene)")
    import pycolmap

    transforms = find_transforms(scene_dir)
    if transforms is not None and not (scene_dir / "sparse").exists():  # a nerfstudio scene's cameras
        rec, binary = transforms_reconstruction(transforms), False
    else:
        model_dir = find_model_dir(scene_dir)
        rec = load_reconstruction(model_dir)  # tracks, 2D points and camera models kept as they are
        binary = (model_dir / "images.bin").is_file()
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(np.eye(3)), np.zeros(3)))
    with atomic_dir(out_dir) as tmp:
        (tmp / "sparse" / "0").mkdir(parents=True)
        (rec.write_binary if binary else rec.write_text)(str(tmp / "sparse" / "0"))
        link_scene(scene_dir, tmp)  # images, priors (metric already), GT
        if priors_in_scene_unit(scene) and scene.has_depth_priors:  # `geocues mvs` depth: it scales with it
            _scaled_depth_priors(scene_dir, tmp, scale)
        meta = json.loads((tmp / "scene.json").read_text()) if (tmp / "scene.json").is_file() else {}
        meta["rescaled"] = {"from": str(scene_dir.resolve()), "scale": scale, "from_priors_views": used,
                            "median_depth": cfg.median_depth}
        meta.pop("scale", None)  # metric now: no longer "arbitrary"
        (tmp / "scene.json").write_text(json.dumps(meta, indent=1))
    how = (f" (from the depth priors of {used} views)" if used else
           f" (the views' median depth {cfg.median_depth:g} m)" if cfg.median_depth is not None else "")
    log.info("rescaled %s by %.6g%s: extent %.3g -> %.3g m", scene_dir, scale, how, scene_extent(scene),
             scene_extent(scene) * scale)
    return out_dir
