"""Shared subcommand dispatch for the console scripts.

Each console script is a table ``{name: function}``; a function's signature (typed arguments and
dataclass configs with field docstrings) is its CLI, parsed by tyro. A script may also have a
default command, run when the first argument is not a subcommand name (``evaluate MESH --gt GT``).
"""

from __future__ import annotations

import contextlib
import difflib
import logging
import math
import os
import re
import signal
import sys
import time
from typing import Callable

import tyro

from cli._signals import exit_code, sigterm_as_interrupt
from geocues.logs import LevelFormatter


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at emit time (pytest swaps it between tests)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        pass


GLOBAL_HELP = ("global options (every command): -v/--verbose debug logging and tracebacks; "
               "-q/--quiet warnings and errors only, no progress bars (before or after the command)")


@contextlib.contextmanager
def _tqdm_defaults(**defaults):
    """Within the block every tqdm bar created takes ``defaults`` (modules hold the class itself, so
    its constructor's defaults are changed; TQDM_* variables are only read at import); restored
    after, so one command's bars do not change the next one's in the same process."""
    from functools import partialmethod

    import tqdm

    init = tqdm.tqdm.__init__
    tqdm.tqdm.__init__ = partialmethod(init, **defaults)
    try:
        yield
    finally:
        tqdm.tqdm.__init__ = init


def progress_bars_off():
    """Within the block every tqdm bar is disabled (`-q`)."""
    return _tqdm_defaults(disable=True)


LOG_PROGRESS_INTERVAL_S = 30.0  # with stderr in a file or a pipe: a bar's line at most this often
_clock = time.monotonic


class _ProgressLines:
    """tqdm's file when stderr is a log, not a terminal: each refresh a line of its own (tqdm redraws
    one line with carriage returns and cursor moves, which a log file keeps as one huge line)."""

    encoding = "utf-8"
    _ansi = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
    _count = re.compile(r"(?:^|\s)\d")  # where a bar's description ends: its percentage or count

    def __init__(self) -> None:
        self._first: dict[str, float] = {}  # per bar (its description): when it was first drawn,
        self._last: dict[str, float] = {}  # when a line of it was last written,
        self._held: dict[str, str] = {}  # its latest line not written,
        self._said: dict[str, str] = {}  # and its last line written

    def write(self, s: str) -> None:
        # tqdm's mininterval and delay do not hold back an explicit refresh (set_postfix: a training's
        # log step drew a line every 1-3 s), so the same limits are kept here, per bar. A bar that
        # closes writes its last state and then a lone newline: the last line held back is written then.
        text = self._ansi.sub("", s).replace("\r", "\n")
        if not text.strip() and "\n" in text and self._held:
            for key, line in list(self._held.items()):
                repeat = line.split(" [")[0] == self._said.get(key, "").split(" [")[0]  # same count as written
                if _clock() - self._first.get(key, 0.0) >= LOG_PROGRESS_INTERVAL_S and not repeat:
                    self._emit(key, line)
            self._held.clear()
            return
        for line in text.split("\n"):
            if not line.strip():
                continue
            key = self._count.split(line, 1)[0].strip()
            now, every = _clock(), LOG_PROGRESS_INTERVAL_S
            if now - self._first.setdefault(key, now) < every or now - self._last.get(key, -math.inf) < every:
                self._held[key] = line  # work shorter than the interval, or a line too soon after the last
                continue
            self._emit(key, line)

    def _emit(self, key: str, line: str) -> None:
        self._held.pop(key, None)
        self._last[key], self._said[key] = _clock(), line
        sys.stderr.write(line.rstrip() + "\n")

    def flush(self) -> None:
        sys.stderr.flush()

    def isatty(self) -> bool:
        return False


def progress_bars_as_lines():
    """Within the block every tqdm bar writes whole lines, at most one per bar every
    ``LOG_PROGRESS_INTERVAL_S`` seconds and none for work shorter than that: what a log of a
    redirected command should hold."""
    return _tqdm_defaults(file=_ProgressLines(), mininterval=LOG_PROGRESS_INTERVAL_S,
                          delay=LOG_PROGRESS_INTERVAL_S, ascii=True, ncols=100)


