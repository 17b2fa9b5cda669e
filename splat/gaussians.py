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

The PLY written by :func:`save_ply` is exactly the 3DGS reference layout: one ``vertex`` element of
62 float32 properties (x y z, nx ny nz, f_dc_0..2, f_rest_0..44, opacity, scale_0..2, rot_0..3), a
fixed 248-byte stride that SIBR and every other 3DGS reader take; ``shN`` is zero-padded to SH
degree 3 on disk. The cue type goes into a sidecar ``.npy`` beside it (:func:`cue_type_path`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from torch import Tensor

from geocues.atomic import atomic_path
from geocues.types import CueType
from geocues.cue_io import CueCloud
from splat.sh import SH_C0, num_sh_bases, sh_degree_of

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
    fill_holes: bool = False
    """Also seed SFM-typed Gaussians where the cue Gaussians leave a training view open, at the
    view's L_a anchor depth (splat/hole_seeds.py; an extension: views without an anchor add none)."""
    hole_alpha: float = 0.5
    """A pixel is open where the initial Gaussians' alpha is below this."""
    hole_stride: int = 4
    """Open pixels are sampled every this many pixels (training resolution) in each direction."""
    hole_voxel: float = 0.1
    """Seed points of all views are averaged per voxel of this edge (m)."""
    plane_share: float = 0.0
    """With a budget (--strategy.max-gaussians): thin the PLANE seeds (at random, --seed) so the initial
    Gaussians take at most this share of it, leaving the rest to densification (an extension; 0 = off:
    a cue cloud over the budget then leaves no room to grow)."""


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
# 3DGS-format PLY (the reference layout) and its cue-type sidecar

PLY_REST = 15  # rest SH coefficients per channel on disk: degree 3, (3 + 1)^2 - 1
PLY_FIELDS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
              + [f"f_rest_{i}" for i in range(3 * PLY_REST)]
              + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]


def cue_type_path(ply_path: str | Path) -> Path:
    """The cue-type sidecar of a Gaussian PLY, in the same folder: ``point_cloud.ply`` ->
    ``cue_type.npy``; any other ``NAME.ply`` -> ``NAME.cue_type.npy``."""
    ply_path = Path(ply_path)
    name = "cue_type.npy" if ply_path.name == "point_cloud.ply" else f"{ply_path.stem}.cue_type.npy"
    return ply_path.with_name(name)


def save_ply(path: str | Path, params: dict[str, Tensor], cue_type: Tensor | None = None) -> Path:
    """Write the Gaussians as a binary little-endian PLY in exactly the 3DGS reference layout
    (:data:`PLY_FIELDS`, 62 float32 = 248 bytes per Gaussian; normals zero; ``shN`` zero-padded to
    15 rows, stored channel-major ``f_rest_{c * 15 + k}`` like the reference), and ``cue_type`` [N]
    as uint8 into the sidecar :func:`cue_type_path` (a stale sidecar is removed when ``cue_type`` is
    None). Both atomic. Raises ValueError, naming ``path``, on bad shapes or non-finite values."""
    path = Path(path)
    keys = ("means", "quats", "scales", "opacities", "sh0", "shN")
    if any(k not in params for k in keys):
        raise ValueError(f"cannot write {path}: params lack {[k for k in keys if k not in params]}")
    p = {k: params[k].detach().cpu().float().numpy() for k in keys}
    n = len(p["means"])
    expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,), "sh0": (n, 1, 3)}
    p["opacities"] = p["opacities"].reshape(-1)
    for key, shape in expected.items():
        if p[key].shape != shape:
            raise ValueError(f"cannot write {path}: params['{key}'] has shape {p[key].shape}, expected {shape}")
    shn = p["shN"]
    if shn.ndim != 3 or shn.shape[0] != n or shn.shape[2] != 3 or shn.shape[1] > PLY_REST:
        raise ValueError(f"cannot write {path}: params['shN'] has shape {shn.shape}, expected ({n}, K <= 15, 3)")
    for key, a in p.items():
        if not np.isfinite(a).all():
            raise ValueError(f"refusing to write {path}: params['{key}'] holds "
                             f"{int((~np.isfinite(a)).sum())} non-finite values")
    rest = np.zeros((n, PLY_REST, 3), np.float32)
    rest[:, : shn.shape[1]] = shn
    rest = rest.transpose(0, 2, 1).reshape(n, 3 * PLY_REST)  # channel-major, as the reference
    data = np.concatenate([p["means"], np.zeros((n, 3), np.float32), p["sh0"].reshape(n, 3), rest,
                           p["opacities"][:, None], p["scales"], p["quats"]], axis=1)
    assert data.shape == (n, len(PLY_FIELDS)), data.shape
    rec = np.ascontiguousarray(data, dtype="<f4").view([(name, "<f4") for name in PLY_FIELDS]).reshape(n)
    types = None
    if cue_type is not None:
        types = cue_type.detach().cpu().numpy().reshape(-1)
        if len(types) != n:
            raise ValueError(f"cannot write {path}: cue_type has {len(types)} entries for {n} Gaussians")
        unknown = sorted(set(np.unique(types).tolist()) - {int(t) for t in CueType})
        if unknown:
            raise ValueError(f"cannot write {path}: unknown cue_type values {unknown}")
        types = types.astype(np.uint8)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(str(tmp))
    side = cue_type_path(path)
    if types is None:
        side.unlink(missing_ok=True)
    else:
        with atomic_path(side) as tmp, open(tmp, "wb") as f:  # a file object: np.save keeps the name
            np.save(f, types)
    return path


