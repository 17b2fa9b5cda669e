"""Reports of `splat ablate`: ``ablation.json``, ``report.md`` (laid out like the paper's Tab. 3)
and ``accuracy_vs_time.png`` (Chamfer-L1, F-score, NC and test PSNR against training seconds, a
curve per row, the floor as a line). Built from the summary dict splat/ablate.py assembles; the
figure's data is the JSON's, nothing else.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from geocues.atomic import atomic_path

PANELS = (("chamfer_l1", "Chamfer-L1 (cm)", 100.0), ("f_score", "F-score @ 5 cm", 1.0),
          ("normal_consistency", "normal consistency", 1.0), ("psnr", "test PSNR (dB)", 1.0))
METRICS = ("accuracy", "completeness", "chamfer_l1", "precision", "recall", "f_score", "normal_consistency")
# What must agree for two ablations' rows to share one table (the rows, seeds and how they were
# dispatched may differ).
_SAME_SETUP = ("iters", "gt", "gt_depth", "gt_depth_png_scale", "checkpoints", "metrics", "floor")


def row_stats(runs: list[dict]) -> dict:
    """A finished row's part of the summary: its runs (one per seed) with mean and spread of the
    final metrics, test PSNR/SSIM and training seconds."""
    import numpy as np

    keys = METRICS + ("psnr", "ssim", "train_s")
    finals = [r["final"] | {"train_s": r["train_s"]} for r in runs]
    values = {k: [f[k] for f in finals if f.get(k) is not None] for k in keys}
    return {"status": "done", "n_seeds": len(runs),
            "mean": {k: float(np.mean(v)) if v else None for k, v in values.items()},
            "std": {k: float(np.std(v)) if v else None for k, v in values.items()},
            "runs": sorted(runs, key=lambda r: r["seed"])}


def row_floor(summary: dict, row: str) -> dict | None:
    """The final metrics of the floor ``row`` is read against: the floor through its own meshing where
    its preset meshes otherwise (``floors``), else the table's floor; None where none was fused."""
    for floor in ((summary.get("floors") or {}).get(row), summary.get("floor")):
        if floor and floor.get("status", "done") == "done" and floor.get("final"):
            return floor["final"]
    return None


def merge_summaries(old: dict, new: dict) -> dict:
    """``new`` with the finished runs of ``old`` it lacks: the same ablation continued in another
    OUT (a fresh checkout, another machine). Both must have the same scene label, training options,
    iterations, scoring, floor and `splat train` defaults (``train_keys``; see
    :func:`_training_differs` for a summary written before those were kept); a row's run (row,
    seed) finished in both is taken from ``new``. Raises ValueError naming what differs."""
    differ = [k for k in ("scene_label", "train_args") if old.get(k) != new.get(k)]
    differ += [f"config.{k}" for k in _SAME_SETUP if old["config"].get(k) != new["config"].get(k)]
    old_floor, new_floor = old.get("floor") or {}, new.get("floor") or {}
    same = "setup" if old_floor.get("setup") and new_floor.get("setup") else "key"  # setup: without paths
    if old_floor.get(same) and new_floor.get(same) and old_floor[same] != new_floor[same]:
        differ.append("floor (other training views or TSDF settings)")
    differ += _training_differs(old, new)
    if differ:
        raise ValueError(f"the two ablations differ in {', '.join(differ)}: their rows do not share a table")
    old_rows = {r["row"]: r for r in old["rows"]}
    rows = []
    for row in new["rows"]:
        before = old_rows.pop(row["row"], None)
        if before is not None and before["status"] == "done" and row["status"] != "n/a":
            runs = {r["seed"]: r for r in before["runs"]}
            runs.update({r["seed"]: r for r in row.get("runs", [])})
            row = {k: v for k, v in row.items() if k not in ("reason",)} | row_stats(list(runs.values()))
        rows.append(row)
    order = [r["row"] for r in old["rows"]]
    rows += [r for r in old_rows.values()]  # rows only the earlier ablation ran, in its order
    rows.sort(key=lambda r: order.index(r["row"]) if r["row"] in order else len(order))
    floor = new_floor if new_floor.get("status") == "done" else old.get("floor")
    merged = new | {"rows": rows, "floor": floor, "floors": (old.get("floors") or {}) | (new.get("floors") or {})}
    merged.pop("train_keys", None)  # the keys stand for every row only when both sides had them
    if old.get("train_keys") and new.get("train_keys"):
        merged["train_keys"] = sorted(set(old["train_keys"]) | set(new["train_keys"]))
    return merged


