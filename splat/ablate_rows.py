"""The folder of one ablation row run (``OUT/rows/<row>_s<seed>``): whether it holds a finished run
of a row key (its score.json), a finished training, or a checkpoint of the same options to resume;
runs of other options (finished, or killed with a checkpoint) are set aside beside it (``.outdated``,
``.outdated-2``, ...) and put back when their options come back: a finished one is skipped, a killed
one resumes from its checkpoint (splat/ablate.py)."""

from __future__ import annotations

import json
import logging
import shutil
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


def resumable(train_dir: Path, cfg, quiet: bool = False) -> bool:
    """Whether ``train_dir``'s unfinished run left a checkpoint of exactly this configuration
    (a row killed half-way continues from it instead of starting over); ``quiet``: no warning for a
    checkpoint of other options (looking through the runs set aside)."""
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
    if not same and not quiet:
        log.warning("%s was written with other options: that run is set aside and the row starts again", path)
    return same


def has_checkpoint(out: Path) -> bool:
    """Whether the row folder ``out`` holds an unfinished training's checkpoint (work a kill left)."""
    from splat import checkpoint
    from splat.checkpoint import staging_dir

    return (staging_dir(out / "train") / checkpoint.CKPT_NAME).is_file()


def clear(out: Path) -> None:
    """Make room for a new run in the row folder ``out``: set aside what holds work (a finished row, a
    checkpoint), remove the rest (a run killed before its first checkpoint)."""
    if not out.exists():
        return
    if (out / "score.json").is_file() or has_checkpoint(out):
        log.warning("%s holds a row run of other options: moved to %s", out, set_aside(out))
    else:
        shutil.rmtree(out)


def restore_resumable(out: Path, cfg) -> bool:
    """A killed run set aside earlier whose checkpoint has exactly these options is put back in place
    of ``out`` (whose run is set aside in turn) to resume from it, instead of training from step 0."""
    for aside in sorted(out.parent.glob(out.name + ".outdated*")):
        if aside.is_dir() and not (aside / "score.json").is_file() and resumable(aside / "train", cfg, quiet=True):
            clear(out)
            aside.rename(out)
            log.info("%s: the unfinished run of these options set aside earlier (%s) is back", out, aside.name)
            return True
    return False


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
            clear(out)
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


__all__ = ["clear", "done", "has_checkpoint", "restore_resumable", "restore_set_aside", "resumable", "set_aside",
           "trained"]
