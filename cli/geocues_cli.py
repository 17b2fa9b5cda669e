"""`geocues` console script: scene inspection, SfM and cue extraction."""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path
from typing import Annotated, Literal

import tyro

from cli._dispatch import dispatch, option_from_argv
from geocues.extract import ExtractConfig
from geocues.mvs import MvsConfig
from geocues.presets import EXTRACT_PRESETS, extract_preset_config
from geocues.rescale import RescaleConfig
from geocues.sfm import SfmConfig
from geocues.undistort import UndistortConfig


def sfm(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
        out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
        overwrite: bool = False,
        recompute: bool = False,
        cfg: tyro.conf.OmitArgPrefixes[SfmConfig] = SfmConfig()) -> int:
    """3D points for SCENE with pycolmap: known-pose triangulation, or incremental mapping (--mode map).

    Without -o the model SCENE/sparse/0 is replaced in place; with -o OUT, OUT becomes a complete
    scene folder (images, priors and gt linked). The report is also written to OUT/sfm_report.json.

    Args:
        scene: scene folder with images/ (and sparse/0 for triangulation).
        out: output scene folder (default: write SCENE/sparse/0 in place).
        overwrite: replace a finished run in OUT (without it, a finished OUT is an error).
        recompute: recompute features and matches even if cached.
        cfg: SfM options.
    """
    from geocues.sfm import run

    done = run(cfg, scene, out, overwrite=overwrite, recompute=recompute)
    report = json.loads((done / "sfm_report.json").read_text())
    print(json.dumps({k: v for k, v in report.items() if k != "config"}, indent=2))
    return 0


def undistort(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
              out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
              overwrite: bool = False,
              cfg: tyro.conf.OmitArgPrefixes[UndistortConfig] = UndistortConfig()) -> int:
    """Undistort a scene with a distorted camera model (SIMPLE_RADIAL, OPENCV, ...) into a PINHOLE scene.

    Args:
        scene: scene folder with images/ and a COLMAP model.
        out: the new scene folder.
        overwrite: replace OUT's images and model if they exist.
        cfg: undistortion options.
    """
    from geocues.undistort import run

    print(run(cfg, scene, out, overwrite=overwrite))
    return 0


def _photos_not_in_model(s) -> list[str]:
    """The photos in SCENE/images/ that no camera of the model names (COLMAP names: relative paths)."""
    from geocues.photos import list_images

    folder = Path(s.root) / "images"
    if not folder.is_dir():
        return []
    named = {c.name for c in s.cameras} | {Path(c.image_path).resolve().relative_to(folder.resolve()).as_posix()
                                           for c in s.cameras if Path(c.image_path).resolve().is_relative_to(folder.resolve())}
    return [n for n in list_images(folder) if n not in named]


