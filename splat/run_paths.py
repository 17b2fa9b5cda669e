"""The scene and cue paths a `splat train` folder records, found again from anywhere.

RUN/report.json keeps ``scene`` and ``cues`` as absolute paths and ``scene_from_run`` /
``cues_from_run`` relative to RUN, so a run is read from any working folder and still after the
run and its scene moved together. Runs written before both were recorded kept the paths as given on
the command line (relative to the folder training started in); those are tried from the working
folder, then from each folder above RUN."""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)


def record(path: str | Path, run_dir: str | Path) -> dict[str, str]:
    """{"": absolute path, "_from_run": the same relative to ``run_dir``} (keys to prefix with the name)."""
    absolute = Path(path).resolve()
    return {"": str(absolute), "_from_run": os.path.relpath(absolute, Path(run_dir).resolve())}


def recorded_path(run_dir: str | Path, report: dict, key: str) -> Path | None:
    """``report[key]`` (``"scene"`` or ``"cues"``) as a path that exists where one does, else as recorded;
    None when the report has no such entry."""
    if not report.get(key):
        return None
    given = Path(report[key])
    if given.exists():
        return given
    run_dir = Path(run_dir).resolve()
    tries = []
    if report.get(f"{key}_from_run"):
        tries.append(run_dir / report[f"{key}_from_run"])
    if not given.is_absolute():
        tries += [base / given for base in run_dir.parents]
    for path in tries:
        if path.exists():
            log.info("the run's %s %s is not there; using %s", key, given, path)
            return path
    return given


def gaussians_ply(run_dir: str | Path) -> Path:
    """The run's Gaussians: RUN/point_cloud.ply, else the highest RUN/point_cloud/iteration_N/point_cloud.ply
    (the reference layout alone, as SIBR and the reference render.py find it: a run copied without
    the top-level link). FileNotFoundError naming both when neither is there."""
    run_dir = Path(run_dir)
    top = run_dir / "point_cloud.ply"
    if top.is_file():
        return top
    found = []
    for sub in (run_dir / "point_cloud").glob("iteration_*"):
        it = sub.name[len("iteration_"):]
        if it.isdigit() and (sub / "point_cloud.ply").is_file():
            found.append((int(it), sub / "point_cloud.ply"))
    if found:
        return max(found)[1]
    raise FileNotFoundError(f"{run_dir} holds no point_cloud.ply nor point_cloud/iteration_N/point_cloud.ply "
                            "(not a finished `splat train` folder)")
