"""A whole `splat train` run on a GPU machine that has no Open3D (no meshing there).

    python bench/gpu_train.py SCENE CUES OUT [--iters 30000] [--downscale 1] [--preset full]
        [--device cuda] [--backend cuda] [--max-gaussians 0] [--split-mb 15] [--compile]

Runs ``splat.train.run`` with ``mesh=False`` (the TSDF needs Open3D, which GPU images here lack) and
writes OUT/gpu_train.json: the run's report (seconds per stage, test PSNR/SSIM against seconds, the
Gaussian counts) plus the device and torch versions. With ``--split-mb`` the trained Gaussians are
also written compactly (no higher SH bands, float16 but the means) in parts of that many MiB
(OUT/gaussians.npz.part-aa, ...) so that a size-limited file transfer brings them back;
``join_compact`` rebuilds a run folder from them and the report, and ``splat mesh RUN`` then fuses
the mesh on a machine with Open3D. Needs torch, numpy, scipy,
PIL, tqdm, pyyaml and plyfile (no project install). Not part of the tests.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import torch  # noqa: E402

from splat.presets import preset_config  # noqa: E402
from splat.train import run  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path)
    p.add_argument("cues", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--iters", type=int, default=30_000)
    p.add_argument("--downscale", type=float, default=1.0)
    p.add_argument("--preset", default="full")
    p.add_argument("--device", default="cuda")
    p.add_argument("--backend", default="cuda")
    p.add_argument("--max-gaussians", type=int, default=0)
    p.add_argument("--split-mb", type=int, default=0)
    p.add_argument("--compile", action="store_true", help="TrainConfig.compile (splat/compiled.py)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cfg = preset_config(a.preset)
    cfg = replace(cfg, iters=a.iters, downscale=a.downscale, device=a.device, backend=a.backend, mesh=False,
                  compile=a.compile,
                  strategy=replace(cfg.strategy, max_gaussians=a.max_gaussians))
    run(cfg, a.scene, a.cues, a.out, overwrite=True)
    report = json.loads((a.out / "report.json").read_text())
    report["torch"] = torch.__version__
    report["device_name"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    (a.out / "gpu_train.json").write_text(json.dumps(report, indent=2))
    keys = ("timings", "accuracy_vs_time", "gaussians_final", "device_name")
    print(json.dumps({k: report.get(k) for k in keys}, indent=1))
    if a.split_mb > 0:
        split_compact(a.out, a.split_mb)
    return 0


def split_compact(run_dir: Path, part_mb: int) -> None:
    """The Gaussians without their higher SH bands (not needed for the mesh) as an npz (means float32,
    the rest float16, the cue types int8), cut into parts of ``part_mb`` MiB: gaussians.npz.part-aa, ..."""
    import io

    import numpy as np

    from splat.gaussians import load_ply

    params, cue_type = load_ply(run_dir / "point_cloud.ply")
    buf = io.BytesIO()
    np.savez(buf, means=params["means"].numpy().astype(np.float32), cue_type=cue_type.numpy().astype(np.int8),
             **{k: params[k].numpy().astype(np.float16) for k in ("scales", "quats", "opacities", "sh0")})
    data, size = buf.getvalue(), part_mb * 2**20
    for i in range(0, len(data), size):
        k = i // size
        (run_dir / f"gaussians.npz.part-{chr(97 + k // 26)}{chr(97 + k % 26)}").write_bytes(data[i:i + size])


def join_compact(parts_dir: Path, report: Path, run_dir: Path) -> Path:
    """Rebuild a run folder (point_cloud.ply with zero higher SH bands, report.json) from the parts that
    split_compact wrote and the run's report, for `splat mesh RUN` on a machine with Open3D."""
    import io

    import numpy as np

    from splat.gaussians import save_ply

    data = b"".join(p.read_bytes() for p in sorted(parts_dir.glob("gaussians.npz.part-*")))
    z = np.load(io.BytesIO(data))
    rep = json.loads(report.read_text())
    deg = rep["config"]["sh_degree"]
    n = len(z["means"])
    keys = ("means", "scales", "quats", "opacities", "sh0")
    params = {k: torch.from_numpy(z[k].astype(np.float32)) for k in keys}
    params["shN"] = torch.zeros(n, (deg + 1) ** 2 - 1, 3)
    run_dir.mkdir(parents=True, exist_ok=True)
    save_ply(run_dir / "point_cloud.ply", params, torch.from_numpy(z["cue_type"].astype(np.int64)))
    (run_dir / "report.json").write_text(json.dumps(rep, indent=2))
    return run_dir


if __name__ == "__main__":
    raise SystemExit(main())
