"""`evaluate` console script: `evaluate PRED_MESH --gt GT_MESH` (default) and benchmark tools."""

from __future__ import annotations

import sys

from cli._dispatch import dispatch

# Add commands here as {name: function}; each function's typed signature is its CLI (tyro).
# The default command (metrics of a mesh) is registered under "mesh" and runs without its name.
COMMANDS: dict = {}
DEFAULT = None


def main(argv: list[str] | None = None) -> int:
    return dispatch("evaluate", COMMANDS, default=DEFAULT, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
