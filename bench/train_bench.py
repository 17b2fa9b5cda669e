"""Accuracy against time: `splat train` with meshes at checkpoints, each measured against the GT mesh.

    python bench/train_bench.py --scene outputs/demo/room --cues outputs/demo/cues --name textured_s0 \
        --train.iters 3000 --train.downscale 2 [--gt GT_MESH] [train options as in `splat train`, prefixed
        with --train., e.g. --train.strategy.max-gaussians 100000]

One training run; at each checkpoint (fractions of the run) it records the training seconds so
far, the test-view PSNR / SSIM and the Gaussian count (splat/train.py), and fuses a TSDF mesh from
the training views (not counted as training time). Each mesh is then scored with the
``evaluate`` protocol (MonoSDF: culled to the scene's cameras, 5 cm F-score). The result —
a row per checkpoint with seconds, PSNR, SSIM, accuracy, completeness, Chamfer-L1, F-score and
normal consistency — goes to ``bench/results/train_<name>.json`` and is printed as a table. Not
part of the default tests (it runs minutes).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import tyro  # noqa: E402

from evaluation.mesh_metrics import MeshMetricsConfig, evaluate_with_scene  # noqa: E402
from geocues.atomic import atomic_path  # noqa: E402
from splat.train import TrainConfig, run  # noqa: E402

log = logging.getLogger("bench.train")


@dataclass
class TrainBench:
    """Accuracy against training time on one scene."""

    scene: Path
    """Scene folder (with gt/mesh.ply, or pass --gt)."""
    cues: Path
    """Cue folder from `geocues extract`."""
    name: str
    """Result name: bench/results/train_NAME.json."""
    gt: Path | None = None
    """GT mesh (default: SCENE/gt/mesh.ply)."""
    out: Path = Path("outputs/train_bench")
    """Training outputs go to OUT/NAME."""
    train: TrainConfig = field(default_factory=lambda: TrainConfig(
        iters=3000, checkpoints=(0.05, 0.1, 0.25, 0.5, 1.0), mesh_at_checkpoints=True))
    metrics: MeshMetricsConfig = field(default_factory=MeshMetricsConfig)


def main(cfg: TrainBench) -> dict:
    from cli._dispatch import setup_logging

    setup_logging()
    train_cfg = replace(cfg.train, mesh=True, mesh_at_checkpoints=True)
    out_dir = cfg.out / cfg.name
    t0 = time.perf_counter()
    run(train_cfg, cfg.scene, cfg.cues, out_dir, overwrite=True)
    wall = time.perf_counter() - t0
    report = json.loads((out_dir / "report.json").read_text())
    rows = []
    for point in report["accuracy_vs_time"]:
        m = evaluate_with_scene(out_dir / point["mesh"], cfg.gt, cfg.scene, cfg.metrics).to_dict()
        rows.append({**{k: point[k] for k in ("step", "train_s", "psnr", "ssim", "n_gaussians")},
                     **{k: m[k] for k in ("accuracy", "completeness", "chamfer_l1", "f_score",
                                          "normal_consistency")}})
    result = {"scene": str(cfg.scene), "cues": str(cfg.cues), "train_config": asdict(train_cfg),
              "metrics_protocol": asdict(cfg.metrics), "rows": rows, "timings": report["timings"],
              "wall_s": wall, "gaussians_init": report["gaussians_init"],
              "gaussians_final": report["gaussians_final"]}
    path = REPO / "bench" / "results" / f"train_{cfg.name}.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=2, default=str))
    print(format_rows(rows))
    print(f"wrote {path}")
    return result


def format_rows(rows: list[dict]) -> str:
    head = f"{'step':>6}{'train s':>9}{'PSNR':>7}{'SSIM':>7}{'Gauss.':>8}{'acc m':>8}{'comp m':>8}{'C-L1':>8}{'F@5cm':>7}{'NC':>7}"
    lines = [head]
    for r in rows:
        lines.append(f"{r['step']:>6}{r['train_s']:>9.1f}{r['psnr']:>7.2f}{r['ssim']:>7.3f}{r['n_gaussians']:>8}"
                     f"{r['accuracy']:>8.4f}{r['completeness']:>8.4f}{r['chamfer_l1']:>8.4f}{r['f_score']:>7.3f}"
                     f"{r['normal_consistency']:>7.3f}")
    return "\n".join(lines)


if __name__ == "__main__":
    main(tyro.cli(TrainBench))
