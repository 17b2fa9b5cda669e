"""The `mvs` row trained on `--preset mvs` cues against `--preset room --plane.fill-holes` cues of the same
`geocues mvs` scenes (docs/training.md, "Room cues on a photos-only scene"), from bench/results/.

    python bench/mvs_cues_table.py     # prints the Markdown table: C-L1 cm / F / NC / held-out PSNR dB
"""

from __future__ import annotations

import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
PAIRS = [  # (label, --preset mvs cues, room cues): ablation_<name> folders
    ("ICL, seed 0", "icl_livingroom1_mvs_preset4_planarfill", "icl_livingroom1_mvs_preset4_planarfill_roomcues"),
    ("ICL, seed 1", "icl_livingroom1_mvs_preset4_planarfill_seed1", "icl_livingroom1_mvs_preset4_planarfill_roomcues_seed1"),
    ("ICL, seed 2", "icl_livingroom1_mvs_preset4_planarfill_seed2", "icl_livingroom1_mvs_preset4_planarfill_roomcues_seed2"),
    ("photos-only textured room s2, seed 0", "textured_s2_photos_mvs4_planarfill", "textured_s2_photos_mvs4_planarfill_roomcues"),
    ("photos-only textured room s2, seed 1", "textured_s2_photos_mvs4_planarfill_seed1",
     "textured_s2_photos_mvs4_planarfill_roomcues_seed1"),
    ("photos-only textured room s2, seed 2", "textured_s2_photos_mvs4_planarfill_seed2",
     "textured_s2_photos_mvs4_planarfill_roomcues_seed2"),
    ("photos-only bare room s0, seed 0", "bare_s0_photos_mvs4_planarfill", "bare_s0_photos_mvs4_planarfill_roomcues"),
    ("photos-only bare room s0, seed 1", "bare_s0_photos_mvs4_planarfill_seed1", "bare_s0_photos_mvs4_planarfill_roomcues_seed1"),
    ("photos-only bare room s3 (held out), seed 0", "bare_s3_photos_mvs4_planarfill", "bare_s3_photos_mvs4_planarfill_roomcues"),
]


def cell(name: str) -> str:
    data = json.loads((RESULTS / f"ablation_{name}" / "ablation.json").read_text())
    m = next(r for r in data["rows"] if r["row"] == "mvs")["mean"]
    return f"{100 * m['chamfer_l1']:.2f} / {m['f_score']:.3f} / {m['normal_consistency']:.3f} / {m['psnr']:.2f}"


def table() -> str:
    lines = ["| run | `--preset mvs` cues | `--preset room --plane.fill-holes` cues |", "|---|---|---|"]
    lines += [f"| {label} | {cell(a)} | {cell(b)} |" for label, a, b in PAIRS]
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
