"""`splat` console script: training, rendering and rasterizer benchmarks."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import sys
from pathlib import Path
from typing import Annotated, Literal

import tyro

from cli._dispatch import dispatch, option_from_argv
from cli._signals import exit_code
from splat.ablate import AblateConfig
from splat.bench import BenchConfig
from splat.presets import PRESETS, load_config_file, preset_config
from splat.mesh_run import MeshRunConfig
from splat.render_run import RenderConfig
from splat.train import TrainConfig
from splat.viewer import ViewConfig


def bench(json: Annotated[Path | None, tyro.conf.arg(metavar="OUT", aliases=("-o",))] = None,
          overwrite: bool = False,
          cfg: Annotated[BenchConfig, tyro.conf.arg(name="")] = BenchConfig()) -> int:
    """Time render() forward + backward per compositing backend, image size and Gaussian count.

    Args:
        json: write the results (every run, machine, load average) to this JSON file.
        overwrite: replace OUT if it exists.
    """
    from geocues.atomic import check_output_file
    from splat.bench import format_table, run_bench

    if json is not None:
        check_output_file(json, overwrite)
    result = run_bench(cfg, json_out=json)
    print(format_table(result))
    if json is not None:
        print(f"wrote {json}")
    return 0


PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]


def exit_status(run_dir: Path) -> int:
    """1 with an error line when the finished run's model is empty (report.json ``empty_result``: no
    Gaussian left, or none the held-out views see); the run's files are kept to look at. Else 0."""
    import json

    try:
        empty = json.loads((Path(run_dir) / "report.json").read_text()).get("empty_result")
    except (OSError, ValueError):
        return 0
    if empty:
        print(f"splat train: error: the trained model is empty (the warning above says why); its files are kept "
              f"in {run_dir}", file=sys.stderr)
        return 1
    return 0


def _train_command(preset_name: str = "full", config_file: Path | None = None, iters_given: bool = False):
    """`splat train` with the defaults of preset ``preset_name`` or of a run's config.yaml
    (options on the command line win; ``iters_given``: --iters is among them)."""
    base = load_config_file(config_file) if config_file is not None else preset_config(preset_name)

    def train(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
              cues: Annotated[Path, tyro.conf.arg(aliases=("-c",))],
              out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
              preset: PresetName = preset_name,
              overwrite: bool = False,
              resume: bool = False,
              load_config: Path | None = config_file,
              cfg: Annotated[TrainConfig, tyro.conf.arg(name="")] = base) -> int:
        """Train typed Gaussians on SCENE from the cue cloud CUES, then fuse a TSDF mesh (IndoorGS §4).

        Writes OUT/point_cloud.ply (3DGS format), OUT/mesh.ply, OUT/test_renders/, OUT/train_log.jsonl and
        OUT/report.json (test PSNR/SSIM at checkpoints against training seconds, timings per stage).

        Args:
            scene: scene folder (COLMAP model, images/, optional priors/).
            cues: cue folder from `geocues extract` (or its cues.ply).
            out: output folder.
            preset: start from this named configuration (splat/presets.py: `full` is IndoorGS, `no-cues`
                the RaDe-GS-style baseline, the rest the paper's ablation rows and this project's extensions:
                `room` / `room-mesh` for `geocues extract --preset room` cues, `mvs` for a `geocues mvs` scene and
                `--preset mvs` cues); options given on the command line override it.
            overwrite: replace a finished run in OUT (without it, a finished OUT is an error).
            resume: continue the unfinished run in OUT.partial from its checkpoint (same options).
            load_config: start from the options of an earlier run (its RUN/config.yaml) to repeat it exactly.
            cfg: training options.
        """
        from splat.presets import cue_preset_mismatch, get_preset, unmet_needs
        from splat.train import run
        from splat.train_setup import cue_cloud_path

        log = logging.getLogger("splat")
        cue_cloud_path(cues)  # a missing cue cloud first, before notes on the preset that read the cue folder
        if mismatch := cue_preset_mismatch(preset, cues):
            log.warning("%s", mismatch)
        if why := unmet_needs(preset, scene, cues):
            log.warning("--preset %s trains as another row on this scene (%s): `splat ablate` reports it n/a",
                        preset, why)
        factor = get_preset(preset).iters_factor
        if factor != 1.0 and iters_given:  # the preset's factor applies to the given --iters, as in ablate
            cfg = dataclasses.replace(cfg, iters=max(1, round(cfg.iters * factor)))
            log.info("--preset %s: %g x --iters = %d iterations", preset, factor, cfg.iters)
        run(cfg, scene, cues, out, overwrite=overwrite, resume=resume)
        print(f"wrote {out}/report.json")
        return exit_status(out)

    return train