def _sets_budget(train_args: list[str]) -> bool:
    """Whether `splat train` options set the Gaussian budget (``--strategy.max-gaussians``, any spelling)."""
    return any(a.partition("=")[0].replace("_", "-") == "--strategy.max-gaussians" for a in train_args or [])


def _training_differs(old: dict, new: dict) -> list[str]:
    """What may differ in how two ablations' rows trained beyond their (equal) train options: the
    defaults of `splat train` (``train_keys``: the `full` row's configuration keys without scene and
    cue paths, splat/ablate_keys.py). A summary written before those were kept beside one with them:
    only a budget set in the options is known to be shared (its default changed from no limit to
    "auto" on 2026-11-29); other defaults are taken as the same."""
    a, b = old.get("train_keys"), new.get("train_keys")
    if a and b:
        return [] if set(a) & set(b) else ["training defaults (`splat train` of another version: rerun the rows)"]
    if bool(a) != bool(b) and not _sets_budget(new.get("train_args")):
        return ["Gaussian budget (the one written before ablations kept `train_keys` set none, and the default "
                "changed from no limit to 'auto' then: it is not known)"]
    return []


def _fmt(value, scale: float = 1.0, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value * scale:.{digits}f}"


def _cell(row: dict, key: str, scale: float = 1.0, digits: int = 3) -> str:
    mean, std = row["mean"].get(key), row["std"].get(key)
    text = _fmt(mean, scale, digits)
    if row.get("n_seeds", 1) > 1 and std is not None:
        text += f" ± {_fmt(std, scale, digits)}"
    return text


def _delta(row: dict, full: dict | None, key: str, scale: float = 1.0, digits: int = 3) -> str:
    if full is None or full.get("status") != "done" or row["row"] == "full":
        return ""
    a, b = row["mean"].get(key), full["mean"].get(key)
    if a is None or b is None:
        return ""
    other = row.get("n_seeds") != full.get("n_seeds")  # means over other seeds: marked, not hidden
    return f"{(a - b) * scale:+.{digits}f}" + ("\\*" if other else "")