def _progress_mode(quiet: bool):
    if quiet:
        return progress_bars_off()
    try:
        terminal = sys.stderr.isatty()
    except (AttributeError, ValueError):  # a closed or stand-in stream
        terminal = False
    return contextlib.nullcontext() if terminal else progress_bars_as_lines()


def setup_logging(verbose: bool = False, quiet: bool = False) -> None:
    """Route the package loggers to stderr; the library itself never configures logging."""
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    handler = _StderrHandler()
    handler.setFormatter(LevelFormatter())
    for name in ("geocues", "splat", "evaluation"):
        logger = logging.getLogger(name)
        logger.setLevel(level)
        if not logger.handlers:
            logger.addHandler(handler)


def summary(doc: str | None, width: int = 100) -> str:
    """The first sentence of a docstring's first paragraph (which may wrap over lines), cut at a word
    with "..." when longer than ``width``: a command's line in the usage."""
    para = " ".join((doc or "").strip().split("\n\n")[0].split())
    sentence = para
    for m in re.finditer(r"(\S+)\. ", para):  # a period after an abbreviation (Tab., e.g.) ends nothing
        word = m.group(1).lstrip("([{`'\"").lower()
        if word not in ("tab", "fig", "figs", "eq", "sec", "cf", "vs", "etc", "no") and "." not in word:
            sentence = para[:m.end() - 1]
            break
    return sentence if len(sentence) <= width else sentence[:width].rsplit(" ", 1)[0].rstrip(",;:(") + " ..."


def _looks_like_a_command(word: str) -> bool:
    """A word with no path separator, no suffix and no file of its name: a command, not a path."""
    return (not word.startswith("-") and "/" not in word and os.sep not in word and "." not in word
            and not os.path.exists(word))


def _usage(prog: str, commands: dict[str, Callable], default: str | None) -> str:
    lines = [f"usage: {prog} COMMAND [ARGS...]   ({prog} COMMAND --help for its options)", "", "commands:"]
    col = max(14, *(len(name) + 1 for name in commands))
    for name, fn in commands.items():
        lines.append(f"  {name:<{col}} {summary(fn.__doc__)}")
    if default is not None:
        lines.append(f"\nWith no command name, `{prog} ARGS...` runs `{default}`.")
    lines.append("\n" + GLOBAL_HELP)
    return "\n".join(lines)


def dispatch(prog: str, commands: dict[str, Callable], default: str | None = None,
             argv: list[str] | None = None) -> int:
    """Pick the subcommand from ``argv[0]`` and let tyro parse the rest against its signature."""
    try:
        return _dispatch(prog, commands, default, argv)
    except BrokenPipeError:  # `splat ablate --help | head`: the reader left; stop quietly as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return 1


