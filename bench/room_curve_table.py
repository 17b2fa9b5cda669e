"""What the mesh gains after each checkpoint: per room, the checkpoint metrics of one `splat ablate` row.

Every `splat ablate` run fuses a mesh at its checkpoints (steps 300 / 750 / 1500 / 3000 of 3000) and
stores their figures in ``ablation.json`` (``rows[].runs[].curve``). This prints, for each named
result folder, Chamfer-L1 / F@5cm / NC / held-out PSNR and the training seconds at every checkpoint,
and a last line with the change from the 1500th step to the end over all of them: how much of the
mesh the second half of the run buys. With ``--doc`` the table replaces the text between
``<!-- MARKER -->`` and ``<!-- /MARKER -->``.

    python bench/room_curve_table.py --row full --doc docs/training.md --marker room-curve \
        --room "textured s0" textured_s0_room_wallsnap --room "bare s0" bare_s0_room_wallsnap
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.doc_markers import replace_block  # noqa: E402


def curves(name: str, row: str) -> list[list[dict]]:
    """The checkpoint curves (one per seed) of row ``row`` in bench/results/ablation_<name>."""
    path = REPO / "bench" / "results" / f"ablation_{name}" / "ablation.json"
    if not path.is_file():
        raise SystemExit(f"room_curve_table: no {path}")
    rows = [r for r in json.loads(path.read_text())["rows"] if r["row"] == row]
    if not rows or not rows[0].get("runs"):
        raise SystemExit(f"room_curve_table: {path} has no finished row {row!r}")
    return [run["curve"] for run in rows[0]["runs"] if run.get("curve")]


def _cell(c: dict) -> str:
    return (f"{100 * c['chamfer_l1']:.2f} / {c['f_score']:.3f} / {c['normal_consistency']:.3f} / "
            f"{c['psnr']:.1f} ({c['train_s']:.0f} s)")


def table(rooms: list[tuple[str, str]], row: str, mid: int = 1500) -> str:
    steps: list[int] = []
    body, deltas = [], []
    for label, name in rooms:
        for curve in curves(name, row):
            by_step = {c["step"]: c for c in curve if c.get("f_score") is not None}
            steps = steps or sorted(by_step)
            if sorted(by_step) != steps:
                raise SystemExit(f"room_curve_table: {name} has checkpoints {sorted(by_step)}, not {steps}")
            body.append(f"| {label} | " + " | ".join(_cell(by_step[s]) for s in steps) + " |")
            a, b = by_step[mid], by_step[steps[-1]]
            deltas.append((100 * (b["chamfer_l1"] - a["chamfer_l1"]), b["f_score"] - a["f_score"],
                           b["normal_consistency"] - a["normal_consistency"], b["psnr"] - a["psnr"],
                           b["train_s"] - a["train_s"]))
    head = ["| room | " + " | ".join(f"step {s}" for s in steps) + " |", "|---" * (len(steps) + 1) + "|"]
    spans = []
    for k, (n, fmt) in enumerate((("C-L1", "+.2f"), ("F", "+.3f"), ("NC", "+.3f"), ("PSNR", "+.2f"),
                                  ("training", "+.0f"))):
        v = [d[k] for d in deltas]
        unit = {"C-L1": " cm", "PSNR": " dB", "training": " s"}.get(n, "")
        spans.append(f"{n} {statistics.median(v):{fmt}}{unit} ({min(v):{fmt}} to {max(v):{fmt}})")
    foot = (f"\nFrom step {mid} to step {steps[-1]}, median (range) over the {len(deltas)} runs: "
            + ", ".join(spans) + ".")
    return "\n".join(head + body) + "\n" + foot


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--room", nargs=2, action="append", metavar=("LABEL", "NAME"), required=True)
    ap.add_argument("--row", default="full")
    ap.add_argument("--mid", type=int, default=1500, help="the checkpoint the last line compares the end with")
    ap.add_argument("--doc", type=Path)
    ap.add_argument("--marker", default="room-curve")
    args = ap.parse_args()
    text = table([tuple(r) for r in args.room], args.row, args.mid)
    if args.doc is None:
        print(text)
        return
    replace_block(args.doc, args.marker, text)
    print(f"wrote the table into {args.doc}")


if __name__ == "__main__":
    main()
