"""`evaluate` console script: `evaluate PRED_MESH [SCENE] [--gt GT_MESH]` (default) and benchmark tools.

SCENE is positional, as in `geocues` and `splat`; the old `--scene SCENE` still works (a deprecation
note on stderr) and is moved into place before tyro parses."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import tyro

from cli._dispatch import dispatch
from cli.rooms_cli import make_room
from evaluation.cue_metrics import CueMetricsConfig
from evaluation.mesh_metrics import MeshMetricsConfig, evaluate_with_scene, format_table, save_json
from evaluation.sim_priors import SimPriorsConfig
from geocues.atomic import atomic_path, check_output_file


def mesh(pred_mesh: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="PRED_MESH")],
         scene: Annotated[Path | None, tyro.conf.Positional, tyro.conf.arg(metavar="[SCENE]")] = None,
         gt: Annotated[Path | None, tyro.conf.arg(metavar="GT_MESH")] = None,
         json: Annotated[Path | None, tyro.conf.arg(metavar="OUT", aliases=("-o",))] = None,
         overwrite: bool = False,
         renders: Annotated[Path | None, tyro.conf.arg(metavar="DIR")] = None,
         test_every: int = 8,
         lpips: Annotated[Path | None, tyro.conf.arg(metavar="WEIGHTS")] = None,
         align_to: Annotated[Path | None, tyro.conf.arg(metavar="GT_SCENE")] = None,
         icp: bool = False,
         cfg: Annotated[MeshMetricsConfig, tyro.conf.arg(name="")] = MeshMetricsConfig()) -> int:
    """Mesh metrics (accuracy, completeness, Chamfer-L1, F-score, normal consistency) of a mesh,
    and with --renders the PSNR / SSIM of rendered held-out views. A mesh that looks like it is in
    another frame or unit than the GT (most of it outside the GT's box, or 3x its size) is warned
    about: score such a mesh with --align-to.

    Args:
        pred_mesh: the predicted mesh (PLY, OBJ, OFF, STL, GLB/GLTF or FBX; polygons are triangulated).
        scene: a scene folder; its cameras (train and test) cull both meshes to what they saw.
        gt: the ground-truth mesh (default: SCENE/gt/mesh.ply when SCENE is given).
        json: write the metrics and the protocol used to this JSON file.
        overwrite: replace OUT if it exists.
        renders: a folder of rendered test views named like their images (splat train's
            OUT/test_renders); needs SCENE.
        test_every: the held-out split the renders were made for (every n-th image).
        lpips: a TorchScript LPIPS network you made (no weights are downloaded); adds LPIPS to --renders' figures
            (refused without --renders).
        align_to: the GT scene of a reconstruction made in its own frame (e.g. `geocues sfm --mode
            map`): the mesh (in the frame of SCENE) is moved into GT_SCENE's frame by the similarity
            of the camera centres both share (Umeyama), then scored against GT_SCENE's GT mesh
            (or --gt) culled to GT_SCENE's cameras. Needs SCENE.
        icp: after --align-to, refine with ICP (rotation, translation and scale) against the GT mesh; a
            correction over 3 deg, 5 % of scale or a mean surface shift of 2 x --threshold is warned about.
    """
    _check_arguments(pred_mesh, scene, gt)
    if json is not None:
        check_output_file(json, overwrite)
    if renders is not None and scene is None:
        raise ValueError("--renders needs SCENE (the test images are the scene's): "
                         "evaluate PRED_MESH SCENE --renders DIR")
    if lpips is not None and renders is None:  # it was ignored without a word
        raise ValueError(f"--lpips {lpips} scores rendered views, and there are none: pass --renders DIR "
                         "(and SCENE) with it, or leave --lpips out")
    images = None
    if renders is not None:  # first: a bad folder is named before the minute the mesh metrics take
        from evaluation.image_metrics import evaluate_renders

        images = evaluate_renders(renders, scene, test_every, lpips)
    if align_to is not None:
        if scene is None:
            raise ValueError("--align-to needs SCENE, the scene whose frame the mesh is in: "
                             "evaluate PRED_MESH SCENE --align-to GT_SCENE")
        from evaluation.align import alignment_line, evaluate_aligned

        result = evaluate_aligned(pred_mesh, scene, align_to, gt, cfg, icp=icp)
        print(alignment_line(align_to, result.protocol["alignment"]))
    else:
        if icp:
            raise ValueError("--icp refines an --align-to alignment; pass --align-to GT_SCENE")
        _warn_own_frame(scene, "mesh")
        result = evaluate_with_scene(pred_mesh, gt, scene, cfg)
    print(format_table(result))
    _warn_registered(scene)
    if images is not None:
        lp = f", LPIPS {images['lpips']:.4f}" if images["lpips"] is not None else ""
        print(f"held-out views: {images['n_images']}, PSNR {images['psnr']:.2f} dB, SSIM {images['ssim']:.4f}{lp}")
    if json is not None:
        save_json(result, json, {"images": images} if images is not None else None)  # atomic
        print(f"wrote {json}")
    return 0


def _check_arguments(pred_mesh: Path, scene: Path | None, gt: Path | None) -> None:
    """The mix-ups a new user makes, each named with the right form: SCENE and MESH swapped, a run
    folder for its mesh, a GT mesh where SCENE goes, a folder for --gt."""
    usage = "evaluate PRED_MESH [SCENE] [--gt GT_MESH]"
    if pred_mesh.is_dir():
        if (pred_mesh / "mesh.ply").is_file():
            raise ValueError(f"{pred_mesh} is a folder (a run?): its mesh is {pred_mesh / 'mesh.ply'} — {usage}")
        swapped = scene is not None and scene.is_file()
        raise ValueError(f"no mesh at {pred_mesh} (a folder)"
                         + (f"; the mesh comes first: evaluate {scene} {pred_mesh}" if swapped else f" — {usage}"))
    if scene is not None and scene.is_file():
        raise ValueError(f"{scene} is a file where SCENE (a folder) goes; a ground-truth mesh is given as "
                         f"--gt {scene} — {usage}")
    if gt is not None and gt.is_dir():
        from geocues.scene import gt_mesh_file

        inside = gt_mesh_file(gt) or ((gt / "mesh.ply") if (gt / "mesh.ply").is_file() else None)
        raise ValueError(f"--gt {gt} is a folder; --gt takes the GT mesh file"
                         + (f" ({inside}?)" if inside else "") + (f", a scene folder goes after the mesh" if inside is None
                                                                  and (gt / "sparse").is_dir() else ""))


def _warn_registered(scene: Path | None) -> None:
    """One warning when `geocues sfm` left many of SCENE's photos out (geocues.advice.registration_warning)."""
    from evaluation.align import scene_metadata
    from geocues.advice import registration_warning

    if (warning := registration_warning(scene_metadata(scene))) is not None:
        print(f"warning: {warning}", file=sys.stderr)


def _warn_own_frame(scene: Path | None, what: str) -> None:
    """One warning when SCENE was mapped from images alone (evaluation.align.own_frame_warning)."""
    from evaluation.align import own_frame_warning

    if (warning := own_frame_warning(scene, what)) is not None:
        print(f"warning: {warning}", file=sys.stderr)


def cues(cues_dir: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="CUES")],
         scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
         gt: Annotated[Path | None, tyro.conf.arg(metavar="GT_MESH")] = None,
         json: Annotated[Path | None, tyro.conf.arg(metavar="OUT", aliases=("-o",))] = None,
         overwrite: bool = False,
         align_to: Annotated[Path | None, tyro.conf.arg(metavar="GT_SCENE")] = None,
         cfg: Annotated[CueMetricsConfig, tyro.conf.arg(name="")] = CueMetricsConfig()) -> int:
    """Accuracy (distance to GT per cue type) and coverage of `geocues extract` output. Cues of a scene
    mapped from images alone are in its own frame: score them with --align-to (a warning says so).

    Args:
        cues_dir: the folder `geocues extract` wrote (cues.ply, report.json).
        scene: the scene the cues came from (its cameras define the seen GT surface).
        gt: the ground-truth mesh (default: SCENE/gt/mesh.ply, or GT_SCENE's with --align-to).
        json: write the result to this JSON file.
        overwrite: replace OUT if it exists.
        align_to: the GT scene of a SCENE in its own frame (e.g. `geocues sfm --mode map`): the cues are
            moved into GT_SCENE's frame by the similarity of the camera centres both share, as
            `evaluate PRED_MESH SCENE --align-to GT_SCENE` does, and the seen surface is what GT_SCENE's
            cameras of those images see.
    """
    import json as _json

    from evaluation.cue_metrics import evaluate_cues_dir, format_cue_table

    if json is not None:
        check_output_file(json, overwrite)
    if align_to is None:
        _warn_own_frame(scene, "cues")
        result = evaluate_cues_dir(cues_dir, scene, gt, cfg)
    else:
        from evaluation.align import alignment_line

        result = evaluate_cues_dir(cues_dir, scene, gt, cfg, align_to=align_to)
        print(alignment_line(align_to, result["alignment"]))
    print(format_cue_table(result))
    if json is not None:
        with atomic_path(json) as tmp:
            tmp.write_text(_json.dumps(result, indent=1))
        print(f"wrote {json}")
    return 0