def _dispatch(prog: str, commands: dict[str, Callable], default: str | None,
              argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    lead = []  # `geocues -q undistort ...`: the global flags before the command too
    while argv and argv[0] in ("--verbose", "-v", "--quiet", "-q"):
        lead.append(argv.pop(0))
    if not argv or argv[0] in ("-h", "--help"):
        if default is not None and argv:
            # `evaluate --help` shows the default command's options after the command list.
            print(_usage(prog, commands, default) + "\n")
            tyro.cli(commands[default], args=["--help"], prog=prog)
        print(_usage(prog, commands, default))
        return 0 if argv else 2
    if argv[0] in commands:
        name, rest = argv[0], argv[1:]
    elif default is not None and _looks_like_a_command(argv[0]):
        # `evaluate views --help`: a bare word that is no file is a mistyped command, not a path for
        # the default command (whose usage would be shown, the word taken for its first argument)
        near = difflib.get_close_matches(argv[0], list(commands), n=1)
        print(f"{prog}: unknown command {argv[0]!r}{f' (did you mean {near[0]!r}?)' if near else ''}; "
              f"`{prog} PATH ...` runs `{default}` on a file\n\n" + _usage(prog, commands, default), file=sys.stderr)
        return 2
    elif default is not None:
        name, rest = default, argv
    else:
        near = difflib.get_close_matches(argv[0], list(commands), n=1)
        print(f"{prog}: unknown command {argv[0]!r}{f' (did you mean {near[0]!r}?)' if near else ''}\n\n"
              + _usage(prog, commands, default), file=sys.stderr)
        return 2
    rest = lead + rest
    fn = commands[name]
    sub_prog = prog if (name == default and argv[0] != name) else f"{prog} {name}"
    verbose = "--verbose" in rest or "-v" in rest
    quiet = "--quiet" in rest or "-q" in rest
    setup_logging(verbose, quiet)
    rest = [a for a in rest if a not in ("--verbose", "-v", "--quiet", "-q")]
    if "-h" in rest or "--help" in rest:
        try:
            tyro.cli(fn.from_argv(rest) if hasattr(fn, "from_argv") else fn, args=rest, prog=sub_prog)
        except SystemExit:
            print(GLOBAL_HELP)
            return 0
    old_sigterm = sigterm_as_interrupt()
    try:
        with _progress_mode(quiet):
            return _run(fn, rest, sub_prog, verbose)
    finally:
        if old_sigterm is not None:
            signal.signal(signal.SIGTERM, old_sigterm)


def _run(fn: Callable, rest: list[str], sub_prog: str, verbose: bool) -> int:
    try:
        if hasattr(fn, "run_argv"):  # the command parses its own argv (e.g. passes options through)
            result = fn.run_argv(rest)
        else:
            if hasattr(fn, "from_argv"):  # the command's defaults depend on an option (--preset)
                fn = fn.from_argv(rest)
            result = tyro.cli(fn, args=rest, prog=sub_prog)
    except (FileNotFoundError, ValueError, PermissionError, IsADirectoryError, NotADirectoryError) as exc:
        # Bad input: one clear line naming what is wrong, no traceback (-v shows it).
        if verbose:
            raise
        print(f"{sub_prog}: error: {exc}", file=sys.stderr)
        return 1
    except RuntimeError as exc:
        # A run that stopped cleanly: interrupted (checkpoint written) or diverged (last good kept).
        name = type(exc).__name__
        if name == "TrainingInterrupted":
            print(f"{sub_prog}: {exc}", file=sys.stderr)
            return exc.exit_code
        if name == "TrainingDiverged":
            print(f"{sub_prog}: error: {exc}", file=sys.stderr)
            return 1
        raise
    except KeyboardInterrupt as exc:
        # Ctrl-C in a command without a checkpoint of its own: every output is written atomically,
        # so what exists is complete; the same command again redoes the rest. Exit 128 + the
        # signal's number (130 Ctrl-C, 143 SIGTERM), as a shell reports a process the signal ended.
        if verbose:
            raise
        print(f"{sub_prog}: interrupted; finished outputs are kept, run the same command again to "
              "redo the rest", file=sys.stderr)
        return exit_code(exc)
    return int(result) if isinstance(result, int) else 0


def option_from_argv(argv: list[str], name: str) -> str | None:
    """The value of option ``name`` in ``argv`` (``NAME VALUE`` or ``NAME=VALUE``), or None: for commands
    whose defaults depend on an option (``--preset``) before tyro parses. Given twice with two values it
    is an error (`--preset room --preset paper` ran room, the first)."""
    values = []
    for k, a in enumerate(argv):
        if a == name and k + 1 < len(argv):
            values.append(argv[k + 1])
        elif a.startswith(name + "="):
            values.append(a.split("=", 1)[1])
    if len(set(values)) > 1:
        raise ValueError(f"{name} is given {len(values)} times ({', '.join(values)}): give it once")
    return values[0] if values else None
