"""`splat` console script: training, rendering and rasterizer benchmarks."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import tyro

from cli._dispatch import dispatch
from splat.bench import BenchConfig


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


# Add commands here as {name: function}; each function's typed signature is its CLI (tyro).
COMMANDS: dict = {"bench": bench}


def main(argv: list[str] | None = None) -> int:
    return dispatch("splat", COMMANDS, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