def report(run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")],
           scene: Annotated[Path | None, tyro.conf.Positional, tyro.conf.arg(metavar="[SCENE]")] = None,
           gt: Annotated[Path | None, tyro.conf.arg(metavar="GT_MESH")] = None,
           gt_depth: Annotated[Path | None, tyro.conf.arg(metavar="DIR")] = None,
           views: int = 4,
           overwrite: bool = False,
           align_to: Annotated[Path | None, tyro.conf.arg(metavar="GT_SCENE")] = None) -> int:
    """Plots and a contact sheet of one `splat train` folder, linked from RUN/report.md.

    Loss terms and Gaussians per type against iterations; test PSNR/SSIM (and mesh metrics of the
    checkpoint meshes when a GT mesh is at hand) against seconds; held-out views as GT | render |
    depth | normals | depth error. The checkpoint meshes of a run on a scene mapped from images alone
    are scored with --align-to (without it they are left out, with a warning and a note in
    report.md). -v/--verbose: debug logging.

    Args:
        run: the `splat train` output folder.
        scene: the scene it was trained on (default: the one its report.json names).
        gt: GT mesh for the checkpoint meshes (default: SCENE/gt/mesh.ply when present).
        gt_depth: folder of exact depth maps for the depth-error panel (default: SCENE/gt/depth).
        views: held-out views in the contact sheet.
        overwrite: replace an earlier report in RUN (report.md, its plots and report_data.json).
        align_to: the GT scene of a run on a scene in its own frame (e.g. `geocues sfm --mode map`): the
            checkpoint meshes are moved into GT_SCENE's frame and scored as `evaluate PRED_MESH SCENE
            --align-to GT_SCENE` does (GT: --gt or GT_SCENE's gt/mesh.ply).
    """
    from evaluation.run_report import write_run_report

    print(f"wrote {write_run_report(run, scene, gt, gt_depth, views, overwrite=overwrite, align_to=align_to)}")
    return 0


