"""Warnings a process gives once, however often the code that finds them runs (a scene loaded once per
ablation row, a backend fallback at every render)."""

from __future__ import annotations

import logging

_SAID: set[tuple[str, str]] = set()


def warn_once(logger: logging.Logger, sentence: str) -> None:
    """``logger.warning(sentence)`` the first time this logger meets this sentence in the process."""
    key = (logger.name, sentence)
    if key not in _SAID:
        _SAID.add(key)
        logger.warning("%s", sentence)
