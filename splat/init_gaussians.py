"""The Gaussians a `splat train` run starts from: the cue cloud (paper §4.2), the scene's SfM points
(the 3DGS baseline), another run's PLY, and the hole seeds of ``--init.fill-holes``
(splat/hole_seeds.py)."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from geocues.cue_io import CueCloud, read_cue_report, read_cues_ply
from geocues.scene import Scene
from geocues.types import CueType
from splat.gaussians import init_from_cues, load_ply
from splat.strategy import AUTO_BUDGET_MIN, AUTO_BUDGET_PER_PIXEL, resolve_budget
from splat.train_config import TrainConfig

log = logging.getLogger(__name__)

FULL_INIT = 0.9  # an initial cloud above this share of the budget leaves densification too little room


def load_init_cloud(cfg: TrainConfig, scene: Scene, cues_ply: Path) -> CueCloud:
    """The points that seed the Gaussians: the cue cloud's ``cfg.cue_types``, or with
    ``init_from="sfm"`` the scene's SfM points as they are (3DGS init)."""
    if cfg.init_from == "sfm":
        if len(scene.points) == 0:
            raise ValueError(f"--init-from sfm: the scene {scene.root} has no SfM points "
                             "(run `geocues sfm SCENE` first)")
        return CueCloud.make(scene.points.xyz, scene.points.rgb, CueType.SFM)
    if cfg.init_from != "cues":
        raise ValueError(f"init_from must be 'cues' or 'sfm', got {cfg.init_from!r}")
    cloud = read_cues_ply(cues_ply)
    foreign = None if scene is None else foreign_cues(cues_ply, scene)
    share = 1.0 if scene is None or foreign else seen_share(cloud.xyz, scene)
    if foreign:
        log.warning("the cues %s were extracted from another scene than %s: %s. Run `geocues extract %s -o CUES` "
                    "for this one", cues_ply, scene.root, foreign, scene.root)
    elif share < 0.5:
        log.warning("only %.0f%% of the cue points of %s lie in front of and inside any view of the scene %s: "
                    "were the cues extracted from another scene (or the model re-posed since)? Run "
                    "`geocues extract %s -o CUES` for this one", 100 * share, cues_ply, scene.root, scene.root)
    cloud = cloud.select(np.isin(cloud.cue_type, [CueType[t].value for t in cfg.cue_types]))
    budget = _budget(with_budget(cfg, scene) if scene is not None else cfg)
    if not cfg.init.plane_share and budget > 0 and len(cloud) >= budget:
        log.warning("the cue cloud (%d points) is already at or over --strategy.max-gaussians %d: training "
                    "starts from all %d and densification adds none; raise the budget, or --init.plane-share "
                    "%.1f thins the PLANE seeds to leave room", len(cloud), budget, len(cloud), FULL_INIT)
    elif not cfg.init.plane_share and budget > 0 and len(cloud) > FULL_INIT * budget:
        log.warning("the cue cloud (%d points) fills %.0f%% of --strategy.max-gaussians %d before training, "
                    "leaving densification little or no room (on benchmark rooms such runs ended 6-7 dB lower in held-out PSNR); "
                    "--init.plane-share %.1f thins the PLANE seeds to leave some", len(cloud),
                    100 * len(cloud) / budget, budget, FULL_INIT)
    return thin_planes(cloud, cfg.init.plane_share, budget, cfg.seed)


def with_budget(cfg: TrainConfig, scene: Scene) -> TrainConfig:
    """``cfg`` with --strategy.max-gaussians a number: "auto" resolved from the largest training view
    at the training resolution (splat.strategy.resolve_budget), logged; ``scene`` is loaded at the
    training --downscale."""
    if cfg.strategy.max_gaussians != "auto":
        return cfg
    cam = max((scene.cameras[i] for i in scene.train_indices or range(len(scene.cameras))),
              key=lambda c: c.width * c.height)
    budget = resolve_budget("auto", cam.width * cam.height)
    log.info("Gaussian budget %d (--strategy.max-gaussians auto: %d x the %dx%d px of a training view, at least "
             "%d; 0 = no limit)", budget, AUTO_BUDGET_PER_PIXEL, cam.width, cam.height, AUTO_BUDGET_MIN)
    return replace(cfg, strategy=replace(cfg.strategy, max_gaussians=budget))


def _budget(cfg: TrainConfig) -> int:
    """--strategy.max-gaussians as a number (0: no limit); "auto" is resolved by with_budget."""
    if cfg.strategy.max_gaussians == "auto":
        raise ValueError("--strategy.max-gaussians auto is resolved from the training views first "
                         "(with_budget)")
    return cfg.strategy.max_gaussians


def foreign_cues(cues_ply: Path, scene: Scene) -> str | None:
    """Why the cues at ``cues_ply`` belong to another scene, from the camera signature `geocues extract`
    recorded in their report.json (geocues/camera_signature.py); None when they agree or nothing was recorded."""
    from geocues.camera_signature import camera_signature, signature_mismatch

    recorded = read_cue_report(cues_ply).get("cameras")
    return signature_mismatch(recorded, camera_signature(scene)) if recorded else None