def ablation_markdown(summary: dict) -> str:
    """The ablation table (paper's Tab. 3 layout), the floor, deltas against `full`, seconds."""
    rows = summary["rows"]
    full = next((r for r in rows if r["row"] == "full"), None)
    cfg = summary["config"]
    counts = sorted({r["n_seeds"] for r in rows if r["status"] == "done"} or {cfg["seeds"]})
    seeds = (f"{counts[0]} seed(s) per row" if len(counts) == 1
             else f"{counts[0]}–{counts[-1]} seeds per row (the count beside a row with more than one)")
    names = {r["row"] for r in rows}
    lines = [f"# Ablation on {summary['scene_label']}", "",
             f"Scene `{summary['scene']}`, cues `{summary['cues']}`; {cfg['iters']} iterations per row"
             + (" (no-cues-long: 3x)" if "no-cues-long" in names else "") + f", {seeds} (mean ± std over seeds), "
             f"train options `{' '.join(summary['train_args']) or '(defaults)'}`. Mesh metrics: the "
             "`evaluate` protocol (MonoSDF sampling, culled to the scene's cameras, F-score at 5 cm). "
             "Paper: IndoorGS Tab. 3 (ScanNet++, 30k iterations)."
             + (" Δ: against `full` (Chamfer in cm)." if full is not None else "")
             + (" \\* a mean over another number of seeds than `full`'s: compare with care." if full is not None
                and any(r.get("n_seeds") != full.get("n_seeds") for r in rows if r["status"] == "done") else ""), "",
             "| row | paper C-L1 (cm) / F / NC | C-L1 (cm) | F@5cm | NC | ΔC-L1 | ΔF | ΔNC | test PSNR | train s |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    floor = summary.get("floor")
    if floor and floor.get("status") == "done":
        f = floor["final"]
        lines.append(f"| **floor** (TSDF of exact GT depth, same views) | – | {_fmt(f['chamfer_l1'], 100, 2)} | "
                     f"{_fmt(f['f_score'])} | {_fmt(f['normal_consistency'])} |  |  |  | – | – |")
    for row, other in (summary.get("floors") or {}).items():
        if other and other.get("status") == "done":
            f = other["final"]
            lines.append(f"| **floor** through `{row}`'s meshing (its TSDF settings) | – | "
                         f"{_fmt(f['chamfer_l1'], 100, 2)} | {_fmt(f['f_score'])} | "
                         f"{_fmt(f['normal_consistency'])} |  |  |  | – | – |")
    for r in rows:
        name = f"`{r['row']}` {r['label']}" + (" *(extension)*" if r.get("extension") else "")
        if len(counts) > 1 and r["status"] == "done" and r["n_seeds"] > 1:
            name += f" ({r['n_seeds']} seeds)"
        paper = (f"{100 * r['paper'][0]:.1f} / {r['paper'][1]:.3f} / {r['paper'][2]:.3f}"
                 if r.get("paper") else "–")
        if r["status"] == "n/a":
            lines.append(f"| {name} | {paper} | n/a ({r['reason']}) |  |  |  |  |  |  |  |")
        elif r["status"] == "diverged":
            lines.append(f"| {name} | {paper} | diverged ({r['reason']}) |  |  |  |  |  |  |  |")
        elif r["status"] == "pending":
            lines.append(f"| {name} | {paper} | (not run yet) |  |  |  |  |  |  |  |")
        else:
            lines.append(f"| {name} | {paper} | {_cell(r, 'chamfer_l1', 100, 2)} | {_cell(r, 'f_score')} | "
                         f"{_cell(r, 'normal_consistency')} | {_delta(r, full, 'chamfer_l1', 100, 2)} | "
                         f"{_delta(r, full, 'f_score')} | {_delta(r, full, 'normal_consistency')} | "
                         f"{_cell(r, 'psnr', 1, 2)} | {_cell(r, 'train_s', 1, 0)} |")
    if not has_curves(summary):
        lines += ["", "No row has finished: no plot of accuracy against time yet.", ""]
        return "\n".join(lines)
    lines += ["", "![accuracy against training time](accuracy_vs_time.png)", "",
              "Accuracy against time: every row's metrics at its checkpoints "
              f"({', '.join(str(c) for c in cfg['checkpoints'])} of its run) against training seconds "
              "(meshing and scoring not counted); the dotted black line is the floor, the `no-cues` rows "
              "are dashed.", ""]
    return "\n".join(lines)


def has_curves(summary: dict) -> bool:
    """Whether any row has finished (a curve to plot)."""
    return any(r["status"] == "done" for r in summary["rows"])


def plot_accuracy_vs_time(summary: dict, path: Path) -> Path:
    """Four panels (C-L1, F, NC, PSNR) against training seconds, a curve per finished row (seed 0
    drawn, other seeds thin; `no-cues` rows dashed), the floor as a dotted black line."""
    from evaluation import figures as plt  # detached figures: the user's matplotlib backend is left alone

    fig, axes = plt.subplots(2, 2, figsize=(12, 8), constrained_layout=True)
    floor = summary.get("floor") or {}
    cmap = plt.get_cmap("tab20")
    done = [r for r in summary["rows"] if r["status"] == "done"]
    for ax, (key, title, scale) in zip(axes.flat, PANELS):
        for k, r in enumerate(done):
            for j, run in enumerate(r["runs"]):
                pts = [(c["train_s"], c[key] * scale) for c in run["curve"] if c.get(key) is not None]
                if not pts:
                    continue
                xs, ys = zip(*pts)
                style = dict(lw=2.2 if r["row"] == "full" else 1.3, color=cmap((2 * k) % 20 + ((2 * k) // 20) % 2),
                             ls="-" if not r["row"].startswith("no-cues") else "--")
                ax.plot(xs, ys, marker="o", ms=3, label=r["row"] if j == 0 else None,
                        alpha=1.0 if j == 0 else 0.4, **style)
        if floor.get("status") == "done" and key in floor.get("final", {}):
            ax.axhline(floor["final"][key] * scale, color="k", ls=":", lw=1.5, label="floor")
        ax.set_xlabel("training seconds")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside right center", fontsize=8)
    fig.suptitle(f"accuracy against time: {summary['scene_label']}")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    return path


def write_reports(summary: dict, out_dir: Path) -> None:
    """OUT/ablation.json, OUT/report.md, OUT/accuracy_vs_time.png (once a row has finished)."""
    out_dir = Path(out_dir)
    with atomic_path(out_dir / "ablation.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1, default=str))
    with atomic_path(out_dir / "report.md") as tmp:
        tmp.write_text(ablation_markdown(summary))
    png = out_dir / "accuracy_vs_time.png"
    if has_curves(summary):
        plot_accuracy_vs_time(summary, png)
    else:  # only n/a, diverged or pending rows: four empty panels would say nothing
        png.unlink(missing_ok=True)
