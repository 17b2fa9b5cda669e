"""A scene's cameras in four numbers, recorded with its cues so that training can tell cues of
another scene: `geocues extract` writes :func:`camera_signature` into CUES/report.json and
`splat train` compares it with its scene's (:func:`signature_mismatch`). A rescaled copy
(`geocues rescale`), a re-posed model or another capture differ in the cameras' spread or centre;
the same cameras under another folder (`geocues sfm -o`, `undistort`, `mvs`) do not."""

from __future__ import annotations

import hashlib

import numpy as np

from geocues.scene import Scene

TOLERANCE = 0.01  # of the cameras' spread: far above float noise, far below a rescale or a re-posing


def camera_signature(scene: Scene) -> dict:
    """{"n", "names" (a digest of the sorted image names), "centroid" [3], "spread"} of the camera centres
    (spread: their RMS distance from the centroid, in the scene's unit)."""
    centres = np.array([c.center for c in scene.cameras], dtype=np.float64).reshape(-1, 3)
    centroid = centres.mean(0) if len(centres) else np.zeros(3)
    spread = float(np.sqrt(((centres - centroid) ** 2).sum(1).mean())) if len(centres) else 0.0
    names = hashlib.sha1("\n".join(sorted(c.name for c in scene.cameras)).encode()).hexdigest()[:16]
    return {"n": len(centres), "names": names, "centroid": [float(v) for v in centroid], "spread": spread}


def signature_mismatch(recorded: dict, current: dict) -> str | None:
    """Why cameras with signature ``recorded`` are not those of ``current`` (a clause), or None when they
    agree within :data:`TOLERANCE` of the spread (image names may differ: a model can drop images)."""
    a, b = float(recorded["spread"]), float(current["spread"])
    if max(a, b) <= 0:
        return None
    if abs(a - b) > TOLERANCE * max(a, b):
        return (f"its cameras spread {a:.4g} units from their centre, this scene's {b:.4g} "
                f"(x{b / a:.3g}{': a rescaled copy?' if a > 0 else ''})")
    shift = float(np.linalg.norm(np.subtract(recorded["centroid"], current["centroid"])))
    if shift > TOLERANCE * max(a, b):
        return f"its cameras' centre lies {shift:.3g} units from this scene's (another frame or capture?)"
    return None
