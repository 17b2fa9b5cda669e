"""Typed Gaussians: initialisation from the geometric cues (IndoorGS §4.2) and 3DGS-format PLY I/O.

Parameters follow the rasterizer's contract (splat/projection.py, gsplat naming):
``means [N, 3]`` metres, ``quats [N, 4]`` (w, x, y, z), ``scales [N, 3]`` log metres,
``opacities [N]`` logits, ``sh0 [N, 1, 3]``, ``shN [N, (d+1)^2 - 1, 3]``. Beside them travels
``cue_type [N]`` (int64, geocues.types.CueType: SFM=0 -> G_M, LINE=1 -> G_L, PLANE=2 -> G_S),
which is not trained and which clones and splits inherit.

Initialisation (3DGS, with the cues' normals): the tangent scale of each Gaussian is the RMS
distance to its ``knn`` nearest cue points; a cue with a known normal (plane-like points, and line
samples where extract gave one) becomes a flat disc whose third axis is that normal and whose
thickness is ``flat_ratio`` times the tangent scale; one without a normal is isotropic. Colours
come from the cue colours as the SH DC term, higher bands start at zero.

The PLY written by :func:`save_ply` has the property layout of the 3DGS reference code (x y z,
nx ny nz, f_dc_*, f_rest_*, opacity, scale_*, rot_*), which common splat viewers open, plus a
``cue_type`` property that they ignore.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from torch import Tensor

from geocues.atomic import atomic_path
from geocues.cue_io import CueCloud, _read_ply_vertices
from splat.sh import SH_C0, num_sh_bases

log = logging.getLogger(__name__)


@dataclass
class InitConfig:
    """How the typed Gaussians are seeded from the cue cloud."""

    knn: int = 3
    """Nearest cue points whose RMS distance sets a Gaussian's tangent scale (3DGS: 3)."""
    flat_ratio: float = 0.1
    """Thickness along a known cue normal, as a fraction of the tangent scale."""
    init_opacity: float = 0.1
    """Initial opacity of every Gaussian (3DGS: 0.1)."""
    max_scale_mult: float = 10.0
    """Upper bound of the tangent scale as a multiple of the median one (isolated cues)."""
    min_scale: float = 1e-4
    """Lower bound of every scale in metres (duplicate cue points have zero neighbour distance)."""


def scene_scale(camera_centers: np.ndarray, points: np.ndarray | None = None) -> float:
    """Scene extent in metres: 3DGS's camera extent (1.1 x the largest distance of a camera centre
    from their mean), but at least half the 90th-percentile distance of ``points`` from their median.

    3DGS's extent suits cameras around an object; indoors the cameras may stand close together in
    the middle of a room (a turn on the spot has extent 0), while learning rates and the prune size
    must follow the room. camera_centers: [C, 3]; points: [N, 3] (the cues) or None.
    """
    c = np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3)
    if len(c) == 0:
        raise ValueError("scene_scale needs at least one camera centre")
    radius = float(np.linalg.norm(c - c.mean(0), axis=1).max()) * 1.1
    if points is not None and len(points):
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        radius = max(radius, 0.5 * float(np.percentile(np.linalg.norm(p - np.median(p, 0), axis=1), 90)))
    return radius if radius > 1e-6 else 1.0


def tangent_scales(xyz: np.ndarray, knn: int) -> np.ndarray:
    """[N] RMS distance of each point to its ``knn`` nearest other points (3DGS init scale)."""
    n = len(xyz)
    if n < 2:
        return np.ones(n)
    k = min(knn, n - 1)
    dist, _ = cKDTree(xyz).query(xyz, k=k + 1)
    return np.sqrt((dist[:, 1:] ** 2).mean(1))