def info(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")], downscale: float = 1.0, test_every: int = 8) -> int:
    """Print a summary of SCENE: cameras, image sizes, points, priors, train/test split.

    Args:
        scene: scene folder (or a COLMAP model folder, or a nerfstudio transforms.json).
        downscale: divide image sizes and intrinsics by this factor.
        test_every: hold out every n-th image (index % n == 0) as a test view; 0 = none.
    """
    from geocues.advice import photos_only_summary
    from geocues.scene import Scene

    if (photos := photos_only_summary(scene)) is not None:  # README's first step: photos, no model yet
        print("\n".join(photos))
        return 0
    s = Scene.load(scene, downscale=downscale, test_every=test_every, allow_distorted=True)
    sizes = sorted({(c.width, c.height) for c in s.cameras})
    K = s.cameras[0].K
    pts = s.points
    n_depth = sum(s.depth_prior_path(i) is not None for i in range(len(s)))
    n_normal = sum(s.normal_prior_path(i) is not None for i in range(len(s)))
    print(f"scene      {s.root}")
    print(f"model      {s.model_dir}")
    print(f"cameras    {len(s)}  sizes {', '.join(f'{w}x{h}' for w, h in sizes)}  "
          f"(first: fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f})")
    if unposed := _photos_not_in_model(s):
        from geocues.advice import sfm_registered

        reg = sfm_registered(s.metadata)
        unmapped = reg is not None and len(unposed) <= reg["photos"] - reg["images"]
        print(f"photos     {len(unposed)} in {s.root / 'images'} are not in the model and are not used "
              f"({', '.join(unposed[:3])}{', ...' if len(unposed) > 3 else ''}): "
              + ("`geocues sfm` could not register them (its warning said so)" if unmapped
                 else "photos added after SfM need `geocues sfm` again"))
    if len(pts) and not pts.track_length.any():  # a nerfstudio ply_file_path: positions alone
        print(f"points     {len(pts)}  (without tracks: their visibility is tested by projection)")
    elif len(pts):
        print(f"points     {len(pts)}  mean track length {pts.track_length.mean():.2f}  "
              f"mean reprojection error {pts.error.mean():.3f} px")
    else:
        print("points     0  (run `geocues sfm` to triangulate them)")
    if s.distorted_models:
        print(f"warning    distorted camera model {', '.join(s.distorted_models)} (the intrinsics above ignore the "
              f"distortion): `geocues undistort {shlex.quote(str(s.root))} -o OUT` makes the PINHOLE scene the other commands read")
    print(f"priors     depth {n_depth}/{len(s)}" + (f" ({s.depth_kind})" if n_depth else "")
          + f"  normal {n_normal}/{len(s)}" + (f" ({s.normal_axes} axes)" if n_normal else ""))
    for kind in ("depth", "normal"):
        if stray := s.stray_priors(kind):
            print(f"warning    {len(stray)} file(s) in priors/{kind}/ are no image's prior and are ignored "
                  f"({', '.join(p.name for p in stray[:3])}{', ...' if len(stray) > 3 else ''}): a prior is named "
                  f"after its image's stem (images/{s.cameras[0].name} -> priors/{kind}/{s.cameras[0].stem}.npy)")
    from geocues.advice import fov_warning, normal_axes_warning

    if odd := fov_warning(s):
        print(f"warning    {odd}")

    if away := normal_axes_warning(s):
        print(f"warning    {away}")
    from geocues.rescale import metric_warning, scene_extent

    unit = "m" if "rescaled" in s.metadata else "units"  # `geocues rescale` made it metres; else the model's own
    print(f"extent     {scene_extent(s):.3g} {unit} (5-95 % box of the {'points' if len(pts) >= 10 else 'cameras'})")
    warn = metric_warning(s)
    if warn:
        print(f"warning    {warn}")
    print(f"split      {len(s.train_indices)} train / {len(s.test_indices)} test (every {test_every})")
    from geocues.advice import few_views_warning, registration_warning

    if few := few_views_warning(len(s)):
        print(f"warning    {few}")
    if few := registration_warning(s.metadata):
        print(f"warning    {few}")
    print(f"gt mesh    {s.gt_mesh_path or 'none'}")
    if s.metadata:
        print(f"metadata   {', '.join(sorted(s.metadata))}")
    from geocues.advice import next_steps

    for k, (cmd, why) in enumerate(next_steps(s, not_metric=warn is not None)):  # a script to copy
        print(f"{'next' if k == 0 else '':<11}# {why}\n{'':<11}{cmd}")
    return 0


ExtractPresetName = Literal[tuple(EXTRACT_PRESETS)]  # type: ignore[valid-type]


def _extract_command(preset_name: str = "paper"):
    """`geocues extract` with the defaults of preset ``preset_name`` (options on the command line win)."""

    def extract(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
                out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
                preset: ExtractPresetName = preset_name,
                overwrite: bool = False,
                cfg: Annotated[ExtractConfig, tyro.conf.arg(name="")] = extract_preset_config(preset_name)) -> int:
        """Extract line, SfM and plane-like cues of SCENE into OUT (cues.ply, lines3d.npz, report.json).

        Args:
            scene: scene folder (images/, sparse/0, optional priors/; or a nerfstudio transforms.json).
            out: output folder CUES/ (its cache/ is reused by later runs).
            preset: start from these options (geocues/presets.py): `paper` the paper's cues (§4.1);
                `room` adds floor lines, walls, ceiling, floor grids and level snap for a room with a level floor and
                ceiling and vertical walls, seen with depth priors (train with `splat train --preset
                room`); `mvs` for a scene whose depth priors come from `geocues mvs` (photos only): plane points
                also in the MVS depth's holes (train with `splat train --preset mvs`).
                Options given on the command line override it.
            overwrite: replace cues already in OUT (the per-image cache is still reused).
            cfg: extraction options; --no-sfm / --no-lines / --no-planes / --no-priors switch stages off;
                --prior-kind disparity reads the depth priors as inverse depth (Depth-Anything, MiDaS).
        """
        from geocues.extract import run

        turned = [f"--{k.replace('_', '-')}" for k, v in EXTRACT_PRESETS[preset].items()
                  if k.startswith("floor.") and v is True]
        if turned:
            try:
                cfg.floor.validate()
            except ValueError as exc:  # `--preset room --floor.no-lines` named a flag the user never typed
                raise ValueError(f"{exc} (--preset {preset} turns on {', '.join(turned)}: leaving one out needs the "
                                 "ones that depend on it off too)") from None
        report_path = Path(out) / "report.json"
        before = report_path.stat().st_mtime_ns if report_path.is_file() else None
        out_dir = run(cfg, scene, out, overwrite=overwrite)
        report = json.loads((out_dir / "report.json").read_text())
        if before is not None and report_path.stat().st_mtime_ns == before:  # the same run finished earlier
            print(f"{out_dir} already holds these cues (same options and scene): nothing redone; --overwrite "
                  "extracts them again")
            print(json.dumps({"counts": report["counts"], "notes": report["notes"]}, indent=2))
            return 0
        print(json.dumps({k: report[k] for k in ("counts", "seconds", "notes")}, indent=2))
        return 0

    return extract


def _extract_from_argv(argv: list[str]):
    name = option_from_argv(argv, "--preset") or "paper"
    if name not in EXTRACT_PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(EXTRACT_PRESETS)}")
    return _extract_command(name)


