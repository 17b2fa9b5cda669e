"""What the Gaussian budget (--strategy.max-gaussians) costs and buys: one row per budget, from
`splat ablate --rows full` folders (their `full` row, mean ± spread over its seeds, and the floor) or `splat train` folders
scored by `evaluate ... -o RUN/metrics.json`. Writes bench/results/budget_<name>.json and prints
its rows of the markdown table docs/training.md ("Budget") shows; without run folders it prints the
whole table from the results files (--write: into docs/training.md between its budget-table markers).

    python bench/budget_summary.py --name textured_s21_heldout24 --scene "textured s21" \
        OUT/b_50000 OUT/b_auto OUT/b_200000
    python bench/budget_summary.py --write

bench/budget_sweep.sh makes the runs. A row is marked "auto" when its budget is what today's default
(splat.strategy.resolve_budget) gives its training views.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.doc_markers import replace_block  # noqa: E402
from geocues.atomic import atomic_path  # noqa: E402
from geocues.photos import read_image_size  # noqa: E402
from geocues.scene import downscaled_size  # noqa: E402
from splat.strategy import resolve_budget  # noqa: E402

RESULTS = REPO / "bench" / "results"


_FIGURES = ("gaussians_final", "train_s", "psnr", "chamfer_l1_cm", "f_score", "normal_consistency")


def _run(train: Path, mesh: dict) -> dict:
    """One training's figures: Gaussians at the end, training seconds, held-out PSNR, the mesh's."""
    report = json.loads((train / "report.json").read_text())
    curve = {c["step"]: c for c in report["accuracy_vs_time"]}
    last = curve[max(curve)]
    mesh = mesh.get("mesh", mesh)  # evaluate's metrics.json nests the mesh figures
    return {"seed": report["config"]["seed"], "gaussians_final": sum(report["gaussians_final"].values()),
            "train_s": last["train_s"], "psnr": last["psnr"], "chamfer_l1_cm": 100 * mesh["chamfer_l1"],
            "f_score": mesh["f_score"], "normal_consistency": mesh["normal_consistency"], "report": report}


def _row(folder: Path) -> dict:
    """One budget: its runs (an ablation's `full` row, one per training seed, or one `splat train`
    folder), their mean and spread (population std), the floor where the ablation fused one."""
    import numpy as np

    if (folder / "ablation.json").is_file():
        abl = json.loads((folder / "ablation.json").read_text())
        full = next(r for r in abl["rows"] if r["row"] == "full")
        trains = [(folder / "rows" / f"full_s{r['seed']}" / "train", r["final"]) for r in full["runs"]]
        floor = abl["floor"]["final"] if abl.get("floor") else None
    else:
        trains, floor = [(folder, json.loads((folder / "metrics.json").read_text()))], None
    runs = [_run(train, mesh) for train, mesh in trains]
    report = runs[0]["report"]
    budgets = {r["report"].get("gaussian_budget", r["report"]["config"]["strategy"]["max_gaussians"]) for r in runs}
    if len(budgets) != 1:
        raise SystemExit(f"{folder}: its runs trained with other budgets {sorted(budgets)}")
    pixels = _view_pixels(trains[0][0], report)
    option = report["config"]["strategy"]["max_gaussians"]
    budget = budgets.pop()  # runs from before report.json kept it: the number they were given
    return {"run": str(folder), "budget": budget, "budget_option": option,
            "is_default": budget == resolve_budget("auto", pixels), "view_pixels": pixels,
            "note": ("'auto' under an earlier rule" if option == "auto" and budget != resolve_budget("auto", pixels)
                     else None),
            "n_seeds": len(runs), "seeds": [r["seed"] for r in runs],
            **{k: float(np.mean([r[k] for r in runs])) for k in _FIGURES},
            "std": {k: float(np.std([r[k] for r in runs])) for k in _FIGURES},
            "runs": [{k: r[k] for k in ("seed", *_FIGURES)} for r in runs],
            "floor": None if floor is None else {"chamfer_l1_cm": 100 * floor["chamfer_l1"], "f_score": floor["f_score"],
                                                 "normal_consistency": floor["normal_consistency"]}}


def _view_pixels(train: Path, report: dict) -> int:
    """The largest view's pixels at the training resolution (what the 'auto' budget is 2x of): the held-out
    renders' size; without them cameras.json's through the run's --downscale (cameras.json holds the
    photos' own size since 2026-11-30, the training resolution before)."""
    renders = sorted((train / "test_renders").glob("*.png"))
    if renders:
        return max(w * h for w, h in map(read_image_size, renders))
    down = float(report.get("config", {}).get("downscale", 1.0))
    sizes = [downscaled_size(c["width"], c["height"], down) for c in json.loads((train / "cameras.json").read_text())]
    return max(w * h for w, h in sizes)


