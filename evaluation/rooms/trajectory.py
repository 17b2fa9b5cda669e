"""A hand-held capture path through a room: a smooth closed loop with smooth gaze and jitter.

The camera walks a wobbly ellipse inset from the walls at eye height and looks across the room
(towards the far side, with a slow yaw sweep of +-`yaw_sweep` degrees), pitched down at the floor
and furniture by a smoothly varying angle, with a slight roll. On top of the smooth motion each
frame gets small Gaussian jitter in position and angles, like a hand-held phone. All smooth terms
are sums of sinusoids of the loop angle with integer frequencies, so the loop closes smoothly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class TrajectoryConfig:
    """Hand-held loop parameters."""

    inset: float = 1.0
    """Distance (m) of the walking loop from the walls (shrinks the loop if furniture is in the way)."""
    height_min: float = 1.4
    """Lowest camera height (m)."""
    height_max: float = 1.7
    """Highest camera height (m)."""
    yaw_sweep: float = 40.0
    """Amplitude (degrees) of the slow left-right gaze sweep around the look-across direction."""
    pitch_mean: float = -15.0
    """Mean pitch (degrees, negative = looking down)."""
    pitch_sweep: float = 12.0
    """Amplitude (degrees) of the slow up-down gaze variation."""
    roll_sweep: float = 2.0
    """Amplitude (degrees) of the slow roll."""
    jitter_pos: float = 0.01
    """Per-frame position jitter (m, standard deviation)."""
    jitter_angle: float = 0.7
    """Per-frame yaw/pitch/roll jitter (degrees, standard deviation)."""
    clearance: float = 0.25
    """Smallest distance (m) from a camera centre to a wall or a piece of furniture."""


def _smooth(rng: np.random.Generator, theta: np.ndarray, freqs=(1, 2, 3)) -> np.ndarray:
    """Random smooth periodic function of theta in about [-1, 1]: sum of sinusoids."""
    amps = rng.uniform(0.3, 1.0, len(freqs))
    phases = rng.uniform(0, 2 * np.pi, len(freqs))
    f = sum(a * np.sin(k * theta + p) for a, k, p in zip(amps, freqs, phases))
    return f / amps.sum()


def look_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """World-to-camera rotation (OpenCV axes, world z up) looking along yaw/pitch (radians) with
    roll about the optical axis, [3, 3] with rows right, down, forward."""
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    c, s = np.cos(roll), np.sin(roll)
    return np.stack([c * right + s * down, -s * right + c * down, f])


def _clear(p: np.ndarray, size, boxes, clearance: float) -> bool:
    W, D, H = size
    if min(p[0], W - p[0], p[1], D - p[1], H - p[2]) < clearance:
        return False
    for lo, hi in boxes:
        d = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        if np.linalg.norm(d) < clearance:
            return False
    return True


def make_trajectory(size: tuple[float, float, float], boxes: list, n_views: int,
                    rng: np.random.Generator, cfg: TrajectoryConfig = TrajectoryConfig()
                    ) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n_views`` world-to-camera poses (R [3, 3], t [3]) along a loop in a room of ``size``
    (W, D, H) avoiding the axis-aligned ``boxes`` [(lo [3], hi [3])]."""
    if n_views < 2:
        raise ValueError(f"n_views must be >= 2, got {n_views}")
    if not cfg.height_min <= cfg.height_max:
        raise ValueError(f"height_min {cfg.height_min} > height_max {cfg.height_max}")
    W, D, H = size
    theta0, direction = rng.uniform(0, 2 * np.pi), rng.choice([-1.0, 1.0])
    theta = theta0 + direction * 2 * np.pi * np.arange(n_views) / n_views
    wobble = 0.12 * _smooth(rng, theta, (2, 3))
    height = 0.5 * (cfg.height_min + cfg.height_max) + 0.5 * (cfg.height_max - cfg.height_min) * \
        _smooth(rng, theta, (1, 2))
    yaw_off = np.radians(cfg.yaw_sweep) * _smooth(rng, theta, (2, 3, 5))
    pitch = np.radians(cfg.pitch_mean + cfg.pitch_sweep * _smooth(rng, theta, (1, 3, 4)))
    roll = np.radians(cfg.roll_sweep) * _smooth(rng, theta, (1, 2))
    jit_p = rng.normal(0.0, cfg.jitter_pos, (n_views, 3))
    jit_a = np.radians(rng.normal(0.0, cfg.jitter_angle, (n_views, 3)))

    inset = cfg.inset
    for _ in range(20):
        a, b = max(W / 2 - inset, 0.2), max(D / 2 - inset, 0.2)
        r = 1.0 + wobble
        centres = np.stack([W / 2 + a * r * np.cos(theta), D / 2 + b * r * np.sin(theta), height], 1)
        centres = centres + jit_p
        centres[:, 2] = np.clip(centres[:, 2], cfg.height_min, cfg.height_max)
        if all(_clear(c, size, boxes, cfg.clearance) for c in centres):
            break
        inset += 0.1
    else:
        raise ValueError(f"no clear camera loop in a {W:.2f} x {D:.2f} m room (inset up to {inset:.2f} m)")
    if inset != cfg.inset:
        log.info("trajectory: loop inset grown from %.2f to %.2f m to clear the furniture", cfg.inset, inset)

    poses = []
    for k in range(n_views):
        c = centres[k]
        across = np.arctan2(D / 2 - c[1], W / 2 - c[0])  # look across the room, through its middle
        R = look_rotation(across + yaw_off[k] + jit_a[k, 0], pitch[k] + jit_a[k, 1],
                          roll[k] + jit_a[k, 2])
        poses.append((R, -R @ c))
    return poses