def simulate_priors(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
                    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
                    overwrite: bool = False,
                    cfg: Annotated[SimPriorsConfig, tyro.conf.arg(name="")] = SimPriorsConfig()) -> int:
    """SIMULATED monocular depth/normal priors for a real scene with exact depth (e.g. ICL-NUIM).

    OUT is SCENE (images, model, gt linked) plus priors/ made from the exact depth and the GT mesh
    with the benchmark rooms' simulated errors; OUT/scene.json marks them simulated. For the
    `splat ablate` rows that need priors; label such results "simulated priors".

    Args:
        scene: the scene folder (COLMAP model, images/, gt/mesh.ply or --gt-mesh).
        out: the new scene folder.
        overwrite: replace OUT if it exists.
        cfg: sources and simulated errors.
    """
    from evaluation.sim_priors import simulate_scene_priors

    print(f"wrote {simulate_scene_priors(scene, out, cfg, overwrite=overwrite)}")
    return 0


def scene_option_to_positional(argv: list[str]) -> list[str]:
    """The old spelling `--scene SCENE` (before SCENE became positional, as in `geocues`/`splat`):
    moved to the end of the arguments as the positional SCENE, with a one-line deprecation note."""
    out, scene = [], None
    k = 0
    while k < len(argv):
        a = argv[k]
        if a == "--scene" or a.startswith("--scene="):
            if scene is not None:
                raise ValueError("--scene is given twice")
            if a == "--scene":
                if k + 1 >= len(argv):
                    raise ValueError("--scene needs a value (better: give SCENE as a positional argument)")
                scene, k = argv[k + 1], k + 2
            else:
                scene, k = a.split("=", 1)[1], k + 1
            continue
        out.append(a)
        k += 1
    if scene is None:
        return argv
    print(f"evaluate: --scene is deprecated; give SCENE as a positional argument (`evaluate ... {scene}`)",
          file=sys.stderr)
    return out + [scene]


# Add commands here as {name: function}; each function's typed signature is its CLI (tyro).
# The default command (metrics of a mesh) is registered under "mesh" and runs without its name.
COMMANDS: dict = {"mesh": mesh, "make-room": make_room, "cues": cues, "report": report,
                  "simulate-priors": simulate_priors}
DEFAULT = "mesh"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] not in ("make-room", "simulate-priors") and any(a == "--scene" or a.startswith("--scene=") for a in argv):
        try:
            argv = scene_option_to_positional(argv)
        except ValueError as exc:
            print(f"evaluate: error: {exc}", file=sys.stderr)
            return 1
    return dispatch("evaluate", COMMANDS, default=DEFAULT, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