def _cell(row: dict, key: str, digits: int, scale: float = 1.0) -> str:
    """Mean, and ± the spread over seeds where the row has more than one."""
    text = f"{row[key] * scale:.{digits}f}"
    return text + (f" ± {row['std'][key] * scale:.{digits}f}" if row.get("n_seeds", 1) > 1 else "")


# The results files of docs/training.md's "Budget" table, in its order.
TABLE = ("textured_s21_heldout24", "textured_s24_heldout24", "icl_livingroom1")


def table_lines(scene: str, rows: list[dict]) -> list[str]:
    """One scene's rows of the table (budgets in increasing order, no limit last), then its floor."""
    lines = []
    for r in rows:
        label = "auto, " if r["is_default"] else ""  # today's rule (a run may predate it)
        budget = f"{r['budget'] / 1000:.0f}k" if r["budget"] else "no limit"  # rounded as the Gaussians
        lines.append(f"| {scene} | {label}{budget} | {r.get('n_seeds', 1)} | {r['gaussians_final'] / 1000:.0f}k | "
                     f"{r['train_s']:.0f} | {_cell(r, 'chamfer_l1_cm', 2)} | {_cell(r, 'f_score', 3)} | "
                     f"{_cell(r, 'normal_consistency', 3)} | {_cell(r, 'psnr', 2)} |")
    if floor := next((r["floor"] for r in rows if r["floor"]), None):  # the ablations' (a train folder has none)
        lines.append(f"| {scene} | floor (exact GT depth) | | | | {floor['chamfer_l1_cm']:.2f} | {floor['f_score']:.3f} | "
                     f"{floor['normal_consistency']:.3f} | |")
    return lines


def table() -> str:
    """docs/training.md's "Budget" table from bench/results/budget_<name>.json of :data:`TABLE`."""
    lines = ["| scene | budget | seeds | Gaussians at the end | train s | C-L1 (cm) | F@5cm | NC | test PSNR |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name in TABLE:
        data = json.loads((RESULTS / f"budget_{name}.json").read_text())
        lines += table_lines(data["scene"], data["rows"])
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="*", type=Path, help="ablation or train folders, one per budget")
    p.add_argument("--name", help="results file bench/results/budget_NAME.json")
    p.add_argument("--scene", help="the scene's label in the table")
    p.add_argument("--write", action="store_true",
                   help="write the table of every results file into docs/training.md (its budget-table markers)")
    a = p.parse_args()
    if a.runs:
        if not (a.name and a.scene):
            p.error("run folders need --name and --scene")
        rows = sorted((_row(r) for r in a.runs), key=lambda r: r["budget"] or float("inf"))
        out = RESULTS / f"budget_{a.name}.json"
        with atomic_path(out) as tmp:
            tmp.write_text(json.dumps({"scene": a.scene, "rows": rows}, indent=1) + "\n")
        print("\n".join(table_lines(a.scene, rows)))
        print(f"wrote {out}")
    elif a.write:
        replace_block(REPO / "docs" / "training.md", "budget-table", table())
    else:
        print(table())


if __name__ == "__main__":
    main()
