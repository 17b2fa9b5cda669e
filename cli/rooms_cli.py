"""`evaluate make-room`: thin front end of evaluation.rooms (parses, then calls make_room)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import tyro

from evaluation.rooms.writer import RoomConfig


def make_room(out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")],
              cfg: Annotated[RoomConfig, tyro.conf.arg(name="")] = RoomConfig(),
              overwrite: bool = False) -> int:
    """Render a procedural benchmark room (images, poses, SfM points, GT mesh/depth/normals, simulated priors).

    Args:
        out: Scene folder to create (built in a temporary sibling, then renamed into place).
        cfg: Room, rendering, trajectory and prior options.
        overwrite: Replace OUT if it exists.
    """
    from evaluation.rooms.writer import make_room as _make_room

    path = _make_room(out, cfg, overwrite=overwrite)
    print(f"wrote {path}")
    return 0