extract = _extract_command()
extract.from_argv = _extract_from_argv  # dispatch picks the preset's defaults before parsing


# Add commands here as {name: function}; each function's typed signature is its CLI (tyro).
def mvs(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
        out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
        overwrite: bool = False,
        cfg: tyro.conf.OmitArgPrefixes[MvsConfig] = MvsConfig()) -> int:
    """Weight-free dense depth priors from the posed images (plane-sweep NCC stereo, forward-backward
    consistency, textureless holes completed from the planes of the consistent depth): OUT becomes a scene folder (images, model, GT linked) with priors/depth/*.npy in
    the scene's unit (metres once the scene is metric: `geocues rescale`) and priors/depth_conf/*.npy; run `geocues extract OUT` next. An extension (docs/geocues.md).

    Args:
        scene: scene folder with images/ and a posed COLMAP model (SfM points set the depth range).
        out: the new scene folder.
        overwrite: compute the priors again into an OUT that has them.
        cfg: MVS options.
    """
    from geocues.mvs import run

    done = run(cfg, scene, out, overwrite=overwrite)
    print(f"wrote {done}/priors/depth and {done}/mvs_report.json")
    return 0


def rescale(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
            out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
            overwrite: bool = False,
            cfg: tyro.conf.OmitArgPrefixes[RescaleConfig] = RescaleConfig()) -> int:
    """Make a scene metric: OUT is SCENE with camera translations and SfM points multiplied by --scale,
    by the factor its metric depth priors give (--from-priors), or by the one that puts the views'
    median depth at --median-depth metres (a guess); images, priors and GT linked.
    `geocues info` shows a scene's extent and warns when it is far from metric.

    Args:
        scene: scene folder with a COLMAP model.
        out: the new scene folder.
        overwrite: replace an existing OUT.
        cfg: the factor (--scale S, --from-priors or --median-depth M).
    """
    from geocues.rescale import run

    done = run(cfg, scene, out, overwrite=overwrite)
    print(f"wrote {done} (scale in {done}/scene.json)")
    return 0


COMMANDS: dict = {"info": info, "sfm": sfm, "undistort": undistort, "mvs": mvs, "rescale": rescale,
                  "extract": extract}


def main(argv: list[str] | None = None) -> int:
    return dispatch("geocues", COMMANDS, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
