"""Training variants side by side on a benchmark room: mesh metrics, held-out PSNR and where the
rendered depth goes wrong, for each set of `splat train` options.

    python bench/train_variants.py --scene outputs/demo/room --cues outputs/demo/cues --name textured_1k

Each variant is one `splat train` run (common options + the variant's), scored with the
``evaluate`` protocol against the room's GT mesh and with ``bench/depth_diag.py`` against its exact
GT depth. A variant whose output folder already holds all three results is not run again (delete
the folder to re-run it). Results go to ``bench/results/train_variants_<name>.json`` and are printed
as a table. Slow (about 2.5 min a variant at the defaults on 2 cores); not part of the tests.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import tyro

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

VARIANTS = {
    "paper": "",
    "paper_seed1": "--seed 1",
    "flatten_sfm_too": "--loss.flat-types 0 1",
    "no_sfm_cues": "--cue-types LINE PLANE",
    "pcc_patch_64": "--loss.patch-size 64",
    "lambda_depth_0.5": "--loss.lambda-depth 0.5",
    "budget_200k": "--strategy.max-gaussians 200000",
    "anchor_1": "--loss.lambda-anchor 1 --loss.anchor-tol-p90 1",
    "anchor_5": "--loss.lambda-anchor 5 --loss.anchor-tol-p90 1",
    "anchor_1_tol_half": "--loss.lambda-anchor 1 --loss.anchor-tol-p90 0.5",
    "anchor_5_tol_half": "--loss.lambda-anchor 5 --loss.anchor-tol-p90 0.5",
    "anchor_5_tol_half_seed1": "--loss.lambda-anchor 5 --loss.anchor-tol-p90 0.5 --seed 1",
}


@dataclass
class TrainVariants:
    scene: Path
    cues: Path
    name: str
    """Result name: bench/results/train_variants_NAME.json."""
    out: Path = Path("outputs/train_variants")
    common: str = "--iters 1000 --downscale 2 --strategy.max-gaussians 100000"
    """`splat train` options shared by every variant (a later option wins)."""
    only: list[str] = field(default_factory=list)
    """Run only these variants (default: all of VARIANTS)."""


def _run(cmd: list[str], log: Path) -> None:
    with open(log, "a") as f:
        f.write("$ " + shlex.join(cmd) + "\n")
        f.flush()
        subprocess.run(cmd, check=True, stdout=f, stderr=subprocess.STDOUT, cwd=REPO)


def run_variant(cfg: TrainVariants, name: str, options: str) -> dict:
    out = cfg.out / cfg.name / name
    files = [out / "report.json", out / "metrics.json", out / "depth_diag.json"]
    if not all(f.is_file() for f in files):
        out.mkdir(parents=True, exist_ok=True)
        log = out.parent / f"{name}.log"
        _run([str(BIN / "splat"), "train", str(cfg.scene), "-c", str(cfg.cues), "-o", str(out),
              *shlex.split(cfg.common), *shlex.split(options)], log)
        _run([str(BIN / "evaluate"), str(out / "mesh.ply"), str(cfg.scene), "-o", str(out / "metrics.json"),
              "--overwrite"], log)
        _run([sys.executable, str(REPO / "bench" / "depth_diag.py"), "--scene", str(cfg.scene), "--model", str(out),
              "--json", str(out / "depth_diag.json")], log)
    report, mesh, depth = (json.loads(f.read_text()) for f in files)
    return {"options": options, "train_s": report["timings"]["train_s"], "psnr": report["test_metrics"]["psnr"],
            "ssim": report["test_metrics"]["ssim"], "gaussians": report["gaussians_final"],
            "mesh": {k: mesh[k] for k in ("accuracy", "completeness", "chamfer_l1", "f_score", "normal_consistency")},
            "depth": {k: depth[k] for k in ("within_5cm", "in_front_5cm", "behind_5cm", "hole")}}


def main(cfg: TrainVariants) -> Path:
    names = cfg.only or list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    rows = {n: run_variant(cfg, n, VARIANTS[n]) for n in names}
    result = {"scene": str(cfg.scene), "cues": str(cfg.cues), "common": cfg.common, "variants": rows}
    path = REPO / "bench" / "results" / f"train_variants_{cfg.name}.json"
    path.write_text(json.dumps(result, indent=2))
    print(f"{'variant':26s} {'train s':>7s} {'PSNR':>6s} {'acc cm':>6s} {'comp cm':>7s} {'C-L1 cm':>7s} "
          f"{'F@5cm':>6s} {'NC':>6s} {'d<5cm':>6s} {'front':>6s}")
    for n, r in rows.items():
        m, d = r["mesh"], r["depth"]
        print(f"{n:26s} {r['train_s']:7.0f} {r['psnr']:6.2f} {100 * m['accuracy']:6.1f} {100 * m['completeness']:7.1f} "
              f"{100 * m['chamfer_l1']:7.1f} {m['f_score']:6.3f} {m['normal_consistency']:6.3f} "
              f"{d['within_5cm']:6.3f} {d['in_front_5cm']:6.3f}")
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main(tyro.cli(TrainVariants))
