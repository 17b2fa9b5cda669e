"""Write the committed ablation results into the docs (figures in docs are generated, not typed).

    python bench/ablation_summary.py                      # docs/ablation_results.md from bench/results/ablation_*/
    python bench/ablation_summary.py --demo outputs/demo  # also README.md's demo figures and plot

For each ``bench/results/ablation_<scene>/ablation.json`` (copied there from a `splat ablate` OUT
with ``--collect OUT NAME [--label TEXT]``; merged with the rows already there when the setup is the same, so an
ablation can be finished over several sessions), a table of every row: Chamfer-L1, F@5cm, NC, test PSNR, training
seconds, the ratio of Chamfer-L1 to the floor's and the deltas against `no-cues`. The text between
``<!-- ablation-summary -->`` and ``<!-- /ablation-summary -->`` in docs/ablation_results.md is replaced.
With ``--demo DIR`` the main job's figures (DIR/ablation/ablation.json) and its wall time per step
(DIR/timings.json, written by scripts/demo.sh) go between ``<!-- demo-figures -->`` markers in README.md,
its plot to docs/img/demo_accuracy_vs_time.png, and the files they come from to bench/results/demo/.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.doc_markers import replace_block  # noqa: E402
from evaluation.ablation_report import row_floor  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"


def _f(v, scale=1.0, digits=3):
    return "–" if v is None else f"{v * scale:.{digits}f}"


def scene_table(data: dict) -> str:
    rows = {r["row"]: r for r in data["rows"]}
    floor = (data.get("floor") or {}).get("final") if (data.get("floor") or {}).get("status") == "done" else None
    base = rows.get("no-cues", {}).get("mean") if rows.get("no-cues", {}).get("status") == "done" else None
    cfg = data["config"]
    counts = sorted({r["n_seeds"] for r in rows.values() if r["status"] == "done"} or {cfg["seeds"]})
    seeds = (f"{counts[0]} seed(s)" if len(counts) == 1
             else f"{counts[0]}–{counts[-1]} seeds per row (mean; the count beside a row with more than one)")
    lines = [f"**{data['scene_label']}** — {cfg['iters']} iterations, {seeds}, train options "
             f"`{' '.join(data['train_args']) or '(defaults)'}`", "",
             "| row | C-L1 (cm) | F@5cm | NC | C-L1 / floor | ΔF vs no-cues | ΔNC vs no-cues | test PSNR | "
             "PSNR at 1st checkpoint | train s |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    if floor:
        lines.append(f"| floor (exact GT depth) | {_f(floor['chamfer_l1'], 100, 2)} | {_f(floor['f_score'])} | "
                     f"{_f(floor['normal_consistency'])} | 1.00 |  |  | – | – | – |")
    own = {row: f["final"] for row, f in (data.get("floors") or {}).items() if f and f.get("status") == "done"}
    for row, f in own.items():  # a row whose preset meshes otherwise is read against its own meshing's floor
        lines.append(f"| floor through `{row}`'s meshing | {_f(f['chamfer_l1'], 100, 2)} | {_f(f['f_score'])} | "
                     f"{_f(f['normal_consistency'])} | 1.00 |  |  | – | – | – |")
    for name, r in rows.items():
        if r["status"] != "done":
            why = f"{r['status']} ({r['reason']})" if r["status"] in ("n/a", "diverged") else "not run yet"
            lines.append(f"| `{name}` | {why} |  |  |  |  |  |  |  |  |")
            continue
        m = r["mean"]
        its = row_floor(data, name)
        ratio = f"{m['chamfer_l1'] / its['chamfer_l1']:.2f}" if its else "–"
        df = f"{m['f_score'] - base['f_score']:+.3f}" if base and name != "no-cues" else ""
        dn = f"{m['normal_consistency'] - base['normal_consistency']:+.3f}" if base and name != "no-cues" else ""
        early = [run["curve"][0] for run in r.get("runs", []) if run.get("curve")]  # the first checkpoint
        early_s = (f"{sum(c['psnr'] for c in early) / len(early):.1f} (step {early[0]['step']})" if early else "–")
        label = f"`{name}`" + (f" ({r['n_seeds']} seeds)" if len(counts) > 1 and r["n_seeds"] > 1 else "")
        lines.append(f"| {label} | {_f(m['chamfer_l1'], 100, 2)} | {_f(m['f_score'])} | "
                     f"{_f(m['normal_consistency'])} | {ratio} | {df} | {dn} | {_f(m.get('psnr'), 1, 2)} | "
                     f"{early_s} | {_f(m.get('train_s'), 1, 0)} |")
    return "\n".join(lines)


def collect(out: Path, name: str, replace: bool = False, label: str | None = None) -> Path:
    """Copy a `splat ablate` OUT's reports (not its training folders) to bench/results/ablation_NAME/.
    Where that folder already holds an ablation of the same setup, the two are merged (rows and seeds
    finished only there stay; ``replace`` drops them) and the report and plot are redrawn. ``label``
    names the scene in the tables instead of the run's ``--scene-label`` (JSON, report and plot alike)."""
    from evaluation.ablation_report import merge_summaries, write_reports

    if not (out / "ablation.json").is_file():
        raise SystemExit(f"{out}: no ablation.json (not the OUT of a `splat ablate` run)")
    new = json.loads((out / "ablation.json").read_text())
    dst = RESULTS / f"ablation_{name}"
    dst.mkdir(parents=True, exist_ok=True)
    if label:
        new["scene_label"] = new["config"]["scene_label"] = label
    if (dst / "ablation.json").is_file() and not replace:
        old = json.loads((dst / "ablation.json").read_text())
        try:
            write_reports(merge_summaries(old, new), dst)
        except ValueError as exc:
            raise SystemExit(f"{dst}: {exc} (--replace overwrites it)") from None
        return dst
    write_reports(new, dst)  # the run's own reports, redrawn (with ``label`` where given)
    return dst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--collect", nargs=2, metavar=("OUT", "NAME"), action="append", default=[],
                    help="copy the reports of a `splat ablate` OUT to bench/results/ablation_NAME first")
    ap.add_argument("--replace", action="store_true",
                    help="--collect replaces bench/results/ablation_NAME instead of merging into it")
    ap.add_argument("--label", help="--collect names the scene so in its tables (instead of the run's label)")
    ap.add_argument("--demo", type=Path, help="the main job's output folder (outputs/demo)")
    args = ap.parse_args()
    for out, name in args.collect:
        print(f"collected {collect(Path(out), name, args.replace, args.label)}")
    parts = []
    for path in sorted(RESULTS.glob("ablation_*/ablation.json")):
        data = json.loads(path.read_text())
        rel = path.parent.relative_to(REPO)
        parts.append(scene_table(data) + f"\n\n([report]({'../' + str(rel)}/report.md), "
                     f"[plot]({'../' + str(rel)}/accuracy_vs_time.png), [JSON]({'../' + str(rel)}/ablation.json))")
    if parts:
        replace_block(REPO / "docs" / "ablation_results.md", "ablation-summary", "\n\n".join(parts))
        print("updated docs/ablation_results.md")
    if args.demo:
        data = json.loads((args.demo / "ablation" / "ablation.json").read_text())
        timings = json.loads((args.demo / "timings.json").read_text())
        (REPO / "docs" / "img").mkdir(exist_ok=True)
        shutil.copyfile(args.demo / "ablation" / "accuracy_vs_time.png", REPO / "docs" / "img" / "demo_accuracy_vs_time.png")
        keep = RESULTS / "demo"
        keep.mkdir(exist_ok=True)
        for src in ["ablation/ablation.json", "ablation/report.md", "timings.json", "cue_metrics.json",
                    "mesh_metrics_trained.json"]:
            shutil.copyfile(args.demo / src, keep / Path(src).name)
        text = ("Measured on 2 cores (generated by `bench/ablation_summary.py --demo outputs/demo` from the run's "
                "`ablation.json` and `timings.json`, kept in [bench/results/demo/](bench/results/demo/)):\n\n"
                + scene_table(data) + "\n\n" + demo_time_line(timings)
                + "\n\n![accuracy against time of the main job](docs/img/demo_accuracy_vs_time.png)")
        replace_block(REPO / "README.md", "demo-figures", text)
        print("updated README.md")


def demo_time_line(t: dict) -> str:
    """The main job's wall time, step by step, from scripts/demo.sh's timings.json."""
    s = t["steps_s"]
    total = round(t["total_s"])
    room = (f"the room {s['room']:.0f} s to render and triangulate" if t["room_made"]
            else f"the room already made ({s['room']:.0f} s)")
    return (f"Time: **{total // 60} min {total % 60:02d} s** wall on {t['cpus']} cores ({t['date']}, after the "
            f"install; a first run also builds the C++ extension, about a minute more): {room}, cues "
            f"{s['cues']:.0f} s, their scoring {s['cue_scoring']:.0f} s, the two trainings side by side with a "
            f"mesh at each checkpoint, their scoring, the floor and the reports {s['ablation']:.0f} s (the table's "
            f"train s: each row's training alone), the final scoring {s['final_scoring']:.0f} s.")


if __name__ == "__main__":
    main()
