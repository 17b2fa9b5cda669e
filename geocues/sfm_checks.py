"""`geocues sfm`'s option checks and advice (pycolmap's own checks name no option: 'Check failed:
ExistsCameraModelWithName(...)'), and the flags that repeat a run's options in a hint."""

from __future__ import annotations

from dataclasses import asdict, fields
from typing import TYPE_CHECKING

from geocues import sfm_steps as U

if TYPE_CHECKING:  # pragma: no cover
    from geocues.sfm import SfmConfig


def check_sfm_options(cfg: "SfmConfig") -> None:
    """Raise ValueError naming the first option of ``cfg`` out of range."""
    import pycolmap

    from geocues.extract_checks import check_finite

    if cfg.mode not in ("auto", "triangulate", "map"):
        raise ValueError(f"--mode must be auto, triangulate or map, got {cfg.mode!r}")
    if cfg.verification not in ("poses", "ransac"):
        raise ValueError(f"--verification must be poses or ransac, got {cfg.verification!r}")
    check_finite(cfg)
    models = [m for m in pycolmap.CameraModelId.__members__ if m != "INVALID"]
    if cfg.camera_model not in models:
        near = " (camera model names are upper case)" if cfg.camera_model.upper() in models else ""
        raise ValueError(f"--camera-model {cfg.camera_model!r} is no COLMAP camera model{near}; one of "
                         + ", ".join(models))
    for name, least in (("max_num_features", 1), ("num_neighbors", 1), ("pair_stride", 1),
                        ("exhaustive_below", 0), ("sequential_overlap", 1), ("min_num_inliers", 1),
                        ("min_track_length", 2), ("max_image_size", 0)):
        if getattr(cfg, name) < least:
            raise ValueError(f"--{name.replace('_', '-')} must be >= {least}, got {getattr(cfg, name)}")
    for name in ("num_threads", "mapper_threads"):
        if getattr(cfg, name) == 0 or getattr(cfg, name) < -1:
            raise ValueError(f"--{name.replace('_', '-')} must be -1 (all cores) or >= 1, got {getattr(cfg, name)}")
    for name, hi in (("peak_threshold", None), ("max_ratio", 1.0), ("max_epipolar_error", None),
                     ("max_reproj_error", None), ("max_pair_angle", 180.0)):
        v = getattr(cfg, name)
        if not v > 0 or (hi is not None and v > hi):
            raise ValueError(f"--{name.replace('_', '-')} must be in (0, {hi if hi is not None else 'inf'}"
                             f"{']' if hi is not None else ')'}, got {v}")
    if not 0 <= cfg.min_tri_angle < 90:
        raise ValueError(f"--min-tri-angle must be in [0, 90) degrees, got {cfg.min_tri_angle}")


def command_flags(cfg: "SfmConfig") -> list[str]:
    """The command-line flags of ``cfg``'s options that differ from the defaults (for a hint that
    repeats the command: another option is another cache key, and the features are extracted again)."""
    default = asdict(type(cfg)())
    flags = []
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if value == default[f.name]:
            continue
        name = f.name.replace("_", "-")
        flags.append(f"--{name}" if value is True else f"--no-{name}" if value is False else f"--{name} {value}")
    return flags


FEW_POINTS = 100  # the cues start from the SfM points: fewer leaves most of a room without a cue


def few_points_advice(n_points: int, n_images: int, n_short: int, cfg: "SfmConfig") -> str:
    """What to do when triangulation left (almost) no points."""
    return (f"sfm: only {n_points} points from {n_images} images ({n_short} seen in fewer than "
            f"--min-track-length {cfg.min_track_length} images were dropped): the cues start from these points. "
            + more_points_advice(cfg))


def more_points_advice(cfg: "SfmConfig") -> str:
    """The options and photos that give more points."""
    two_view = cfg.ignore_two_view_tracks or cfg.min_track_length > 2
    return (("With few images, `--min-track-length 2 --no-ignore-two-view-tracks` keeps points seen in two; "
             if two_view else "")
            + "a room wants dozens of overlapping photos, each wall seen from several places" + U.camera_model_note(cfg))
