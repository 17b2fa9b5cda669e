"""The values `geocues extract` refuses before any work (found by a sweep of 150 runs over its options):
a NaN anywhere, an inf (``--line.support-dist-px inf`` was an OverflowError traceback), and values that
gave empty cues or garbage without a word (``--plane.min-ray-cos 2``, ``--sor.sor-neighbors 1``,
``--texture.work-width 0``, a negative angle). One error naming the option as the command spells it.
The stages' own ``validate()`` (lines, floor) run after these. Also what a refused rerun changed and the
options of stages that are off."""

from __future__ import annotations

import json
import math
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

POSITIVE = {  # > 0
    "line": ("min_length_px", "dedup_dist_px", "support_dist_px", "support_depth_rel", "max_depth_m",
             "max_line_sigma_m", "link_depth_rel", "merge_dist_m", "merge_gap_m", "sample_step"),
    "texture": ("graph_sigma", "graph_k", "merge_step", "sift_contrast_threshold", "weak_density",
                "max_segment_density"),
    "align": ("inlier_rel", "min_depth_spread", "huber_rel", "edge_rel", "warp_max", "min_scale"),
    "plane": ("voxel_size", "anchor_sigma", "max_plane_std", "cut_px", "max_depth", "ransac_dist", "ransac_rel",
              "occlusion_rel", "agree_search_rel", "agree_dist", "occluder_jump", "occluder_step_px",
              "free_ransac_dist", "free_loo_dist", "fuse_dist", "fuse_prior_rel", "fuse_prior_dist",
              "support_radius", "conflict_radius"),
    "floor": ("ceiling_margin",),
}
NON_NEGATIVE = {  # >= 0 (0: off where the option says so)
    "sor": ("max_reproj_error", "min_track_length"),
    "align": ("warp_degree", "warp_ridge", "edge_px"),
    "texture": ("erode_px",),
    "plane": ("border_px", "min_agree_anchors", "free_min_off_line"),
}
AT_LEAST_ONE = {  # counts and sizes
    "line": ("max_segments", "n_neighbors", "topk_matches", "min_track_nodes"),
    "texture": ("segment_width", "graph_min_size", "slic_region_size", "density_window"),
    "align": ("min_anchors", "max_anchors", "ransac_iters"),
    "plane": ("pixel_stride", "min_region_points", "max_planes", "free_min_anchors", "free_min_groups",
              "free_local_k", "min_plane_views", "min_views"),
    "floor": ("ceiling_min_views",),
}
FRACTIONS = {  # in [0, 1]
    "line": ("min_pair_overlap", "support_coverage", "min_support_ratio", "min_track_ratio", "extent_min_share",
             "min_epipolar_iou"),
    "texture": ("min_region_frac",),
    "plane": ("min_plane_frac", "free_min_inlier_ratio", "free_local_ratio", "min_ray_cos"),
}
MIN_WORK_WIDTH = 16  # px: texture.work_width below this was raised to it in silence


def flag(path: str) -> str:
    """A config field's dotted path as the command line spells it: ``line.min_views`` -> ``--line.min-views``."""
    return "--" + path.replace("_", "-")


def float_options(obj: Any, prefix: str = ""):
    """(dotted path, value) of every float of a config, tuples' items included."""
    for f in fields(obj):
        value = getattr(obj, f.name)
        if is_dataclass(value):
            yield from float_options(value, f"{prefix}{f.name}.")
        elif isinstance(value, float):
            yield prefix + f.name, value
        elif isinstance(value, tuple):
            yield from ((prefix + f.name, v) for v in value if isinstance(v, float))


