"""Cue benchmark (issue 3): accuracy, coverage and speed of `geocues extract` against a GT mesh.

    python bench/cues_bench.py --scene outputs/rooms/textured_s0 --name textured_s0
    python bench/cues_bench.py --scene outputs/icl_sfm --name icl --gt ../shared/data/icl_livingroom1/reference_mesh.ply \
        --modes prior_free priors --simulate-priors-from ../shared/data/icl_livingroom1/depth

Per scene and mode (``priors``: the scene's depth priors are used; ``prior_free``: they are
ignored) it runs the full extract and measures, against the GT surface (exact point-to-triangle
distances, Open3D RaycastingScene):

* line samples: median distance, share within 1 and 2 cm;
* SfM points: share within 5 cm before and after statistical outlier removal;
* plane-like cues: median distance, share within 3 cm;
* coverage: share of GT surface samples (area-uniform, culled to what the cameras see) within
  5 cm of some cue point, per cue type and for all cues together;
* seconds per stage (from report.json), per image, and the whole run.

``--simulate-priors-from DEPTH_DIR`` builds a variant of the scene whose depth priors are
SIMULATED from ground-truth depth PNGs (ICL) with the benchmark rooms' prior simulator
(``evaluation.rooms.priors``); the variant's scene.json says so. Results go to
``bench/results/cues_<name>.json``; extract outputs to ``--out``/<name>_<mode>/. Not part of the
default tests (it runs minutes).
"""

from __future__ import annotations

import copy
import json
import logging
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluation.cue_metrics import (  # noqa: E402
    CueMetricsConfig, GroundTruth, coverage, median_or_none, share_within)
from geocues import extract as ex  # noqa: E402
from geocues.atomic import atomic_path  # noqa: E402
from geocues.cue_io import read_cues_ply  # noqa: E402
from geocues.scene import Scene  # noqa: E402
from geocues.types import CueType  # noqa: E402

log = logging.getLogger("bench.cues")

TARGETS = {"line_median_m_rooms": 0.01, "line_median_m_icl": 0.02, "line_within_2cm": 0.8,
           "plane_within_3cm_priors": 0.9, "plane_within_3cm_prior_free": 0.8,
           "per_image_s": 1.0, "icl_total_s": 300.0}


@dataclass
class BenchConfig:
    """Cue benchmark on one scene."""

    scene: Path
    """Scene folder (images/, sparse/0, optional priors/)."""
    name: str
    """Result name: bench/results/cues_<name>.json."""
    gt: Path | None = None
    """GT mesh (default: SCENE/gt/mesh.ply)."""
    modes: tuple[str, ...] = ("priors", "prior_free")
    """Runs to make, in order; the first runs with a cold cache when fresh is set."""
    out: Path = REPO / "outputs" / "cues" / "bench"
    """Where the extract outputs (and the shared per-scene cache) go."""
    fresh: bool = True
    """Clear the per-scene cache first, so the first mode's timings include every stage."""
    simulate_priors_from: Path | None = None
    """Folder of GT depth PNGs (uint16) to build a SIMULATED-prior variant of the scene from."""
    depth_png_scale: float = 1000.0
    """Units per metre of those PNGs (ICL: millimetres)."""
    n_gt_samples: int = 100_000
    """GT surface samples for coverage."""
    coverage_dist: float = 0.05
    """A GT sample is covered if a cue point lies within this distance (metres)."""
    seed: int = 0
    """Seed of GT sampling and prior simulation."""
    results: Path = REPO / "bench" / "results"
    """Folder of the result JSON."""
    extract: ex.ExtractConfig = field(default_factory=ex.ExtractConfig)
    """Extraction options (priors is set per mode)."""


def simulated_prior_scene(scene_dir: Path, depth_dir: Path, out: Path, png_scale: float, seed: int,
                          gt_mesh: Path | None = None) -> Path:
    """``scene_dir`` (images and model linked) with SIMULATED priors made from the GT depth in
    ``depth_dir`` and the GT mesh's normals: `evaluate simulate-priors` (evaluation.sim_priors)."""
    from evaluation.sim_priors import SimPriorsConfig, simulate_scene_priors

    cfg = SimPriorsConfig(seed=seed, gt_depth=depth_dir, gt_depth_png_scale=png_scale, gt_mesh=gt_mesh)
    return simulate_scene_priors(scene_dir, out, cfg, overwrite=True)