def load_ply(path: str | Path, sh_degree: int | None = None) -> tuple[dict[str, Tensor], Tensor | None]:
    """Read a Gaussian PLY: this project's (cue type from the sidecar :func:`cue_type_path`, or from
    a ``cue_type`` property in older files), the 3DGS reference layout, or gsplat's export (no
    normals, 0..45 ``f_rest``, channel-major). Returns (params, cue_type [N] int64 or None).

    ``shN`` keeps the rows the file has (15 for a padded file) unless ``sh_degree`` is given: then it
    has exactly (sh_degree + 1)^2 - 1 rows, trailing bands trimmed (they must be all zero) or padded
    with zeros. The renderer takes the degree from ``shN`` unless told one, and zero bands add nothing.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no Gaussian PLY at {path}")
    if sh_degree is not None and not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises several types for malformed files
        what = "is truncated or damaged" if "end-of-file" in str(e) else "is not a readable PLY file"
        raise ValueError(f"{path} {what}: {e}") from e
    if "vertex" not in [el.name for el in ply.elements]:
        raise ValueError(f"{path} has no 'vertex' element (elements: {[el.name for el in ply.elements]})")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    missing = [name for name in _REQUIRED if name not in names]
    if missing:
        raise ValueError(f"{path} is not a 3DGS Gaussian PLY: no {missing} (properties: {list(names)})")
    rest_names = [name for name in names if name.startswith("f_rest_")]
    m = len(rest_names)
    if m % 3 or sorted(rest_names) != sorted(f"f_rest_{i}" for i in range(m)):
        raise ValueError(f"{path}: {m} f_rest properties, expected f_rest_0..f_rest_(3K-1)")
    k = m // 3
    if k not in (0, 3, 8, 15):
        raise ValueError(f"{path}: {m} f_rest properties is no SH degree in 0..3 (0, 9, 24 or 45)")
    n = len(v)
    col = lambda *keys: np.stack([np.asarray(v[key], np.float32) for key in keys], 1)  # noqa: E731
    shn = (col(*[f"f_rest_{i}" for i in range(m)]).reshape(n, 3, k).transpose(0, 2, 1) if k
           else np.zeros((n, 0, 3), np.float32))  # channel-major on disk -> [N, K, 3]
    if sh_degree is not None:
        rows = num_sh_bases(sh_degree) - 1
        if rows < k and np.any(shn[:, rows:]):
            raise ValueError(f"{path} holds non-zero SH coefficients above degree {sh_degree}; "
                             f"load it with sh_degree=None or {sh_degree_of(shn)}")
        shn = np.concatenate([shn[:, :rows], np.zeros((n, max(0, rows - k), 3), np.float32)], 1)
    params = {
        "means": torch.from_numpy(col("x", "y", "z")),
        "quats": torch.from_numpy(col("rot_0", "rot_1", "rot_2", "rot_3")),
        "scales": torch.from_numpy(col("scale_0", "scale_1", "scale_2")),
        "opacities": torch.from_numpy(np.asarray(v["opacity"], np.float32).copy()),
        "sh0": torch.from_numpy(col("f_dc_0", "f_dc_1", "f_dc_2")).reshape(n, 1, 3),
        "shN": torch.from_numpy(np.ascontiguousarray(shn)),
    }
    bad = {k: int((~torch.isfinite(t)).reshape(n, -1).any(1).sum()) for k, t in params.items() if n}
    if any(bad.values()):
        raise ValueError(f"{path} holds non-finite values (Gaussians per parameter: "
                         + ", ".join(f"{k} {c}" for k, c in bad.items() if c) + ")")
    side = cue_type_path(path)
    if side.is_file():
        types, source = np.load(side), side
    elif "cue_type" in names:
        types, source = np.asarray(v["cue_type"]), path
    else:
        return params, None
    types = types.reshape(-1).astype(np.int64)
    if len(types) != n:
        raise ValueError(f"{source} holds {len(types)} cue types for the {n} Gaussians of {path}")
    unknown = sorted(set(np.unique(types).tolist()) - {int(t) for t in CueType})
    if unknown:
        raise ValueError(f"{source}: unknown cue_type values {unknown}")
    return params, torch.from_numpy(types)

