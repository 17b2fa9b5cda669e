"""Ctrl-C and SIGTERM as one thing (imports nothing heavy: cli/entry.py uses it before torch & co.).

SIGTERM (`kill`, a job scheduler) raises ``KeyboardInterrupt("SIGTERM")`` as Ctrl-C raises
``KeyboardInterrupt``; :func:`exit_code` gives a shell's code for either (128 + the signal's number).
pycolmap's glog installs a handler on import that dumps a native stack trace on SIGTERM and replaces
one installed before it, so :func:`sigterm_as_interrupt` imports pycolmap first (where installed).
"""

from __future__ import annotations

import signal


def _interrupt(signum, _frame) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def sigterm_as_interrupt(import_pycolmap: bool = True):
    """Make SIGTERM raise KeyboardInterrupt("SIGTERM"); pycolmap imported first. Returns the handler it
    replaced (None outside the main thread, where nothing is changed)."""
    if import_pycolmap:
        try:
            import pycolmap  # noqa: F401
        except ImportError:
            pass
    try:
        return signal.signal(signal.SIGTERM, _interrupt)
    except ValueError:  # not the main thread (an embedding application): leave its handlers alone
        return None


def exit_code(exc: KeyboardInterrupt) -> int:
    """130 for Ctrl-C, 143 for SIGTERM: 128 + the signal's number, as a shell reports it."""
    return 143 if exc.args and exc.args[0] == "SIGTERM" else 130
