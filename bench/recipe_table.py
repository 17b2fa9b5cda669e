"""A recipe's `full` rows against an earlier recipe's, per room, with the floor and issue 12's targets.

Reads ``bench/results/ablation_<name>/ablation.json`` (written by ``bench/ablation_summary.py
--collect``) and writes a markdown table between ``<!-- MARKER -->`` markers of a doc:

    python bench/recipe_table.py --doc docs/training.md --marker ceiling-table \
        --room "bare s5" bare_s5_floorwalls_check_gap_planefirst bare_s5_ceiling_grid ...

Each ``--room LABEL BEFORE AFTER [NOCUES]`` adds a row: the `full` row (mean over its seeds) of both
folders, C-L1 cm / F / NC / test PSNR dB (AFTER in bold where its C-L1 is lower), the floor of AFTER,
and which of the targets AFTER meets (C-L1 <= 1.3 x floor, F >= floor - 0.05, NC >= floor - 0.04).
With NOCUES on every room, the `no-cues` row of ablation_<NOCUES> is added, with whether AFTER beats
it by the paper's own margins (C-L1 -27 %, F +0.10, NC +0.02), and both recipes' training seconds.
BEFORE / AFTER may name another row than `full` as ``NAME:ROW`` (``icl_mvs_preset:mvs``), and
``--fixed-targets LABEL C_L1_CM F NC`` scores a room against fixed targets instead of its floor
(issue 12's ICL targets: 3.0 cm, 0.85, 0.85).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.doc_markers import replace_block  # noqa: E402
from evaluation.ablation_report import row_floor  # noqa: E402

RESULTS = REPO / "bench" / "results"


def full_row(name: str, row: str = "full") -> tuple[dict, dict, int]:
    """(mean metrics of the ``row`` row, its floor's final metrics, seeds) of ablation_<name>; the
    metrics also hold ``psnr_300``, the held-out PSNR at the first checkpoint (mean over seeds).
    ``name`` may carry its row as ``NAME:ROW``."""
    if ":" in name:
        name, row = name.split(":", 1)
    path = RESULTS / f"ablation_{name}" / "ablation.json"
    if not path.is_file():
        raise SystemExit(f"recipe_table: no {path}")
    data = json.loads(path.read_text())
    rows = [r for r in data["rows"] if r["row"] == row and r.get("status") == "done"]
    if not rows:
        raise SystemExit(f"recipe_table: {path} has no finished `{row}` row")
    first = [run["curve"][0] for run in rows[0]["runs"] if run.get("curve")]
    mean = dict(rows[0]["mean"], psnr_300=sum(c["psnr"] for c in first) / max(len(first), 1),
                step_300=first[0]["step"] if first else None)
    return mean, row_floor(data, row) or {}, int(rows[0]["n_seeds"])


def _cell(m: dict, bold: bool = False) -> str:
    s = f"{100 * m['chamfer_l1']:.2f} / {m['f_score']:.3f} / {m['normal_consistency']:.3f} / {m['psnr']:.1f}"
    return f"**{s}**" if bold else s


def targets(m: dict, floor: dict) -> str:
    ratio = m["chamfer_l1"] / floor["chamfer_l1"]
    met = [n for n, ok in (("C-L1", ratio <= 1.3), ("F", m["f_score"] >= floor["f_score"] - 0.05),
                           ("NC", m["normal_consistency"] >= floor["normal_consistency"] - 0.04)) if ok]
    miss = []
    if ratio > 1.3:
        miss.append(f"C-L1 {ratio:.2f}×")
    if m["f_score"] < floor["f_score"] - 0.05:
        miss.append(f"F {m['f_score'] - floor['f_score']:+.3f}")
    text = "all" if len(met) == 3 else (", ".join(met) or "none")
    return f"{text} (C-L1 {ratio:.2f}×)" if len(met) == 3 else f"{text}; misses {', '.join(miss)}"


def fixed_targets(m: dict, goal: tuple[float, float, float]) -> str:
    """Which of C-L1 <= goal[0] cm, F >= goal[1], NC >= goal[2] ``m`` meets."""
    c, f, n = 100 * m["chamfer_l1"], m["f_score"], m["normal_consistency"]
    checks = (("C-L1", c <= goal[0], f"C-L1 {c:.2f} > {goal[0]:g} cm"), ("F", f >= goal[1], f"F {f:.3f} < {goal[1]:g}"),
              ("NC", n >= goal[2], f"NC {n:.3f} < {goal[2]:g}"))
    met, miss = [k for k, ok, _ in checks if ok], [why for _, ok, why in checks if not ok]
    fixed = f"≤ {goal[0]:g} cm, ≥ {goal[1]:g}, ≥ {goal[2]:g}"
    return f"all of {fixed}" if not miss else f"{', '.join(met) or 'none'} of {fixed}; misses {', '.join(miss)}"


def beats_no_cues(m: dict, base: dict) -> str:
    """Whether ``m`` beats the no-cue row by the paper's margins (C-L1 -27 %, F +0.10, NC +0.02)."""
    d_c = m["chamfer_l1"] / base["chamfer_l1"] - 1.0
    d_f, d_n = m["f_score"] - base["f_score"], m["normal_consistency"] - base["normal_consistency"]
    ok = d_c <= -0.27 and d_f >= 0.10 and d_n >= 0.02
    return f"{'yes' if ok else 'no'} ({100 * d_c:+.0f} %, {d_f:+.2f}, {d_n:+.3f})"


def table(rooms: list[tuple[str, ...]], before: str, after: str,
          fixed: dict[str, tuple[float, float, float]] | None = None) -> str:
    with_base = all(len(r) == 4 for r in rooms)
    head = f"| room | {before} | {after} | floor | targets ({after}) |"
    if with_base:
        head += (" `no-cues` | beats `no-cues` by the paper's margins | test PSNR at the first checkpoint"
                 " (before → after) | train s (before → after) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for label, a, b, *base in rooms:
        ma, _, na = full_row(a)
        mb, floor, nb = full_row(b)
        seeds = lambda n: f" ({n} seeds)" if n > 1 else ""  # noqa: E731
        fl = f"{100 * floor['chamfer_l1']:.2f} / {floor['f_score']:.3f} / {floor['normal_consistency']:.3f}"
        line = f"| {label} | {_cell(ma)}{seeds(na)} | {_cell(mb, mb['chamfer_l1'] < ma['chamfer_l1'])}{seeds(nb)} | {fl} | {fixed_targets(mb, fixed[label]) if label in (fixed or {}) else targets(mb, floor)} |"
        if with_base:
            mc, _, _ = full_row(base[0], "no-cues")
            line += (f" {_cell(mc)} | {beats_no_cues(mb, mc)} | {ma['psnr_300']:.1f} → {mb['psnr_300']:.1f}"
                     f" (step {mb['step_300']}) | {ma['train_s']:.0f} → {mb['train_s']:.0f} |")
        lines.append(line)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--doc", type=Path, required=True)
    ap.add_argument("--marker", required=True)
    ap.add_argument("--before", default="before")
    ap.add_argument("--after", default="after")
    ap.add_argument("--room", nargs="+", action="append", required=True,
                    help="LABEL BEFORE AFTER [NOCUES]: ablation_* folder names")
    ap.add_argument("--fixed-targets", nargs=4, action="append", default=[], metavar=("LABEL", "C_L1_CM", "F", "NC"),
                    help="score room LABEL against these targets instead of its floor")
    args = ap.parse_args()
    bad = [r for r in args.room if len(r) not in (3, 4)]
    if bad:
        ap.error(f"--room takes LABEL BEFORE AFTER [NOCUES], got {bad[0]}")
    fixed = {label: (float(c), float(f), float(n)) for label, c, f, n in args.fixed_targets}
    text = table([tuple(r) for r in args.room], args.before, args.after, fixed)
    replace_block(args.doc, args.marker, text)
    print(text)


if __name__ == "__main__":
    main()
