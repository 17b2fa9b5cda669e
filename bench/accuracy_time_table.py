"""docs/training.md's accuracy-against-time table from bench/results/train_<name>.json (bench/train_bench.py).

    python bench/accuracy_time_table.py            # textured_s0 as "paper", textured_s0_anchor as "+ L_a"

Replaces the text between ``<!-- accuracy-vs-time -->`` and ``<!-- /accuracy-vs-time -->``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.doc_markers import replace_block  # noqa: E402
RUNS = (("paper", "textured_s0"), ("+ L_a", "textured_s0_anchor"))


def table(runs=RUNS) -> str:
    lines = ["| loss | step | train s | test PSNR | SSIM | Gaussians | acc (m) | comp (m) | Chamfer-L1 (m) | F@5cm | NC |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for label, name in runs:
        for r in json.loads((REPO / "bench" / "results" / f"train_{name}.json").read_text())["rows"]:
            lines.append(f"| {label} | {r['step']} | {r['train_s']:.0f} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
                         f"{r['n_gaussians']:,} | {r['accuracy']:.3f} | {r['completeness']:.3f} | "
                         f"{r['chamfer_l1']:.3f} | {r['f_score']:.3f} | {r['normal_consistency']:.3f} |")
    return "\n".join(lines)


def main(doc: Path = REPO / "docs" / "training.md") -> None:
    replace_block(doc, "accuracy-vs-time", table())
    print(f"wrote the table into {doc}")


if __name__ == "__main__":
    main()
