"""Named `geocues extract` presets, and the dotted-path overrides both CLIs' presets are made of.

``paper`` is the default: the cues of the paper (§4.1). ``room`` adds this project's extensions for a
room with a level floor and ceiling and vertical walls (docs/geocues.md, "Stages"): floor-contact
lines lifted onto the floor, raised into walls as far as the aligned depth priors confirm them, the
ceiling placed at the height the priors give it, grids of plane anchors on ceiling and floor, weak
regions on those two level planes cut onto them, and what no anchored plane took of a region on a
checked wall's plane cut onto that wall.
Train such cues with ``splat train --preset room``.
``mvs`` is the recipe for a scene whose depth priors come from ``geocues mvs`` (photos only, no network;
docs/training.md, "Photos only: the `mvs` recipe"): plane-like points also in the holes of the MVS depth.
Train with ``splat train --preset mvs``. (Until the twenty-fifth session it also lifted floor lines,
``--floor.lines --floor.prior-check``: they cost held-out PSNR on ICL and on a photos-only room.)
"""

from __future__ import annotations

import dataclasses
from typing import Any

EXTRACT_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "room": {"floor.lines": True, "floor.walls": True, "floor.wall_check": True, "floor.wall_front_gap": 0.3,
             "floor.ceiling": True, "floor.floor_grid": True, "floor.level_snap": True, "floor.wall_snap": True},
    "mvs": {"plane.fill_holes": True},
}


def _set(obj: Any, path: list[str], value: Any) -> Any:
    if not dataclasses.is_dataclass(obj) or not hasattr(obj, path[0]):
        raise ValueError(f"preset override: {type(obj).__name__} has no field {path[0]!r}")
    if len(path) == 1:
        return dataclasses.replace(obj, **{path[0]: value})
    return dataclasses.replace(obj, **{path[0]: _set(getattr(obj, path[0]), path[1:], value)})


def apply_overrides(cfg: Any, overrides: dict[str, Any]) -> Any:
    """A copy of the dataclass ``cfg`` with each dotted field path set to its value."""
    for key, value in overrides.items():
        cfg = _set(cfg, key.split("."), value)
    return cfg


def extract_preset_config(name: str) -> Any:
    """The ExtractConfig of preset ``name``."""
    from geocues.extract import ExtractConfig

    if name not in EXTRACT_PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(EXTRACT_PRESETS)}")
    return apply_overrides(ExtractConfig(), EXTRACT_PRESETS[name])
