"""Types shared by every stage: the cue / Gaussian type labels."""

from __future__ import annotations

from enum import IntEnum


class CueType(IntEnum):
    """Where a cue point (and the Gaussian it seeds) comes from. Clones and splits inherit it."""

    SFM = 0  # structure-from-motion point, SOR-filtered (G_M in the paper)
    LINE = 1  # sample on a triangulated 3D line segment (G_L)
    PLANE = 2  # plane-like point of a weak-texture region (G_S)
