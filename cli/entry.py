"""The console scripts' entry points (pyproject.toml ``[project.scripts]``). A command table imports
torch, scipy and Open3D before it parses anything (about two seconds): a Ctrl-C in that time ends
with one line and exit code 130, as it does once the command runs, not with a traceback of an import."""

from __future__ import annotations

import importlib
import sys


def _run(prog: str, module: str) -> int:
    try:
        main = importlib.import_module(module).main
    except KeyboardInterrupt:
        print(f"{prog}: interrupted while starting", file=sys.stderr)
        return 130
    return main()


def geocues() -> int:
    return _run("geocues", "cli.geocues_cli")


def splat() -> int:
    return _run("splat", "cli.splat_cli")


def evaluate() -> int:
    return _run("evaluate", "cli.evaluate_cli")
