"""Markdown table of bench/results/icl_images_only_scale*.json (bench/icl_images_only_scale.sh): the
photos-only recipe on an images-only ICL model in its mapped unit, a guessed one and the exact one.

Usage: python bench/images_only_scale_table.py [--write] [RESULTS.json ...]
(--write: the table into docs/training.md between its <!-- images-only-scale --> markers.)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.doc_markers import replace_block  # noqa: E402

ROWS = {"mapped": "as mapped (COLMAP's unit)", "guess": "`--median-depth 2` (a guess)",
        "exact": "`--scale S` (exact)"}


def table(results: list[tuple[int, dict]]) -> str:
    """One row per unit and training seed: ``results`` are (seed, results file contents)."""
    lines = ["| unit | one unit taken as (m; error) | median view depth (units) | C-L1 cm / F / NC | with ICP | "
             "held-out PSNR dB | Gaussians at start | train s |",
             "|---|---:|---:|---|---|---:|---:|---:|"]
    for seed, res in results:
        for key, label in ROWS.items():
            v = res["variants"][key]
            figs = {icp: "{:.2f} / {:.3f} / {:.3f}".format(100 * v[icp]["chamfer_l1"], v[icp]["f_score"],
                                                           v[icp]["normal_consistency"]) for icp in ("no-icp", "icp")}
            lines.append(f"| {label}{f', seed {seed}' if seed else ''} | {v['m_per_unit']:.4f} "
                         f"({100 * v['metres_per_unit_error']:+.0f} %) | {v['median_view_depth_units']:.2f} | "
                         f"{figs['no-icp']} | {figs['icp']} | {v['test_psnr']:.2f} | "
                         f"{sum(v['gaussians_init'].values())} | {v['train_s']:.0f} |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    do_write = "--write" in argv
    argv = [a for a in argv if a != "--write"]
    paths = [Path(p) for p in argv] or sorted(Path("bench/results").glob("icl_images_only_scale*.json"))
    if not paths:
        print("no bench/results/icl_images_only_scale*.json: run bash bench/icl_images_only_scale.sh", file=sys.stderr)
        return 1
    text = table([(int(p.stem.rpartition("_seed")[2]) if "_seed" in p.stem else 0, json.loads(p.read_text()))
                  for p in paths])
    print(text)
    if do_write:
        replace_block(REPO / "docs" / "training.md", "images-only-scale", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