def train_command(argv: list[str]):
    name = option_from_argv(argv, "--preset") or "full"
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    config = option_from_argv(argv, "--load-config")
    if config is not None and option_from_argv(argv, "--preset") is not None:
        raise ValueError("give --preset or --load-config, not both")
    return _train_command(name, Path(config) if config else None, option_from_argv(argv, "--iters") is not None)


train = _train_command()
train.from_argv = train_command  # dispatch picks the preset's defaults before parsing


def ablate(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
           cues: Annotated[Path, tyro.conf.arg(aliases=("-c",))],
           out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
           overwrite: bool = False,
           cfg: Annotated[AblateConfig, tyro.conf.arg(name="")] = AblateConfig()) -> int:
    """The paper's ablation (Tab. 3) on SCENE: one `splat train` per row, meshes scored at checkpoints.

    Writes OUT/report.md (the table, deltas against `full`, the floor), OUT/accuracy_vs_time.png and
    OUT/ablation.json. Running it again resumes: finished rows are skipped, a killed row continues
    from its checkpoint. Any `splat train` option after these applies to every row (e.g. --downscale 2
    --strategy.max-gaussians 100000). -v/--verbose: debug logging.

    Args:
        scene: scene folder (COLMAP model, images/, optional priors/, gt/mesh.ply or --gt).
        cues: cue folder from `geocues extract`.
        out: output folder (rows/, floor/ and floor_<row>/, reports).
        overwrite: start again from nothing: remove OUT's rows, floors and reports first (without it
            a re-run resumes).
        cfg: ablation options.
    """
    raise AssertionError("parsed by ablate_main")  # pragma: no cover


def ablate_main(argv: list[str]) -> int:
    """Parse the ablation's own options; everything tyro does not know goes to `splat train`."""
    from splat.ablate import run

    args, train_args = tyro.cli(_ablate_args, args=argv, prog="splat ablate", return_unknown_args=True)
    scene, cues, out, overwrite, cfg = args
    run(cfg, scene, cues, out, overwrite=overwrite, train_args=train_args)
    print(f"wrote {out}/report.md, {out}/accuracy_vs_time.png, {out}/ablation.json")
    return 0


def _ablate_args(scene: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SCENE")],
                 cues: Annotated[Path, tyro.conf.arg(aliases=("-c",))],
                 out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
                 overwrite: bool = False,
                 cfg: Annotated[AblateConfig, tyro.conf.arg(name="")] = AblateConfig()):
    return scene, cues, out, overwrite, cfg


_ablate_args.__doc__ = ablate.__doc__
ablate.run_argv = ablate_main


def render(run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")],
           out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
           overwrite: bool = False,
           cfg: Annotated[RenderConfig, tyro.conf.arg(name="")] = RenderConfig()) -> int:
    """Render a finished run's views: RGB, colour-mapped depth, normals and alpha, with GT and priors
    beside them in OUT/panels/, and with --video an MP4 along the camera path.

    Args:
        run: a finished `splat train` folder.
        out: output folder (default RUN/renders).
        overwrite: replace earlier renders in OUT.
        cfg: what to render.
    """
    from splat.render_run import run as render_run

    done = render_run(cfg, run, out, overwrite=overwrite)
    print(f"wrote {done}/ (rgb, depth, normal, alpha, panels" + (", video.mp4)" if cfg.video else ")"))
    return 0


