"""The configuration key of an ablation row (`splat ablate`): what the row trains and how it is scored,
hashed, so that a finished row is found again and a changed one trained again. Options that never
change what a run computes, and options added after rows were first keyed while they stay off, are
left out of it, so that a toolkit upgrade does not re-run finished rows."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict


# TrainConfig fields that never change what a run computes (when and whether it checkpoints; the
# numerics guard, which only acts on a non-finite or diverging step and then stops or rolls back a
# run the report marks; the live view): left out of a row's key, so that adding one does not re-run
# finished rows. The TSDF device enters the key in one spelling ("cpu" and Open3D's "CPU:0" agree).
OPERATIONAL_FIELDS = ("save_every", "keep_ckpt", "guard", "view", "view_port", "view_every",
                      "compile")  # compile: the same loss up to float rounding (tests/test_compiled.py)


def config_key(payload: dict) -> str:
    return hashlib.sha1(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


_ADDED_LATER = (  # options added after rows were first keyed: (config section, "" = top level, its fields, "left off")
    ("tsdf", lambda k: k.startswith("consisten"), lambda s: s.get("consistent_views") is None),
    ("tsdf", lambda k: k == "max_depth_spread", lambda s: s.get("max_depth_spread") is None),
    ("tsdf", lambda k: k == "smooth_iters", lambda s: not s.get("smooth_iters")),
    ("loss", lambda k: k == "plane_anchor", lambda s: not s.get("plane_anchor")),
    ("loss", lambda k: k == "plane_normals", lambda s: not s.get("plane_normals")),
    ("init", lambda k: k in ("fill_holes", "hole_alpha", "hole_stride", "hole_voxel"),
     lambda s: not s.get("fill_holes")),
    ("init", lambda k: k == "plane_share", lambda s: not s.get("plane_share")),
    ("loss", lambda k: k.startswith("fused_"), lambda s: not s.get("fused_anchor")),
    ("loss", lambda k: k in ("fused_method", "fused_neighbours"),
     lambda s: s.get("fused_method", "tsdf") == "tsdf" and s.get("fused_neighbours", 32) == 32),
    ("loss", lambda k: k in ("plane_first", "plane_views"),
     lambda s: not s.get("plane_first") and s.get("plane_views", "own") == "own"),
    ("loss", lambda k: k == "lambda_mv" or k.startswith("mv_"), lambda s: not s.get("lambda_mv")),
    ("strategy", lambda k: k == "plane_rule", lambda s: s.get("plane_rule", "none") == "none"),
    ("", lambda k: k in ("pose_opt", "focal_opt", "pose_lr", "focal_lr"),
     lambda s: not s.get("pose_opt") and not s.get("focal_opt")),
    ("", lambda k: k == "geometry_until", lambda s: s.get("geometry_until", 1.0) == 1.0),
    ("", lambda k: k in ("priors_until", "priors_kept"),
     lambda s: s.get("priors_until", 1.0) == 1.0 and not s.get("priors_kept")),
)


def row_keys(spec: dict) -> list[str]:
    """The key of a row (first): what it trains and how it is scored, without
    :data:`OPERATIONAL_FIELDS` and without options left unset (None), so that an option added later,
    unset, keeps the key; then the keys the same row got under earlier key rules: a finished row
    with any of them is the same row."""
    from splat.mesh import open3d_device

    payload = {k: spec[k] for k in ("scene", "cues", "gt", "metrics")}
    tc = {k: v for k, v in spec["train_config"].items() if k not in OPERATIONAL_FIELDS and v is not None}
    if tc.get("adam") == "fused":  # the default since it came; torch's Adam up to rounding (tested), so
        del tc["adam"]              # rows trained before it keep their key; `--adam torch` is a new row
    if tc["loss"].get("kernels") == "fused":  # the same: the fused loss kernels are torch's up to rounding
        tc["loss"] = {k: v for k, v in tc["loss"].items() if k != "kernels"}
    tc["tsdf"] = {**tc["tsdf"], "device": open3d_device(tc["tsdf"]["device"])}  # one spelling
    if tc["strategy"].get("max_gaussians") == "auto":  # the rule it stands for: a new rule is a new row
        from splat.strategy import AUTO_BUDGET_MIN, AUTO_BUDGET_PER_PIXEL

        tc["strategy"] = {**tc["strategy"], "max_gaussians": f"auto:{AUTO_BUDGET_PER_PIXEL}xpx,min{AUTO_BUDGET_MIN}"}
    for section, is_field, is_off in _ADDED_LATER:  # off: rows run before the option keep their key
        part = tc[section] if section else tc
        if is_off(part):
            part = {k: v for k, v in part.items() if not is_field(k)}
            tc = {**tc, section: part} if section else part
    keys = []
    if tc["tsdf"].get("depth") == "median":  # rows meshed before --tsdf.depth existed fused the median;
        keys.append(config_key(payload | {"train_config": tc | {"tsdf": {k: v for k, v in tc["tsdf"].items()
                                                                          if k != "depth"}}}))
    return keys + [config_key(payload | {"train_config": tc})]  # rows of the days between: depth kept


def training_keys(train_config) -> list[str]:
    """The keys of a TrainConfig alone (no scene, cues or scoring): what two ablations run apart (other
    folders, machines) compare before their rows share a table (evaluation/ablation_report.py
    merge_summaries); a default of `splat train` changed between them changes these."""
    return row_keys({"scene": None, "cues": None, "gt": None, "metrics": None, "train_config": asdict(train_config)})


__all__ = ["OPERATIONAL_FIELDS", "config_key", "row_keys", "training_keys"]
