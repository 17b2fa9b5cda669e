"""The console scripts' entry points (pyproject.toml ``[project.scripts]``). A command table imports
torch, scipy, Open3D and pycolmap before it parses anything (about two seconds): a Ctrl-C or a
SIGTERM in that time ends with one line and exit code 130 (143 for SIGTERM), as it does once the
command runs, not with a traceback of an import (nor, for SIGTERM, without a word)."""

from __future__ import annotations

import importlib
import signal
import sys


def _interrupt(signum, _frame) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def _catch_sigterm() -> None:
    try:
        signal.signal(signal.SIGTERM, _interrupt)
    except ValueError:  # not the main thread (an embedding application): leave its handlers alone
        pass


def _code(exc: KeyboardInterrupt) -> int:
    return 143 if exc.args and exc.args[0] == "SIGTERM" else 130


def _run(prog: str, module: str) -> int:
    _catch_sigterm()
    try:
        main = importlib.import_module(module).main
        try:  # its glog replaces the SIGTERM handler when imported: import it here, then catch again
            import pycolmap  # noqa: F401
        except ImportError:
            pass
        _catch_sigterm()
    except KeyboardInterrupt as exc:
        print(f"{prog}: interrupted while starting", file=sys.stderr)
        return _code(exc)
    try:
        return main()
    except KeyboardInterrupt as exc:  # before the command's own handling (it parses, sets up logging)
        print(f"{prog}: interrupted while starting", file=sys.stderr)
        return _code(exc)


def geocues() -> int:
    return _run("geocues", "cli.geocues_cli")


def splat() -> int:
    return _run("splat", "cli.splat_cli")


def evaluate() -> int:
    return _run("evaluate", "cli.evaluate_cli")