def seen_share(xyz: np.ndarray, scene: Scene, max_points: int = 5000) -> float:
    """Share of the points ``xyz`` [N, 3] (an evenly spaced sample of at most ``max_points``) in front
    of and inside the image of at least one camera of ``scene``; 1 for no points. Cues extracted from
    the scene's own views are all seen; another scene's mostly are not."""
    if len(xyz) == 0:
        return 1.0
    pts = xyz[np.linspace(0, len(xyz) - 1, min(len(xyz), max_points)).astype(int)]
    seen = np.zeros(len(pts), bool)
    for cam in scene.cameras:
        uv, z = cam.project(pts)
        seen |= (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return float(seen.mean())


def thin_planes(cloud: CueCloud, share: float, budget: int, seed: int = 0) -> CueCloud:
    """``cloud`` with its PLANE points thinned at random (``seed``) so that it holds at most
    ``share`` x ``budget`` points (``--init.plane-share``); unchanged when off (share or budget 0)
    or already within. PLANE points only: never cloned under the paper's rule, they are the ones a
    budget-filling init has most of, and their neighbours' distance sets the survivors' scale."""
    if not 0 <= share <= 1:
        raise ValueError(f"--init.plane-share must be in [0, 1], got {share}")
    if share == 0 or budget <= 0 or len(cloud) <= share * budget:
        return cloud
    plane = np.flatnonzero(cloud.cue_type == CueType.PLANE)
    keep_n = max(int(share * budget) - (len(cloud) - len(plane)), 0)
    if keep_n >= len(plane):
        return cloud
    keep = np.ones(len(cloud), bool)
    keep[np.random.default_rng(seed).choice(plane, len(plane) - keep_n, replace=False)] = False
    log.info("--init.plane-share %.2f: %d of %d PLANE seeds kept, the initial Gaussians take %d of the %d budget",
             share, keep_n, len(plane), int(keep.sum()), budget)
    return cloud.select(keep)


def initial_gaussians(cfg: TrainConfig, scene: Scene, cues_ply: Path, views=None
                      ) -> tuple[dict[str, Tensor], Tensor, np.ndarray]:
    """(params, cue_type [N], seed points [N, 3]) to start from: the Gaussians of ``cfg.init_ply``, or
    Gaussians initialised from :func:`load_init_cloud` (paper §4.2), with ``--init.fill-holes`` also
    from the hole seeds of the training ``views`` (a :class:`splat.views.ViewSet`; splat/hole_seeds.py).
    The seed points are the cloud's (without the hole seeds: they set the scene scale)."""
    cfg = with_budget(cfg, scene)
    if cfg.init_ply is None:
        cloud = load_init_cloud(cfg, scene, cues_ply)
        params, cue_type = init_from_cues(cloud, cfg.sh_degree, cfg.init)
        if cfg.init.fill_holes and views is not None:
            params, cue_type = _with_hole_seeds(cfg, cloud, params, cue_type, views)
        return params, cue_type, cloud.xyz
    ignored = [setting for setting, on in ((f"--cue-types {' '.join(cfg.cue_types)}",
                                            tuple(cfg.cue_types) != ("SFM", "LINE", "PLANE")),
                                           (f"--init-from {cfg.init_from}", cfg.init_from != "cues"),
                                           ("--init.fill-holes", cfg.init.fill_holes)) if on]
    if ignored:  # from the command line or a preset; they choose the cues a run starts from
        log.warning("--init-ply %s: the settings %s are not applied (they choose the cues a run starts from; "
                    "these Gaussians are taken whole)", cfg.init_ply, ", ".join(ignored))
    try:
        params, cue_type = load_ply(cfg.init_ply, sh_degree=cfg.sh_degree)
    except ValueError as e:  # "load it with sh_degree=None or 3": the flag here
        raise ValueError(str(e).replace("load it with sh_degree=None or", "train with --sh-degree")) from None
    n = len(params["means"])
    if n == 0:
        raise ValueError(f"--init-ply {cfg.init_ply} holds no Gaussians")
    if cue_type is None:
        log.info("--init-ply %s has no cue types (no cue_type.npy beside it): all %d Gaussians are SFM", cfg.init_ply, n)
        cue_type = torch.full((n,), CueType.SFM.value, dtype=torch.int64)
    log.info("starting from the %d Gaussians of %s", n, cfg.init_ply)
    if 0 < (budget := _budget(cfg)) <= n:
        log.warning("--init-ply %s: its %d Gaussians are at or over --strategy.max-gaussians %d, so densification "
                    "adds none; raise the budget (0: no limit) to let them grow", cfg.init_ply, n, budget)
    return params, cue_type, params["means"].numpy().astype(np.float64)


def _with_hole_seeds(cfg: TrainConfig, cloud: CueCloud, params: dict[str, Tensor], cue_type: Tensor, views
                     ) -> tuple[dict[str, Tensor], Tensor]:
    """The Gaussians of ``cloud`` and of the hole seeds ``params`` leaves in the ``views``; unchanged
    when no view has an anchor."""
    from splat.hole_seeds import hole_seeds

    extra = hole_seeds(params, views, cfg.init.hole_stride, cfg.init.hole_alpha, cfg.init.hole_voxel)
    if len(extra) == 0:
        log.info("--init.fill-holes: no training view has an L_a anchor, so no hole seeds")
        return params, cue_type
    budget = _budget(cfg)
    room = budget - len(cloud)
    if budget > 0 and len(extra) > room:  # the budget holds from the first step, as densification keeps it
        keep = np.zeros(len(extra), bool)
        keep[np.random.default_rng(cfg.seed).choice(len(extra), max(room, 0), replace=False)] = True
        log.info("--init.fill-holes: %d of %d hole seeds kept, within --strategy.max-gaussians %d",
                 int(keep.sum()), len(extra), budget)
        extra = extra.select(keep)
    return init_from_cues(CueCloud.concat([cloud, extra]), cfg.sh_degree, cfg.init)
