"""`splat` console script: training, rendering and rasterizer benchmarks."""

from __future__ import annotations

import sys

from cli._dispatch import dispatch

# Add commands here as {name: function}; each function's typed signature is its CLI (tyro).
COMMANDS: dict = {}


def main(argv: list[str] | None = None) -> int:
    return dispatch("splat", COMMANDS, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