def check_extract_options(cfg) -> None:
    """Raise ValueError naming the first impossible option of ``cfg`` (a geocues.extract.ExtractConfig)."""
    if not (cfg.sfm or cfg.lines or cfg.planes):
        raise ValueError("--no-sfm --no-lines --no-planes leave nothing to extract: keep one stage on")
    check_finite(cfg)
    for path, value in float_options(cfg):
        if path.endswith("_deg") and not 0 <= value <= 180:
            raise ValueError(f"{flag(path)} is an angle and must be in [0, 180] degrees, got {value}")

    def each(table):
        for group, names in table.items():
            for name in names:
                yield f"{group}.{name}", getattr(getattr(cfg, group), name)

    for path, value in each(POSITIVE):
        if not value > 0:
            raise ValueError(f"{flag(path)} must be > 0, got {value}")
    for path, value in each(NON_NEGATIVE):
        if value < 0:
            raise ValueError(f"{flag(path)} must be >= 0 (0: off), got {value}")
    for path, value in each(AT_LEAST_ONE):
        if value < 1:
            raise ValueError(f"{flag(path)} must be >= 1, got {value}")
    for path, value in each(FRACTIONS):
        if not 0 <= value <= 1:
            raise ValueError(f"{flag(path)} is a share and must be in [0, 1], got {value}")
    if cfg.sor.sor_neighbors < 2:  # Open3D's outlier removal with one neighbour removes every point
        raise ValueError(f"--sor.sor-neighbors must be >= 2, got {cfg.sor.sor_neighbors}")
    if not cfg.sor.sor_std_ratio > 0:
        raise ValueError(f"--sor.sor-std-ratio must be > 0, got {cfg.sor.sor_std_ratio}")
    if cfg.texture.work_width < MIN_WORK_WIDTH:
        raise ValueError(f"--texture.work-width must be >= {MIN_WORK_WIDTH} px, got {cfg.texture.work_width}")
    if cfg.align.max_anchors < cfg.align.min_anchors:
        raise ValueError(f"--align.max-anchors ({cfg.align.max_anchors}) must be >= --align.min-anchors "
                         f"({cfg.align.min_anchors}): every image would be skipped for too few anchors")
    if not cfg.downscale > 0:
        raise ValueError(f"--downscale must be > 0, got {cfg.downscale}")


def idle_options(cfg) -> list[str]:
    """Sentences naming options set away from their defaults for a stage that is off (they do nothing:
    `--floor.min-views 10` without --floor.lines ran as if not given, under the same config key)."""
    default = type(cfg)()
    stages = [("floor", not (cfg.floor.lines and cfg.planes),
               "floor lines are off (--floor.lines)" if cfg.planes else "the plane stage is off (--no-planes)"),
              ("line", not (cfg.lines or (cfg.floor.lines and cfg.planes)),  # floor lines detect with --line.*
               "the line stage is off (--no-lines)"),
              ("sor", not cfg.sfm, "the SfM stage is off (--no-sfm)"),
              ("plane", not cfg.planes, "the plane stage is off (--no-planes)"),
              ("texture", not cfg.planes, "the plane stage is off (--no-planes)"),
              ("align", not (cfg.planes and cfg.priors), "depth priors are not read (--no-planes or --no-priors)")]
    out = []
    for group, off, why in stages:
        if not off:
            continue
        changed = [flag(f"{group}.{f.name}") for f in fields(getattr(cfg, group))
                   if getattr(getattr(cfg, group), f.name) != getattr(getattr(default, group), f.name)
                   and not (group == "floor" and f.name == "lines")]
        if changed:
            out.append(f"{', '.join(changed)} do{'es' * (len(changed) == 1)} nothing: {why}")
    return out


def what_changed(old: dict, key_cfg: dict, default_key_cfg: dict, scene_dir: Path) -> str:
    """Which options of the config key (``key_cfg``: the options as hashed, fields kept out of the key
    left out) differ from an earlier report's (one it does not record counts when set away from its
    default, ``default_key_cfg``), or else that the scene's files changed."""
    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
        return out

    now, default = (flat(json.loads(json.dumps(c, default=str))) for c in (key_cfg, default_key_cfg))
    then = flat(old.get("config", {}))
    changed = ["--" + k.replace("_", "-") for k, v in now.items() if then.get(k, default.get(k)) != v]
    if changed:
        return f"options {', '.join(changed[:6])}{', ...' if len(changed) > 6 else ''} differ"
    if old.get("scene") and Path(old["scene"]).resolve() != Path(scene_dir).resolve():
        return f"it was extracted from {old['scene']}"
    return "the same options: the scene's images/, priors/, sparse/ or scene.json changed since"


def check_finite(cfg: Any, prefix: str = "") -> None:
    """Raise ValueError naming the first NaN or infinite float of the config ``cfg`` (options under
    ``prefix``): every comparison with NaN is False, so range checks let it through."""
    for path, value in float_options(cfg, prefix):
        if not math.isfinite(value):
            raise ValueError(f"{flag(path)} must be a finite number, got {value}")


__all__ = ["check_extract_options", "check_finite", "flag", "float_options", "idle_options", "what_changed"]
