"""What the Gaussian budget (--strategy.max-gaussians) costs and buys: one row per run, from
`splat ablate --rows full` folders (their `full` row and the floor) or `splat train` folders
scored by `evaluate ... -o RUN/metrics.json`. Writes bench/results/budget_<name>.json and prints
the markdown table docs/training.md ("Budget") shows.

    python bench/budget_summary.py --name textured_s21_heldout24 --scene "textured s21" \
        OUT/b_50000 OUT/b_auto OUT/b_200000

bench/budget_sweep.sh makes the runs. A row is marked "auto" when its budget is what today's default
(splat.strategy.resolve_budget) gives its training views.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from splat.strategy import resolve_budget

RESULTS = Path(__file__).resolve().parent / "results"


def _row(folder: Path) -> dict:
    """One run's budget, Gaussians, training seconds, held-out PSNR and mesh figures."""
    if (folder / "ablation.json").is_file():
        abl = json.loads((folder / "ablation.json").read_text())
        full = next(r for r in abl["rows"] if r["row"] == "full")
        train = folder / "rows" / f"full_s{full['runs'][0]['seed']}" / "train"
        mesh, floor = full["mean"], abl["floor"]["final"] if abl.get("floor") else None
    else:
        train, floor = folder, None
        mesh = json.loads((folder / "metrics.json").read_text())
    report = json.loads((train / "report.json").read_text())
    curve = {c["step"]: c for c in report["accuracy_vs_time"]}
    last = curve[max(curve)]
    mesh = mesh.get("mesh", mesh)  # evaluate's metrics.json nests the mesh figures
    pixels = max(c["width"] * c["height"] for c in json.loads((train / "cameras.json").read_text()))
    return {"run": str(folder), "budget": report["gaussian_budget"], "budget_option": report["config"]["strategy"]["max_gaussians"],
            "is_default": report["gaussian_budget"] == resolve_budget("auto", pixels), "view_pixels": pixels,
            "note": ("'auto' under an earlier rule" if report["config"]["strategy"]["max_gaussians"] == "auto"
                     and report["gaussian_budget"] != resolve_budget("auto", pixels) else None),
            "gaussians_final": sum(report["gaussians_final"].values()), "train_s": last["train_s"], "psnr": last["psnr"],
            "chamfer_l1_cm": 100 * mesh["chamfer_l1"], "f_score": mesh["f_score"],
            "normal_consistency": mesh["normal_consistency"],
            "floor": None if floor is None else {"chamfer_l1_cm": 100 * floor["chamfer_l1"], "f_score": floor["f_score"],
                                                 "normal_consistency": floor["normal_consistency"]}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path, help="ablation or train folders, one per budget")
    p.add_argument("--name", required=True, help="results file bench/results/budget_NAME.json")
    p.add_argument("--scene", required=True, help="the scene's label in the table")
    a = p.parse_args()
    rows = sorted((_row(r) for r in a.runs), key=lambda r: r["budget"] or float("inf"))
    out = RESULTS / f"budget_{a.name}.json"
    out.write_text(json.dumps({"scene": a.scene, "rows": rows}, indent=1) + "\n")
    for r in rows:
        label = "auto, " if r["is_default"] else ""  # today's rule (a run may predate it)
        budget = f"{r['budget'] // 1000}k" if r["budget"] else "no limit"
        print(f"| {a.scene} | {label}{budget} | {r['gaussians_final'] / 1000:.0f}k | {r['train_s']:.0f} | "
              f"{r['chamfer_l1_cm']:.2f} | {r['f_score']:.3f} | {r['normal_consistency']:.3f} | {r['psnr']:.2f} |")
    if floor := rows[0]["floor"]:
        print(f"| {a.scene} | floor (exact GT depth) | | | {floor['chamfer_l1_cm']:.2f} | {floor['f_score']:.3f} | "
              f"{floor['normal_consistency']:.3f} | |")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
