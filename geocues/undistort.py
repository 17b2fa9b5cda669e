"""`geocues undistort`: turn a scene with a distorted COLMAP camera model (SIMPLE_RADIAL, OPENCV, ...)
into a PINHOLE scene with pycolmap's image undistorter (COLMAP ``image_undistorter``).

OUT gets undistorted ``images/``, the model in ``sparse/0`` (cameras now PINHOLE, points kept),
``scene.json`` copied and ``gt/`` linked. Priors, and gt/'s exact depth and normals, are per-pixel
maps of the distorted images and are not carried over (they would need the same warp): a warning says
so; a scene already pinhole keeps them (linked: nothing was warped).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from geocues.atomic import atomic_dir, check_not_input, check_output_dir
from geocues.colmap_io import camera_distortion, find_model_dir, is_pinhole, load_reconstruction
from geocues.photos import missing_images_error
from geocues.scene import no_images_folder

log = logging.getLogger(__name__)


@dataclass
class UndistortConfig:
    """Options of `geocues undistort`."""

    blank_pixels: float = 0.0
    """Share of blank (black) pixels allowed in the undistorted image: 0 crops to valid pixels only."""
    max_image_size: int = -1
    """Longest side of the undistorted images (-1 = keep the size)."""
    binary: bool = True
    """Write the model as .bin (else .txt)."""


PER_PIXEL_GT = ("depth", "normal")
"""gt/ folders of per-pixel maps: they fit the distorted images, so undistort leaves them behind."""


def _carry_gt(gt: Path, out_gt: Path, warped: bool) -> None:
    """OUT/gt links SCENE/gt (the mesh is geometry: undistortion leaves it as it is). When the images were
    warped, the per-pixel maps in gt/ (exact depth, normals) no longer fit them: OUT/gt is then a folder
    of links to everything else (so maps added to SCENE/gt later stay out too), and a warning names what
    stayed behind. An OUT/gt made of links (an earlier run's) is made again; one holding files is kept."""
    if not gt.is_dir():
        return
    if out_gt.is_symlink():
        out_gt.unlink()
    elif out_gt.is_dir():
        entries = list(out_gt.iterdir())
        if not all(e.is_symlink() for e in entries):
            return  # the user's own files
        for e in entries:
            e.unlink()
        out_gt.rmdir()
    if not warped:
        out_gt.symlink_to(gt.resolve())
        return
    out_gt.mkdir()
    for entry in sorted(gt.iterdir()):
        if entry.name not in PER_PIXEL_GT:
            (out_gt / entry.name).symlink_to(entry.resolve())
    if left := [name for name in PER_PIXEL_GT if (gt / name).exists()]:
        log.warning("undistort: %s not carried over (per-pixel maps of the distorted images; they would need the "
                    "same warp): `splat ablate`'s floor row and the GT-depth panels of `splat render` read gt/depth",
                    ", ".join(str(gt / name) for name in left))


def run(cfg: UndistortConfig, scene_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Undistort ``scene_dir`` into ``out_dir`` (a new scene folder); returns ``out_dir``. Refuses to
    write into SCENE, and into an OUT that holds a model unless ``overwrite``."""
    import pycolmap

    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    model_dir = find_model_dir(scene_dir)
    image_dir = scene_dir / "images"
    if not image_dir.is_dir():
        raise no_images_folder(image_dir)
    if out_dir.resolve() == scene_dir.resolve():
        raise ValueError(f"undistort writes a new scene: OUT must differ from SCENE ({scene_dir})")
    check_not_input(out_dir, {"scene": scene_dir})
    if (out_dir / "sparse").exists() and not overwrite:
        raise ValueError(f"{out_dir / 'sparse'} exists; pass --overwrite to replace it")
    check_output_dir(out_dir)
    rec = load_reconstruction(model_dir)
    if rec.num_reg_images() == 0:
        raise ValueError(f"the COLMAP model in {model_dir} has no registered images")
    if err := missing_images_error(model_dir, sorted(image_dir / im.name for im in rec.images.values())):
        raise err
    models = sorted({c.model.name for c in rec.cameras.values()})
    pinhole = all(is_pinhole(c.model.name, camera_distortion(c)) for c in rec.cameras.values())
    if pinhole:
        log.info("undistort: %s already uses %s cameras without distortion; images are copied unchanged "
                 "(every command reads this scene as it is)", scene_dir, models)
    if (scene_dir / "priors").is_dir() and not pinhole:
        log.warning("undistort: priors in %s are not carried over (they would need the same warp)",
                    scene_dir / "priors")

    from geocues.sfm_steps import quiet_pycolmap

    quiet_pycolmap()  # COLMAP's per-image lines only with -v
    opts = pycolmap.UndistortCameraOptions()
    opts.blank_pixels = cfg.blank_pixels
    opts.max_image_size = cfg.max_image_size
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".undistort.", dir=out_dir))
    try:
        log.info("undistort: %d images of %s (%s) -> %s", rec.num_reg_images(), scene_dir, models, out_dir)
        pycolmap.undistort_images(str(tmp), str(model_dir), str(image_dir), output_type="COLMAP",
                                  copy_policy=pycolmap.FileCopyType.copy, undistort_options=opts)
        new = pycolmap.Reconstruction(str(tmp / "sparse"))
        with atomic_dir(out_dir / "images") as img_tmp:
            img_tmp.rmdir()
            shutil.move(str(tmp / "images"), str(img_tmp))
        with atomic_dir(out_dir / "sparse" / "0") as model_tmp:
            (new.write_binary if cfg.binary else new.write_text)(str(model_tmp))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if (scene_dir / "scene.json").is_file():
        shutil.copyfile(scene_dir / "scene.json", out_dir / "scene.json")
    _carry_gt(scene_dir / "gt", out_dir / "gt", warped=not pinhole)
    priors = scene_dir / "priors"
    if pinhole and priors.is_dir() and not (out_dir / "priors").exists():  # nothing warped: they still fit
        (out_dir / "priors").symlink_to(priors.resolve())
    log.info("undistort: wrote %s (cameras now %s)", out_dir,
             sorted({c.model.name for c in new.cameras.values()}))
    return out_dir
