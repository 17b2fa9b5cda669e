"""`splat ablate`: the paper's ablation (Tab. 3) on a user's scene, with accuracy against time.

One stage, one entry: ``run(cfg, scene_dir, cues, out_dir, *, overwrite=False, train_args=None)
-> Path``. Each row is a preset of splat/presets.py run as one `splat train` (meshes at checkpoints)
in ``OUT/rows/<row>_s<seed>/train``, and each checkpoint mesh is scored with the ``evaluate``
protocol against the scene's GT mesh. A row is finished when its ``score.json`` exists (written
atomically, last) with the same configuration key: a re-run skips it, so a killed ablation resumes;
``overwrite`` starts again from nothing (OUT's rows, floors and reports removed first). The ``floor``
row fuses the exact GT depth of the same training views (splat/floor.py) through the default meshing
(with ``train_args``), whatever rows the table holds; a row whose preset meshes otherwise (`mvs`)
also gets the floor of its own meshing (``floors``). ``train_args`` are `splat train` options
applied to every row, on top of its preset. Rows run one after another (``jobs=1``), in ``jobs``
processes, or as Ray tasks (``ray="auto"`` or a cluster address; every node must see OUT, SCENE and
CUES at the same paths).

Results: ``OUT/ablation.json`` and, through evaluation/ablation_report.py, ``OUT/report.md`` and
``OUT/accuracy_vs_time.png``, rewritten after every finished row.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from evaluation.ablation_report import METRICS, row_stats
from evaluation.mesh_metrics import MeshMetricsConfig
from geocues.atomic import atomic_path, check_output_dir, locks_output
from splat import ablate_rows
from splat.ablate_exec import execute
from splat.ablate_keys import config_key, row_keys, training_keys
from splat.checkpoint import TrainingInterrupted
from splat.guard import TrainingDiverged
from splat.presets import (DEFAULT_ROWS, PRESETS, config_from_dict, get_preset, missing_needs, needs_facts,
                           preset_config)

log = logging.getLogger(__name__)

RUN_FIELDS = ("seed", "key", "curve", "final", "train_s", "wall_s", "gaussians_init", "gaussians_final")


@dataclass
class AblateConfig:
    """Options of `splat ablate` (every other option goes to each row's `splat train`)."""

    rows: tuple[str, ...] = DEFAULT_ROWS
    """Presets to run (splat/presets.py; `splat train --preset` takes the same names); default: every
    preset, the paper's rows and this project's extensions (several hours at 3000 iterations on a CPU:
    name the rows you want, e.g. --rows full no-cues)."""
    iters: int = 3000
    """Training iterations of a row (no-cues-long: 3x)."""
    seeds: int = 1
    """Repeat every row with seeds 0..K-1 (rows/<row>_s<seed>); the report gives mean and spread (population std)."""
    jobs: int = 1
    """Rows run in this many processes at once (the cores are shared between them)."""
    num_threads: int = 0
    """torch and Open3D threads per row (0: all cores for --jobs 1, cores / jobs otherwise, 1 per Ray task).
    The same count gives the same rows wherever they run; reductions over another count differ in
    the last bits, which a training amplifies."""
    ray: str | None = None
    """Send every row to a Ray cluster ("auto", "local" or an address); needs `pip install .[ray]`."""
    gt: Path | None = None
    """GT mesh (default: SCENE/gt/mesh.ply)."""
    floor: bool = True
    """Add the `floor` row where exact GT depth exists (SCENE/gt/depth or --gt-depth)."""
    gt_depth: Path | None = None
    """Folder of exact depth maps (<stem>.npy in metres or <stem>.png) for the floor row."""
    gt_depth_png_scale: float = 1000.0
    """PNG depth values per metre (1000: millimetres, as the ICL-NUIM copy in ../shared; its TUM format: 5000).
    A scale that disagrees with the scene's SfM points is warned about."""
    checkpoints: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
    """Fractions of each run at which test views are scored and a mesh is fused and scored."""
    scene_label: str = ""
    """Name of the scene in the report (default: the scene folder's name); say "simulated" here
    when its priors are."""
    metrics: MeshMetricsConfig = field(default_factory=MeshMetricsConfig)


def train_config(row: str, train_args: list[str], iters: int, seed_offset: int, checkpoints) -> Any:
    """The TrainConfig of ``row``: its preset, then ``train_args`` (tyro syntax of `splat train`),
    then the ablation's iterations (times the preset's factor), seed offset and checkpoints."""
    import tyro

    from splat.train_config import TrainConfig

    if any(a == "--iters" or a.startswith("--iters=") for a in train_args):
        raise ValueError("give the iterations as `splat ablate --iters N` (rows scale it), not as a train option")
    if any(a == "--seed" or a.startswith("--seed=") for a in train_args):  # its runs were labelled and kept as seeds 0..K-1
        raise ValueError("give the seeds as `splat ablate --seeds K` (seeds 0..K-1, in rows/<row>_s<seed>), not as "
                         "a train option --seed: its runs would be stored as seeds 0..K-1, over those runs")
    base = preset_config(row, TrainConfig())
    cfg = tyro.cli(TrainConfig, args=list(train_args), default=base, prog="splat ablate (train options)")
    preset = get_preset(row)
    return dataclasses.replace(cfg, iters=max(1, round(iters * preset.iters_factor)), seed=cfg.seed + seed_offset,
                               checkpoints=tuple(checkpoints), mesh=True, mesh_at_checkpoints=True)


def score_mesh(mesh: Path, gt: Path | None, scene: Path, metrics: MeshMetricsConfig) -> dict:
    """The ablation's mesh metrics (:data:`METRICS`) of ``mesh`` against ``gt`` (or the scene's GT
    mesh), culled to ``scene``'s cameras as `evaluate mesh` does."""
    from evaluation.mesh_metrics import evaluate_with_scene

    result = evaluate_with_scene(mesh, gt, scene, metrics).to_dict()
    return {k: result[k] for k in METRICS}


def run_row(spec: dict) -> dict:
    """Train and score one row (a plain function of a JSON-able spec: it runs in a worker process
    or a Ray task as well as here) with ``spec["threads"]`` torch and Open3D threads if given (the
    caller's counts are restored after). Writes ``spec["out"]/score.json`` last and returns it; a
    training that diverged returns ``{"row", "seed", "key", "diverged": message}`` (no score.json:
    the same command tries it again from its last good checkpoint)."""
    import open3d as o3d
    import torch

    before = torch.get_num_threads(), o3d.utility.get_max_threads()
    if spec.get("threads"):  # torch's and Open3D's pools (TSDF fusion, mesh metrics) alike
        torch.set_num_threads(int(spec["threads"]))
        o3d.utility.set_max_threads(int(spec["threads"]))
    try:
        return _run_row(spec)
    except TrainingDiverged as exc:  # the other rows go on; the report and the exit status say so
        return {"row": spec["row"], "seed": spec["seed"], "key": spec["key"], "diverged": str(exc)}
    finally:
        torch.set_num_threads(before[0])
        o3d.utility.set_max_threads(before[1])


def _run_row(spec: dict) -> dict:
    from splat.train import TrainConfig, run as train_run

    out = Path(spec["out"])
    if (out / "score.json").is_file():  # a finished row of another configuration: kept aside, not lost
        aside = ablate_rows.set_aside(out)
        log.warning("%s holds a finished row of another configuration: moved to %s, running it again",
                    out, aside)
    cfg = config_from_dict(TrainConfig, spec["train_config"])
    t0 = time.perf_counter()
    if ablate_rows.trained(out / "train", spec):  # killed while scoring: the finished training is kept
        log.info("%s: its training finished before the kill; scoring it", spec["row"])
        train_wall = None
    else:
        resume = (out.exists() and ablate_rows.resumable(out / "train", cfg)
                  or ablate_rows.restore_resumable(out, cfg))  # a killed run of these options set aside
        if not resume:  # a run of other options is set aside, one killed before its first checkpoint removed
            ablate_rows.clear(out)
        out.mkdir(parents=True, exist_ok=True)
        if resume:
            log.info("%s: resuming the unfinished run from its checkpoint", spec["row"])
        train_run(cfg, spec["scene"], spec["cues"], out / "train", overwrite=True, resume=resume)
        train_wall = time.perf_counter() - t0
    report = json.loads((out / "train" / "report.json").read_text())
    metrics = MeshMetricsConfig(**spec["metrics"])
    gt = Path(spec["gt"]) if spec.get("gt") else None
    curve = []
    for point in report["accuracy_vs_time"]:
        scores = score_mesh(out / "train" / point["mesh"], gt, Path(spec["scene"]), metrics)
        curve.append({k: point[k] for k in ("step", "train_s", "psnr", "ssim", "n_gaussians")} | scores)
    result = {"row": spec["row"], "seed": spec["seed"], "key": spec["key"], "curve": curve,
              "final": curve[-1] if curve else {}, "train_s": report["timings"]["train_s"],
              "wall_s": time.perf_counter() - t0, "train_wall_s": train_wall,
              "gaussians_init": report["gaussians_init"], "gaussians_final": report["gaussians_final"]}
    with atomic_path(out / "score.json") as tmp:
        tmp.write_text(json.dumps(result, indent=2))
    return result


def _floor_setup(cfg: AblateConfig, example, png: float | None) -> dict:
    tsdf = {k: v for k, v in asdict(example.tsdf).items() if k != "smooth_iters" or v}
    return {"views": [example.downscale, example.test_every, example.mesh_every], "tsdf": tsdf,
            "png": cfg.gt_depth_png_scale if png is None else png, "metrics": asdict(cfg.metrics)}


def floor_key(cfg: AblateConfig, example, folder: Path, png: float | None = None) -> str:
    """The floor's key: the views, TSDF settings, exact depth and scoring it was fused and scored with
    (``tsdf.smooth_iters`` left out while unset, so floors fused before the option keep their key)."""
    return config_key(_floor_setup(cfg, example, png) | {"depth": str(folder), "gt": str(cfg.gt)})


def floor_setup_key(cfg: AblateConfig, example, png: float | None = None) -> str:
    """The floor's key without its paths (exact depth folder, GT mesh): what two ablations of one scene
    in other folders or on other machines compare before sharing a table (merge_summaries)."""
    return config_key(_floor_setup(cfg, example, png))


def _run_floor(cfg: AblateConfig, scene_dir: Path, out_dir: Path, example, name: str = "floor") -> dict | None:
    from splat.floor import find_gt_depth_dir, fuse_floor, recorded_gt_depth

    if not cfg.floor:
        return None
    folder, png = find_gt_depth_dir(scene_dir, cfg.gt_depth), cfg.gt_depth_png_scale
    if folder is None and (recorded := recorded_gt_depth(scene_dir)) is not None:  # simulate-priors' source
        folder, png = recorded
        log.info("floor: the exact depth %s that %s records", folder, scene_dir)
    if folder is None:
        log.warning("floor: %s has no gt/depth and no --gt-depth was given: the table has no floor row", scene_dir)
        return {"status": "n/a", "reason": "no GT depth"}
    key, setup = floor_key(cfg, example, folder, png), floor_setup_key(cfg, example, png)
    out = out_dir / name
    done = ablate_rows.done(out, [key])
    if done is not None:
        return done | {"setup": setup}  # fused before floors kept it: the same settings (the key matched)
    t0 = time.perf_counter()
    mesh = fuse_floor(scene_dir, out / "mesh.ply", gt_depth=folder, png_scale=png,
                      downscale=example.downscale, test_every=example.test_every,
                      mesh_every=example.mesh_every, tsdf=example.tsdf)
    result = {"row": name, "status": "done", "key": key, "setup": setup, "depth_dir": str(folder), "png_scale": png,
              "final": score_mesh(mesh, cfg.gt, scene_dir, cfg.metrics), "wall_s": time.perf_counter() - t0}
    with atomic_path(out / "score.json") as tmp:
        tmp.write_text(json.dumps(result, indent=2))
    return result


def plan(cfg: AblateConfig, scene_dir: Path, cues: Path, out_dir: Path, train_args: list[str]
         ) -> tuple[list[dict], dict[str, str]]:
    """Row specs to run (one per row and seed) and the rows that are n/a on this scene (with why)."""
    from geocues.scene import Scene

    unknown = [r for r in cfg.rows if r not in PRESETS]
    if unknown:
        raise ValueError(f"unknown rows {unknown}; choose from {', '.join(PRESETS)}")
    if cfg.num_threads < 0:
        raise ValueError(f"--num-threads must be >= 0, got {cfg.num_threads}")
    if cfg.seeds < 1 or cfg.jobs < 1 or cfg.iters < 1:
        raise ValueError(f"--seeds, --jobs and --iters must be >= 1 (got {cfg.seeds}, {cfg.jobs}, {cfg.iters})")
    scene = Scene.load(scene_dir, check_priors=False)
    facts = needs_facts(scene, cues)
    specs, na = [], {}
    for row in dict.fromkeys(cfg.rows):
        why = missing_needs(get_preset(row), *facts)
        if why is not None:
            na[row] = why
            continue
        for s in range(cfg.seeds):
            tcfg = train_config(row, train_args, cfg.iters, s, cfg.checkpoints)
            spec = {"row": row, "seed": s, "scene": str(scene_dir), "cues": str(cues),
                    "gt": str(cfg.gt) if cfg.gt else None, "metrics": asdict(cfg.metrics),
                    "train_config": asdict(tcfg), "out": str(out_dir / "rows" / f"{row}_s{s}")}
            spec["keys"] = row_keys(spec)
            spec["key"] = spec["keys"][0]
            specs.append(spec)
    return specs, na


# What an ablation writes into OUT: what ``overwrite`` removes (nothing else a user put there).
OUTPUTS = ("rows", "floor", "ablation.json", "report.md", "accuracy_vs_time.png")


def run_floors(cfg: AblateConfig, scene_dir: Path, out_dir: Path, train_args: list[str],
               rows: list[str]) -> tuple[dict | None, dict[str, dict]]:
    """The floor (exact GT depth through the default meshing with ``train_args``: the same whatever
    rows a table holds) and, for each row of ``rows`` whose preset meshes otherwise (the `mvs`
    recipe's TSDF), the floor through that row's meshing, in OUT/floor_<row> (one per meshing)."""
    floor = _run_floor(cfg, scene_dir, out_dir, train_config("full", train_args, cfg.iters, 0, cfg.checkpoints))
    if floor is None or floor.get("status") != "done":
        return floor, {}
    folder = Path(floor["depth_dir"])
    by_key: dict[str, dict] = {floor["key"]: floor}
    floors = {}
    for row in rows:
        row_cfg = train_config(row, train_args, cfg.iters, 0, cfg.checkpoints)
        key = floor_key(cfg, row_cfg, folder, floor.get("png_scale"))
        if key not in by_key:
            by_key[key] = _run_floor(cfg, scene_dir, out_dir, row_cfg, name=f"floor_{row}")
        if key != floor["key"]:
            floors[row] = by_key[key]
    return floor, floors


@locks_output("splat ablate")  # two ablations into one OUT trained the same rows at once
def run(cfg: AblateConfig, scene_dir: str | Path, cues: str | Path, out_dir: str | Path, *,
        overwrite: bool = False, train_args: list[str] | None = None) -> Path:
    """Run the ablation, or resume it (finished rows skipped, a killed row continued from its
    checkpoint); with ``overwrite`` start again from nothing. Writes OUT/ablation.json, report.md
    and the plots; returns OUT. ``train_args``: `splat train` options for every row."""
    from evaluation.ablation_report import write_reports

    scene_dir, cues, out_dir = Path(scene_dir).resolve(), Path(cues).resolve(), Path(out_dir).resolve()
    train_args = list(train_args or [])
    check_output_dir(out_dir)
    specs, na = plan(cfg, scene_dir, cues, out_dir, train_args)  # bad options fail before anything is removed
    if overwrite:
        _remove_outputs(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict[tuple[str, int], dict] = {}
    todo = []
    for spec in specs:
        out = Path(spec["out"])
        done = ablate_rows.done(out, spec["keys"]) or ablate_rows.restore_set_aside(out, spec["keys"])
        if done is not None:
            log.info("row %s seed %d: finished earlier, skipped", spec["row"], spec["seed"])
            results[(spec["row"], spec["seed"])] = done
        else:
            todo.append(spec)
    log.info("ablation: %d rows x %d seeds; %d to run, %d finished, n/a: %s", len(specs) // max(cfg.seeds, 1),
             cfg.seeds, len(todo), len(results), na or "none")
    # Row runs an earlier run finished in OUT with the same options stay in the report: other rows
    # (`--rows X` after `--rows Y`) and other seeds (`--seeds 1` after `--seeds 2`).
    _add_finished_on_disk(cfg, scene_dir, cues, out_dir, train_args, results, todo)
    shown = [r for r in PRESETS if r in cfg.rows or any(row == r for row, _ in results)]
    floor, floors = run_floors(cfg, scene_dir, out_dir, train_args, shown)
    diverged: dict[tuple[str, int], str] = {}
    train_keys = training_keys(train_config("full", train_args, cfg.iters, 0, cfg.checkpoints))

    def summary() -> dict:
        return {"scene": str(scene_dir), "scene_label": cfg.scene_label or scene_dir.name, "cues": str(cues),
                "config": asdict(cfg) | {"gt": str(cfg.gt) if cfg.gt else None,
                                         "gt_depth": str(cfg.gt_depth) if cfg.gt_depth else None},
                "train_args": train_args, "train_keys": train_keys, "floor": floor, "floors": floors,
                "rows": [_row_summary(r, [results[k] for k in sorted(results) if k[0] == r], na,
                                      {k[1]: m for k, m in diverged.items() if k[0] == r}) for r in shown]}

    def on_done(spec: dict, result: dict) -> None:
        if "diverged" in result:
            diverged[(spec["row"], spec["seed"])] = result["diverged"]
            log.error("row %s seed %d diverged: %s", spec["row"], spec["seed"], result["diverged"])
        else:
            results[(spec["row"], spec["seed"])] = result
            log.info("row %s seed %d done: %s", spec["row"], spec["seed"], _short(result["final"]))
        write_reports(summary(), out_dir)

    write_reports(summary(), out_dir)
    try:
        execute(todo, on_done, run_row, jobs=cfg.jobs, num_threads=cfg.num_threads, ray=cfg.ray)
    except TrainingInterrupted as exc:  # the same command resumes the row from its checkpoint
        n = len(results)
        raise TrainingInterrupted(f"ablation {str(exc).split(';')[0]}; {n} finished row run{'s' * (n != 1)} in "
                                  f"{out_dir}: run the same command again to continue", exc.signal_name) from None
    write_reports(summary(), out_dir)
    if diverged:
        names = ", ".join(f"{row} (seed {seed})" for row, seed in sorted(diverged))
        raise TrainingDiverged(f"{len(diverged)} row run{'s' * (len(diverged) != 1)} diverged: {names}; "
                               f"{out_dir / 'report.md'} has the other rows and why (first: "
                               f"{next(iter(diverged.values()))})")
    return out_dir


def _seeds_on_disk(out_dir: Path) -> dict[str, int]:
    """Each row with run folders in OUT/rows: one more than its highest seed found there."""
    found: dict[str, int] = {}
    for path in (out_dir / "rows").glob("*_s*"):
        row, _, seed = path.name.rpartition("_s")
        if path.is_dir() and row in PRESETS and seed.isdigit():
            found[row] = max(found.get(row, 0), int(seed) + 1)
    return found


def _add_finished_on_disk(cfg: AblateConfig, scene_dir: Path, cues: Path, out_dir: Path, train_args: list[str],
                          results: dict, todo: list[dict]) -> None:
    """Add to ``results`` every row run in OUT finished with this ablation's options that this run
    neither planned nor skipped (keys that differ mean other options: those stay out)."""
    planned = set(results) | {(spec["row"], spec["seed"]) for spec in todo}
    on_disk = _seeds_on_disk(out_dir)
    if not on_disk:
        return
    earlier = dataclasses.replace(cfg, rows=tuple(on_disk), seeds=max(on_disk.values()))
    for spec in plan(earlier, scene_dir, cues, out_dir, train_args)[0]:
        if (spec["row"], spec["seed"]) in planned or spec["seed"] >= on_disk[spec["row"]]:
            continue
        done = ablate_rows.done(Path(spec["out"]), spec["keys"])
        if done is not None:
            results[(spec["row"], spec["seed"])] = done


def _remove_outputs(out_dir: Path) -> None:
    """Remove what an earlier ablation wrote into ``out_dir`` (:data:`OUTPUTS`)."""
    gone = [name for name in OUTPUTS if (out_dir / name).exists()]
    gone += sorted(p.name for p in out_dir.glob("floor_*") if p.is_dir())
    if gone:
        log.warning("--overwrite: removing the earlier ablation's %s from %s", ", ".join(gone), out_dir)
    for name in gone:
        path = out_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


def _short(final: dict) -> str:
    return ", ".join(f"{k} {final[k]:.4f}" for k in ("chamfer_l1", "f_score", "normal_consistency", "psnr")
                     if final.get(k) is not None)


def _row_summary(row: str, runs: list[dict], na: dict[str, str], diverged: dict[int, str] | None = None) -> dict:
    preset = get_preset(row)
    out = {"row": row, "label": preset.label, "paper": preset.paper, "extension": preset.extension,
           "overrides": {k: list(v) if isinstance(v, tuple) else v for k, v in preset.overrides.items()},
           "iters_factor": preset.iters_factor}
    if row in na:
        return out | {"status": "n/a", "reason": na[row]}
    if diverged:  # a seed whose training diverged: the row's mean would leave it out silently
        return out | {"status": "diverged", "reason": "; ".join(f"seed {k}: {m}" for k, m in sorted(diverged.items()))}
    if not runs:
        return out | {"status": "pending"}
    return out | row_stats([{k: r[k] for k in RUN_FIELDS if k in r} for r in runs])
