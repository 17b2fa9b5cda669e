"""`splat` console script: training, rendering and rasterizer benchmarks."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import tyro

from cli._dispatch import dispatch
from splat.bench import BenchConfig
from splat.train import TrainConfig


def bench(json: Annotated[Path | None, tyro.conf.arg(metavar="OUT")] = None,
          cfg: Annotated[BenchConfig, tyro.conf.arg(name="")] = BenchConfig()) -> int:
    """Time render() forward + backward per compositing backend, image size and Gaussian count.

    Args:
        json: write the results (every run, machine, load average) to this JSON file.
    """
    from splat.bench import format_table, run_bench

    result = run_bench(cfg, json_out=json)
    print(format_table(result))
    if json is not None:
        print(f"wrote {json}")
    return 0


def train(scene: tyro.conf.Positional[Path],
          cues: Annotated[Path, tyro.conf.arg(aliases=("-c",))],
          out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
          cfg: Annotated[TrainConfig, tyro.conf.arg(name="")] = TrainConfig()) -> int:
    """Train typed Gaussians on SCENE from the cue cloud CUES, then fuse a TSDF mesh (IndoorGS §4).

    Writes OUT/point_cloud.ply (3DGS format), OUT/mesh.ply, OUT/test_renders/, OUT/train_log.jsonl and
    OUT/report.json (test PSNR/SSIM at checkpoints against training seconds, timings per stage).

    Args:
        scene: scene folder (COLMAP model, images/, optional priors/).
        cues: cue folder from `geocues extract` (or its cues.ply).
        out: output folder.
        cfg: training options.
    """
    from splat.train import run

    run(cfg, scene, cues, out)
    print(f"wrote {out}/report.json")
    return 0


# Add commands here as {name: function}; each function's typed signature is its CLI (tyro).
COMMANDS: dict = {"bench": bench, "train": train}


def main(argv: list[str] | None = None) -> int:
    return dispatch("splat", COMMANDS, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
