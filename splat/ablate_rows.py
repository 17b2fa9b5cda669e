"""The folder of one ablation row run (``OUT/rows/<row>_s<seed>``): whether it holds a finished run
of a row key (its score.json), a finished training, or a checkpoint of the same options to resume;
runs of other options are set aside beside it (``.outdated``, ``.outdated-2``, ...) and put back when
their options come back (splat/ablate.py)."""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path

from splat.ablate_keys import row_keys

log = logging.getLogger("splat.ablate")


def trained(train_dir: Path, spec: dict) -> bool:
    """Whether ``train_dir`` holds a finished `splat train` run of this row (same key)."""
    try:
        config = json.loads((train_dir / "report.json").read_text())["config"]
    except (OSError, ValueError, KeyError):
        return False
    try:
        return bool(set(row_keys({**spec, "train_config": config})) & set(spec.get("keys", [spec["key"]])))
    except (KeyError, TypeError):  # a report of another layout
        return False


def resumable(train_dir: Path, cfg) -> bool:
    """Whether ``train_dir``'s unfinished run left a checkpoint of exactly this configuration
    (a row killed half-way continues from it instead of starting over)."""
    from splat import checkpoint
    from splat.checkpoint import staging_dir

    path = staging_dir(train_dir) / checkpoint.CKPT_NAME
    if not path.is_file():
        return False
    try:
        saved = checkpoint.load(path)["config"]
    except Exception as exc:  # a checkpoint cut short by the kill: the row starts again
        log.warning("%s cannot be read (%s): the row starts again", path, exc)
        return False
    same = not checkpoint.config_diff(asdict(cfg), saved, asdict(type(cfg)()))
    if not same:
        log.warning("%s was written with other options: the row starts again", path)
    return same


def set_aside(out: Path) -> Path:
    """Move the row folder ``out`` to the first free ``<row>_s<seed>.outdated[-N]`` beside it (a
    second change of options deleted the first one kept aside: a finished run lost)."""
    aside, n = out.with_name(out.name + ".outdated"), 1
    while aside.exists():
        n += 1
        aside = out.with_name(f"{out.name}.outdated-{n}")
    out.rename(aside)
    return aside


def restore_set_aside(out: Path, keys: list[str]) -> dict | None:
    """A run set aside earlier whose options are these again (back to the old options) is put back in
    place of ``out`` (which is set aside in turn), instead of training it again; its score or None."""
    for aside in sorted(out.parent.glob(out.name + ".outdated*")):
        if aside.is_dir() and done(aside, keys) is not None:
            if out.exists():
                log.warning("%s holds a row run of other options: moved to %s", out, set_aside(out))
            aside.rename(out)
            log.info("%s: the run of these options set aside earlier (%s) is back", out, aside.name)
            return done(out, keys)
    return None


def done(out: Path, keys: list[str]) -> dict | None:
    """The score.json of the finished run in ``out`` when its key is one of ``keys``, else None."""
    path = out / "score.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except ValueError:
        return None
    return data if data.get("key") in keys else None


__all__ = ["done", "restore_set_aside", "resumable", "set_aside", "trained"]