def frames_from_normals(normals: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz quaternions of rotations whose third column is the unit normal [N, 3]."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    xyzw = Rotation.from_matrix(np.stack([t1, t2, n], 2)).as_quat()
    return xyzw[:, [3, 0, 1, 2]]  # scipy xyzw -> project wxyz


def init_from_cues(cues: CueCloud, sh_degree: int, cfg: InitConfig = InitConfig()
                   ) -> tuple[dict[str, Tensor], Tensor]:
    """Gaussians seeded from every cue point (IndoorGS §4.2: G_L, G_M, G_S from the three cue types).

    cues: the cue cloud (geocues extract's cues.ply); sh_degree: 0..3.
    Returns (params as float32 tensors on the CPU, cue_type [N] int64).
    """
    if len(cues) == 0:
        raise ValueError("the cue cloud is empty: no Gaussians to initialise (run geocues extract, "
                         "or check its report.json for why every cue was rejected)")
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
    if not np.all(np.isfinite(cues.xyz)):
        raise ValueError("the cue cloud holds non-finite positions")
    n = len(cues)
    s = tangent_scales(cues.xyz, cfg.knn)
    s = s.clip(cfg.min_scale, max(cfg.min_scale, cfg.max_scale_mult * float(np.median(s))))
    scales = np.repeat(s[:, None], 3, axis=1)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    has_normal = np.linalg.norm(cues.normal, axis=1) > 0.5
    if has_normal.any():
        quats[has_normal] = frames_from_normals(cues.normal[has_normal].astype(np.float64))
        scales[has_normal, 2] = np.maximum(cfg.flat_ratio * s[has_normal], cfg.min_scale)
    p = cfg.init_opacity
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    params = {
        "means": f32(cues.xyz),
        "quats": f32(quats),
        "scales": f32(np.log(scales)),
        "opacities": torch.full((n,), math.log(p / (1 - p))),
        "sh0": f32((cues.rgb.astype(np.float32) / 255.0 - 0.5) / SH_C0)[:, None, :],
        "shN": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3),
    }
    cue_type = torch.as_tensor(cues.cue_type.astype(np.int64))
    log.info("initialised %d Gaussians (%s), %d flat along a cue normal", n, cues.counts(), int(has_normal.sum()))
    return params, cue_type


# ----------------------------------------------------------------------------------------------
# 3DGS-format PLY

def _ply_fields(n_rest: int) -> list[str]:
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def save_ply(path: str | Path, params: dict[str, Tensor], cue_type: Tensor | None = None) -> Path:
    """Write the Gaussians as a binary 3DGS PLY (viewers open it), plus ``cue_type``. Atomic."""
    path = Path(path)
    p = {k: v.detach().cpu().float().numpy() for k, v in params.items()}
    n, n_rest = len(p["means"]), p["shN"].shape[1]
    # 3DGS stores the rest coefficients channel-major: f_rest_{c * K + k}
    rest = p["shN"].transpose(0, 2, 1).reshape(n, 3 * n_rest)
    cols = [p["means"], np.zeros((n, 3), np.float32), p["sh0"].reshape(n, 3), rest,
            p["opacities"].reshape(n, 1), p["scales"], p["quats"]]
    data = np.concatenate(cols, axis=1).astype("<f4")
    names = _ply_fields(n_rest)
    dtype = [(name, "<f4") for name in names]
    if cue_type is not None:
        dtype.append(("cue_type", "u1"))
    rec = np.empty(n, dtype=dtype)
    for i, name in enumerate(names):
        rec[name] = data[:, i]
    if cue_type is not None:
        rec["cue_type"] = cue_type.detach().cpu().numpy().astype(np.uint8)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names]
    if cue_type is not None:
        header.append("property uchar cue_type")
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(rec.tobytes())
    return path


def load_ply(path: str | Path) -> tuple[dict[str, Tensor], Tensor | None]:
    """Read a 3DGS PLY (from :func:`save_ply` or the 3DGS reference code): (params, cue_type or None)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no Gaussian PLY at {path}")
    v = _read_ply_vertices(path)
    names = v.dtype.names or ()
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    if n_rest % 3 or any(name not in names for name in _ply_fields(n_rest // 3)):
        raise ValueError(f"{path} is not a 3DGS Gaussian PLY (properties: {list(names)})")
    k = n_rest // 3
    col = lambda *keys: np.stack([np.asarray(v[key], np.float32) for key in keys], 1)  # noqa: E731
    n = len(v)
    params = {
        "means": torch.from_numpy(col("x", "y", "z")),
        "quats": torch.from_numpy(col("rot_0", "rot_1", "rot_2", "rot_3")),
        "scales": torch.from_numpy(col("scale_0", "scale_1", "scale_2")),
        "opacities": torch.from_numpy(np.asarray(v["opacity"], np.float32).copy()),
        "sh0": torch.from_numpy(col("f_dc_0", "f_dc_1", "f_dc_2")).reshape(n, 1, 3),
        "shN": torch.from_numpy(col(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k)
                                .transpose(0, 2, 1).copy()) if k else torch.zeros(n, 0, 3),
    }
    cue_type = torch.from_numpy(np.asarray(v["cue_type"], np.int64)) if "cue_type" in names else None
    return params, cue_type