def measure(cues_dir: Path, gt: GroundTruth, cfg: BenchConfig) -> dict:
    """Accuracy and coverage of one extract output against the GT."""
    cues = read_cues_ply(cues_dir / "cues.ply")
    rep = json.loads((cues_dir / "report.json").read_text())
    dist = gt.distances(cues.xyz)
    out: dict = {"counts": cues.counts()}
    line_d = dist[cues.cue_type == CueType.LINE]
    plane_d = dist[cues.cue_type == CueType.PLANE]
    sfm_d = dist[cues.cue_type == CueType.SFM]
    out["line"] = {"n": int(len(line_d)), "median_m": median_or_none(line_d), "within_1cm": share_within(line_d, 0.01),
                   "within_2cm": share_within(line_d, 0.02), "n_lines": rep["n_lines"]}
    out["plane"] = {"n": int(len(plane_d)), "median_m": median_or_none(plane_d),
                    "within_3cm": share_within(plane_d, 0.03), "within_5cm": share_within(plane_d, 0.05)}
    out["sfm_after_sor"] = {"n": int(len(sfm_d)), "within_5cm": share_within(sfm_d, 0.05)}
    cov = {t.name: coverage(cues.xyz[cues.cue_type == t], gt.samples, cfg.coverage_dist) for t in CueType}
    cov["ALL"] = coverage(cues.xyz, gt.samples, cfg.coverage_dist)
    out["coverage_5cm"] = cov
    out["seconds"] = rep["seconds"]
    out["line_timings"] = rep.get("line_timings", {})
    out["per_image_seconds"] = rep.get("per_image_seconds", {})
    rows = [r for r in rep.get("per_image", []) if "alignment" in r]
    ok = [r["alignment"] for r in rows if r["alignment"]["ok"]]
    out["alignment"] = {
        "images_with_prior": len(rows), "aligned": len(ok),
        "skipped": {k: v for k, v in rep["rejections"].get("depth_align", {}).items()},
        "residual_median_m": median_or_none(np.array([a["residual_median_m"] for a in ok])),
        "residual_p90_m_median": median_or_none(np.array([a["residual_p90_m"] for a in ok])),
    }
    out["plane_modes"] = rep.get("planes", {}).get("plane_modes", {})
    out["rejections"] = rep["rejections"]
    out["notes"] = rep["notes"]
    return out


def run(cfg: BenchConfig) -> Path:
    scene_dir = Path(cfg.scene)
    cfg.out.mkdir(parents=True, exist_ok=True)
    if cfg.simulate_priors_from is not None:
        scene_dir = simulated_prior_scene(scene_dir, Path(cfg.simulate_priors_from),
                                          cfg.out / f"{cfg.name}_simprior_scene", cfg.depth_png_scale, cfg.seed,
                                          Path(cfg.gt) if cfg.gt else None)
    scene = Scene.load(scene_dir)
    gt_path = Path(cfg.gt) if cfg.gt else scene.gt_mesh_path
    if gt_path is None:
        raise FileNotFoundError(f"no GT mesh: pass --gt or put one at {scene_dir / 'gt' / 'mesh.ply'}")
    t0 = time.perf_counter()
    gt = GroundTruth(gt_path, scene.cameras, CueMetricsConfig(
        n_gt_samples=cfg.n_gt_samples, coverage_dist=cfg.coverage_dist, occlusion_tolerance=0.02, seed=cfg.seed))
    gt_samples, seen_frac = gt.samples, gt.seen_fraction
    log.info("GT: %s, %d samples on the seen %.1f %% of the surface (%.1f s)", gt_path, len(gt_samples),
             100 * seen_frac, time.perf_counter() - t0)

    sfm_all = gt.distances(scene.points.xyz)
    result: dict = {
        "scene": str(cfg.scene), "scene_used": str(scene_dir), "gt": str(gt_path),
        "n_images": len(scene.cameras), "image_size": [scene.cameras[0].width, scene.cameras[0].height],
        "priors_simulated": bool(scene.metadata.get("priors", {}).get("simulated", False)),
        "gt_samples": len(gt_samples), "gt_seen_fraction": seen_frac,
        "sfm_before_sor": {"n": int(len(sfm_all)), "within_5cm": share_within(sfm_all, 0.05)},
        "modes": {}, "config": json.loads(json.dumps(asdict(cfg), default=str)),
        "machine": {"cpus": os.cpu_count(), "note": "2 shared cores; other jobs ran at the same time"},
    }
    cache = cfg.out / f"{cfg.name}_cache"
    if cfg.fresh and cache.exists():
        shutil.rmtree(cache)
    for mode in cfg.modes:
        if mode not in ("priors", "prior_free"):
            raise ValueError(f"unknown mode {mode!r}, expected 'priors' or 'prior_free'")
        if mode == "priors" and not scene.has_depth_priors:
            log.warning("%s has no depth priors: mode 'priors' skipped", scene_dir)
            continue
        ecfg = copy.deepcopy(cfg.extract)
        ecfg.priors = mode == "priors"
        out_dir = cfg.out / f"{cfg.name}_{mode}"
        t = time.perf_counter()
        ex.run(ecfg, scene_dir, out_dir, overwrite=True, cache_dir=cache)
        wall = time.perf_counter() - t
        m = measure(out_dir, gt, cfg)
        m["wall_s"] = wall
        m["cold_cache"] = bool(cfg.fresh and mode == cfg.modes[0])  # first run after clearing the cache
        result["modes"][mode] = m
        log.info("%s %s: %s", cfg.name, mode, json.dumps({k: m[k] for k in ("counts", "line", "plane",
                                                                             "coverage_5cm")}))
    result["targets"] = TARGETS
    path = cfg.results / f"cues_{cfg.name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=1, default=str))
    log.info("wrote %s", path)
    return path


if __name__ == "__main__":
    import tyro

    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s", datefmt="%H:%M:%S")
    for name in ("geocues", "evaluation"):
        logging.getLogger(name).setLevel(logging.INFO)
    print(run(tyro.cli(BenchConfig)))
