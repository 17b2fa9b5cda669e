"""The console scripts' entry points (pyproject.toml ``[project.scripts]``). A command table imports
torch, scipy, Open3D and pycolmap before it parses anything (about two seconds): a Ctrl-C or a
SIGTERM in that time ends with one line and exit code 130 (143 for SIGTERM), as it does once the
command runs, not with a traceback of an import (nor, for SIGTERM, without a word); with -v the
traceback is shown."""

from __future__ import annotations

import importlib
import sys

from cli._signals import exit_code, sigterm_as_interrupt


def _run(prog: str, module: str) -> int:
    verbose = "-v" in sys.argv[1:] or "--verbose" in sys.argv[1:]
    try:
        sigterm_as_interrupt(import_pycolmap=False)  # before the imports ...
        main = importlib.import_module(module).main
        sigterm_as_interrupt()  # ... and again after pycolmap's glog replaced it
    except KeyboardInterrupt as exc:
        if verbose:
            raise
        print(f"{prog}: interrupted while starting", file=sys.stderr)
        return exit_code(exc)
    try:
        return main()
    except KeyboardInterrupt as exc:  # before the command's own handling (it parses, sets up logging)
        if verbose:  # the command's own handling re-raises with -v to show where
            raise
        print(f"{prog}: interrupted while starting", file=sys.stderr)
        return exit_code(exc)


def geocues() -> int:
    return _run("geocues", "cli.geocues_cli")


def splat() -> int:
    return _run("splat", "cli.splat_cli")


def evaluate() -> int:
    return _run("evaluate", "cli.evaluate_cli")