def mesh(run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")],
         out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
         overwrite: bool = False,
         cfg: Annotated[MeshRunConfig, tyro.conf.arg(name="")] = MeshRunConfig()) -> int:
    """Fuse a finished run's Gaussians into a mesh again with other TSDF settings (no training):
    voxel size, weight threshold, median or expected rendered depth.

    Args:
        run: a finished `splat train` folder.
        out: the mesh to write (default RUN/mesh_<depth>_w<weight-threshold>[_<tag><value>...].ply: every
            option that changes the surface tagged, docs/meshing.md; not one of the run's own files).
        overwrite: replace OUT if it exists.
        cfg: which views and how to fuse them.
    """
    from splat.mesh_run import run as mesh_run

    print(f"wrote {mesh_run(cfg, run, out, overwrite=overwrite)}")
    return 0


@contextlib.contextmanager
def _signals_deferred():
    """Within the block the first SIGINT or SIGTERM is recorded, not raised: a KeyboardInterrupt raised
    inside a library's start-up (viser's server threads) can be swallowed there, and the command
    served on as if never stopped. A second one raises at once (a slow load can still be stopped).
    Yields the list of signals received; the old handlers are back after."""
    import signal

    received: list[int] = []
    old = {}

    def record(signum, _frame):
        received.append(signum)
        if len(received) > 1:
            raise KeyboardInterrupt(signal.Signals(signum).name)

    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, record)
    except ValueError:  # not the main thread: nothing to defer
        pass
    try:
        yield received
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def view(run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")],
         screenshot: Annotated[Path | None, tyro.conf.arg(metavar="PNG")] = None,
         size: tuple[int, int] = (1280, 720),
         overwrite: bool = False,
         cfg: Annotated[ViewConfig, tyro.conf.arg(name="")] = ViewConfig()) -> int:
    """Look at a finished run in the browser (viser): Gaussians, mesh, cues by type, 3D lines and
    cameras, each behind a checkbox; serves until Ctrl-C.

    Args:
        run: a finished `splat train` folder.
        screenshot: instead of serving, save the page as headless Chromium draws it (software WebGL)
            to this PNG and exit.
        size: width and height of --screenshot.
        overwrite: replace the --screenshot PNG if it exists.
        cfg: what to show and where to serve.
    """
    from geocues.atomic import check_output_file
    from splat.viewer import LAST_GUI_TEXT, serve, stop, url_of
    from splat.viewer import run as view_run

    if screenshot is not None:
        if screenshot.suffix.lower() != ".png":  # Chromium writes PNG data (a .jpg name held a PNG)
            raise ValueError(f"--screenshot {screenshot}: the screenshot is a PNG; name it .png")
        if min(size) < 16 or max(size) > 16384:  # 0 0 hung until killed, -5 was a DevTools traceback
            raise ValueError(f"--size must be two whole pixels in 16..16384, got {size[0]} {size[1]}")
        check_output_file(screenshot, overwrite)

    try:
        with _signals_deferred() as stopped:  # a Ctrl-C inside viser's start-up was lost (it served on)
            server = view_run(cfg, run, block=False)
    except KeyboardInterrupt as exc:  # the second one: view_run stops what it started on the way out
        print("viewer stopped while loading")
        return exit_code(exc)
    if stopped:
        stop(server)
        print("viewer stopped while loading")
        return 128 + int(stopped[0])  # 130 Ctrl-C, 143 SIGTERM, as a shell reports a process a signal ended
    if screenshot is None:
        try:  # a Ctrl-C between the print and serve()'s own handler must stop the server too,
            # or its threads keep the process alive
            print(f"viewer of {run} at {url_of(server)} (Ctrl-C to stop)", flush=True)
            serve(server)
        except KeyboardInterrupt:
            stop(server)
        print("viewer stopped")
        return 0
    from splat.browser_shot import screenshot as take

    try:
        take(url_of(server), screenshot, width=size[0], height=size[1], wait_for_text=LAST_GUI_TEXT)
    finally:
        stop(server)
    print(f"wrote {screenshot}")
    return 0


# Add commands here as {name: function}; each function's typed signature is its CLI (tyro).
COMMANDS: dict = {"bench": bench, "train": train, "ablate": ablate, "render": render, "mesh": mesh, "view": view}


def main(argv: list[str] | None = None) -> int:
    return dispatch("splat", COMMANDS, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
