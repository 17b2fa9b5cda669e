"""Log helpers of the packages: warnings a process gives once, however often the code that finds them runs
(a scene loaded once per ablation row, a backend fallback at every render), and the line format of the
command-line tools and of `splat ablate`'s worker processes."""

from __future__ import annotations

import logging

_SAID: set[tuple[str, str]] = set()


def warn_once(logger: logging.Logger, sentence: str) -> None:
    """``logger.warning(sentence)`` the first time this logger meets this sentence in the process."""
    key = (logger.name, sentence)
    if key not in _SAID:
        _SAID.add(key)
        logger.warning("%s", sentence)


LOG_FORMAT = "[%(asctime)s %(name)s] %(level_tag)s%(message)s"
LOG_DATEFMT = "%H:%M:%S"


class LevelFormatter(logging.Formatter):
    """``[12:00:00 splat.train] message``, and ``[12:00:00 splat.train] warning: message`` for warnings and
    errors: in a run's many info lines a warning looked like the others (researcher audit)."""

    def __init__(self) -> None:
        super().__init__(LOG_FORMAT, LOG_DATEFMT)

    def format(self, record: logging.LogRecord) -> str:
        record.level_tag = f"{record.levelname.lower()}: " if record.levelno >= logging.WARNING else ""
        return super().format(record)
