"""Cue files: the typed cue point cloud (``cues.ply``) and the 3D line segments (``lines3d.npz``).

Cue PLY (docs/conventions.md): binary little-endian with ``x y z`` (float), ``red green blue``
(uchar), ``nx ny nz`` (float, zero where unknown), ``cue_type`` (uchar, ``CueType``) and
``confidence`` (float in [0, 1]). Standard viewers (Open3D, MeshLab, CloudCompare) open it;
Open3D's tensor reader exposes ``cue_type`` and ``confidence`` as extra point attributes.
The writer is plain numpy; the reader parses the header itself and accepts binary little/big-endian
and ASCII files with extra properties.

Two files only for looking at the cues (MeshLab, CloudCompare, Open3D), written with plyfile:
``lines3d.ply`` (the 3D segments as a ``vertex`` element x y z and an ``edge`` element
vertex1 vertex2 with the line's red green blue; ``o3d.io.read_line_set`` opens it) and
``cues_by_type.ply`` (the cue points coloured by type, :data:`CUE_TYPE_COLORS`).

``lines3d.npz`` holds ``segments`` [L, 2, 3] (metres), ``n_views`` [L], the supporting camera
indices as a ragged array (``view_ids`` concatenated, ``view_offsets`` [L + 1]), ``colors`` [L, 3]
uint8, and the line samples ``points`` [P, 3], ``point_colors`` [P, 3] uint8, ``point_line`` [P].
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geocues.atomic import atomic_path
from geocues.types import CueType

log = logging.getLogger(__name__)

# PLY property type names -> numpy type codes (both the C-style and the sized spellings).
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4",
              "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}

_CUE_FIELDS = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
               ("nx", "f4"), ("ny", "f4"), ("nz", "f4"), ("cue_type", "u1"), ("confidence", "f4")]
_NP_TO_PLY = {"f4": "float", "f8": "double", "u1": "uchar", "i1": "char", "u2": "ushort",
              "i2": "short", "u4": "uint", "i4": "int"}

# cues_by_type.ply colours (Tableau blue, red, green): SfM points, line samples, plane-like points.
CUE_TYPE_COLORS = {CueType.SFM: (31, 119, 180), CueType.LINE: (214, 39, 40), CueType.PLANE: (44, 160, 44)}




@dataclass
class CueCloud:
    """Typed cue points, the content of ``cues.ply``."""

    xyz: np.ndarray  # [N, 3] float64 metres
    rgb: np.ndarray  # [N, 3] uint8
    normal: np.ndarray  # [N, 3] float32 unit, zeros where unknown
    cue_type: np.ndarray  # [N] uint8 CueType
    confidence: np.ndarray  # [N] float32 in [0, 1]

    def __post_init__(self) -> None:
        n = len(self.xyz)
        self.xyz = np.asarray(self.xyz, np.float64).reshape(n, 3)
        self.rgb = np.asarray(self.rgb, np.uint8).reshape(n, 3)
        self.normal = np.asarray(self.normal, np.float32).reshape(n, 3)
        self.cue_type = np.asarray(self.cue_type, np.uint8).reshape(n)
        self.confidence = np.asarray(self.confidence, np.float32).reshape(n)

    def __len__(self) -> int:
        return len(self.xyz)

    @staticmethod
    def empty() -> "CueCloud":
        return CueCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.float32),
                        np.zeros(0, np.uint8), np.zeros(0, np.float32))

    @staticmethod
    def make(xyz: np.ndarray, rgb: np.ndarray, cue_type: CueType | int,
             normal: np.ndarray | None = None, confidence: np.ndarray | float = 1.0) -> "CueCloud":
        """Build a cloud of one cue type; ``rgb`` may be uint8 or float in [0, 1]."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        n = len(xyz)
        rgb = np.asarray(rgb)
        if rgb.shape != (n, 3):
            raise ValueError(f"rgb has shape {rgb.shape}, expected ({n}, 3)")
        if rgb.dtype != np.uint8:
            rgb = np.clip(np.round(rgb.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
        nrm = np.zeros((n, 3), np.float32) if normal is None else np.asarray(normal, np.float32)
        if nrm.shape != (n, 3):
            raise ValueError(f"normal has shape {nrm.shape}, expected ({n}, 3)")
        conf = np.broadcast_to(np.asarray(confidence, np.float32), (n,)).copy()
        return CueCloud(xyz, rgb, nrm, np.full(n, int(cue_type), np.uint8), conf)

    @staticmethod
    def concat(clouds: list["CueCloud"]) -> "CueCloud":
        clouds = [c for c in clouds if c is not None]
        if not clouds:
            return CueCloud.empty()
        return CueCloud(*(np.concatenate([getattr(c, f) for c in clouds])
                          for f in ("xyz", "rgb", "normal", "cue_type", "confidence")))

    def select(self, mask: np.ndarray) -> "CueCloud":
        return CueCloud(self.xyz[mask], self.rgb[mask], self.normal[mask], self.cue_type[mask],
                        self.confidence[mask])

    def of_type(self, cue_type: CueType | int) -> "CueCloud":
        return self.select(self.cue_type == int(cue_type))

    def counts(self) -> dict[str, int]:
        """Points per cue type name, e.g. {"SFM": 120, "LINE": 3400, "PLANE": 9000}."""
        return {t.name: int(np.sum(self.cue_type == t.value)) for t in CueType}


def write_cues_ply(path: str | Path, cloud: CueCloud) -> Path:
    """Write ``cloud`` as a binary little-endian cue PLY, atomically. Returns ``path``."""
    path = Path(path)
    if not np.all(np.isfinite(cloud.xyz)):
        raise ValueError(f"refusing to write non-finite cue positions to {path}")
    rec = np.empty(len(cloud), dtype=[(name, "<" + t) for name, t in _CUE_FIELDS])
    rec["x"], rec["y"], rec["z"] = cloud.xyz.T.astype(np.float32)
    rec["red"], rec["green"], rec["blue"] = cloud.rgb.T
    rec["nx"], rec["ny"], rec["nz"] = cloud.normal.T
    rec["cue_type"], rec["confidence"] = cloud.cue_type, cloud.confidence
    header = ["ply", "format binary_little_endian 1.0",
              "comment indoorgs cue cloud: cue_type SFM=0 LINE=1 PLANE=2",
              f"element vertex {len(cloud)}"]
    header += [f"property {_NP_TO_PLY[t]} {name}" for name, t in _CUE_FIELDS]
    header += ["end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(rec.tobytes())
    return path


def _read_ply_vertices(path: Path) -> np.ndarray:
    """Vertex element of a PLY file as a numpy structured array (no list properties allowed)."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path} is not a PLY file (no 'ply' magic line)")
        fmt, elements, current = None, [], None
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no end_header")
            tok = line.decode("ascii", errors="replace").split()
            if not tok or tok[0] in ("comment", "obj_info"):
                continue
            if tok[0] == "end_header":
                break
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                current = [tok[1], int(tok[2]), []]
                elements.append(current)
            elif tok[0] == "property":
                if current is None or tok[1] == "list":
                    if current is not None and current[0] == "vertex":
                        raise ValueError(f"{path}: list property {tok[-1]} in vertex element")
                    if current is not None:
                        current[2].append((tok[-1], None))
                    continue
                if tok[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY property type {tok[1]}")
                current[2].append((tok[2], _PLY_TYPES[tok[1]]))
        if not elements or elements[0][0] != "vertex":
            raise ValueError(f"{path}: the first PLY element must be 'vertex'")
        _, n, props = elements[0]
        if fmt == "ascii":
            dtype = np.dtype([(name, t) for name, t in props])
            rows = np.loadtxt(f, max_rows=n, ndmin=2) if n else np.zeros((0, len(props)))
            out = np.empty(n, dtype)
            for k, (name, _) in enumerate(props):
                out[name] = rows[:, k]
            return out
        endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
        if endian is None:
            raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
        dtype = np.dtype([(name, endian + t) for name, t in props])
        data = f.read(dtype.itemsize * n)
        if len(data) != dtype.itemsize * n:
            raise ValueError(f"{path}: truncated PLY ({len(data)} of {dtype.itemsize * n} bytes)")
        return np.frombuffer(data, dtype=dtype, count=n)


def read_cues_ply(path: str | Path) -> CueCloud:
    """Read a cue PLY (or any point PLY: missing colour/normal/type/confidence get defaults:
    grey, zeros, SFM, 1.0)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no cue PLY at {path}")
    v = _read_ply_vertices(path)
    names = v.dtype.names or ()
    for axis in "xyz":
        if axis not in names:
            raise ValueError(f"{path}: vertex element has no '{axis}' property (has {names})")
    n = len(v)

    def cols(keys: tuple[str, ...], default: float, dtype) -> np.ndarray:
        if all(k in names for k in keys):
            return np.stack([np.asarray(v[k]) for k in keys], axis=-1).astype(dtype)
        return np.full((n, len(keys)), default, dtype)

    cue_type = cols(("cue_type",), int(CueType.SFM), np.uint8)[:, 0]
    unknown = sorted(set(np.unique(cue_type).tolist()) - {int(t) for t in CueType})
    if unknown:
        raise ValueError(f"{path}: unknown cue_type values {unknown} in {int(np.isin(cue_type, unknown).sum())} "
                         f"points (known: {', '.join(f'{t.name}={int(t)}' for t in CueType)})")
    xyz = cols(("x", "y", "z"), 0.0, np.float64)
    if not np.isfinite(xyz).all():
        raise ValueError(f"{path}: {int((~np.isfinite(xyz).all(1)).sum())} points have non-finite coordinates")
    return CueCloud(xyz, cols(("red", "green", "blue"), 128, np.uint8), cols(("nx", "ny", "nz"), 0.0, np.float32),
                    cue_type, cols(("confidence",), 1.0, np.float32)[:, 0])


def _write_ply_elements(path: Path, elements: list) -> Path:
    from plyfile import PlyData

    with atomic_path(path) as tmp:
        PlyData(elements, text=False, byte_order="<").write(str(tmp))
    return path


def write_lines_ply(path: str | Path, segments: np.ndarray, colors: np.ndarray | None = None) -> Path:
    """Write 3D segments [L, 2, 3] (metres) as a line-set PLY, atomically: ``vertex`` (x y z float,
    2L points, segment l = vertices 2l and 2l+1) and ``edge`` (vertex1 vertex2 int, plus red green
    blue uchar when ``colors`` [L, 3] uint8 or float in [0, 1] is given). Returns ``path``."""
    from plyfile import PlyElement

    path = Path(path)
    segments = np.asarray(segments, np.float64).reshape(-1, 2, 3)
    L = len(segments)
    if not np.isfinite(segments).all():
        raise ValueError(f"refusing to write non-finite line segments to {path}")
    vert = np.empty(2 * L, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    vert["x"], vert["y"], vert["z"] = segments.reshape(-1, 3).T.astype(np.float32)
    fields = [("vertex1", "<i4"), ("vertex2", "<i4")]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (L, 3):
            raise ValueError(f"line colours have shape {colors.shape}, expected ({L}, 3)")
        if colors.dtype != np.uint8:
            colors = np.clip(np.round(colors.astype(np.float64) * 255), 0, 255).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    edge = np.empty(L, dtype=fields)
    edge["vertex1"], edge["vertex2"] = np.arange(0, 2 * L, 2), np.arange(1, 2 * L, 2)
    if colors is not None:
        edge["red"], edge["green"], edge["blue"] = colors.T
    return _write_ply_elements(path, [PlyElement.describe(vert, "vertex"), PlyElement.describe(edge, "edge")])


def write_cues_by_type_ply(path: str | Path, cloud: CueCloud) -> Path:
    """Write the cue points coloured by type (:data:`CUE_TYPE_COLORS`) as x y z float, red green blue
    uchar and ``cue_type`` uchar, atomically. Returns ``path``."""
    from plyfile import PlyElement

    path = Path(path)
    if not np.all(np.isfinite(cloud.xyz)):
        raise ValueError(f"refusing to write non-finite cue positions to {path}")
    palette = np.zeros((256, 3), np.uint8)
    for t, rgb in CUE_TYPE_COLORS.items():
        palette[int(t)] = rgb
    rec = np.empty(len(cloud), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                                      ("green", "u1"), ("blue", "u1"), ("cue_type", "u1")])
    rec["x"], rec["y"], rec["z"] = cloud.xyz.T.astype(np.float32)
    rec["red"], rec["green"], rec["blue"] = palette[cloud.cue_type].T
    rec["cue_type"] = cloud.cue_type
    return _write_ply_elements(path, [PlyElement.describe(rec, "vertex")])


def write_lines_npz(path: str | Path, segments: np.ndarray, n_views: np.ndarray,
                    views: list[np.ndarray], colors: np.ndarray, points: np.ndarray | None = None,
                    point_colors: np.ndarray | None = None,
                    point_line: np.ndarray | None = None) -> Path:
    """Write 3D line segments (and their samples) to ``lines3d.npz`` atomically."""
    path = Path(path)
    segments = np.asarray(segments, np.float64).reshape(-1, 2, 3)
    L = len(segments)
    if len(n_views) != L or len(views) != L or len(colors) != L:
        raise ValueError(f"lines: {L} segments but n_views {len(n_views)}, views {len(views)}, "
                         f"colors {len(colors)}")
    colors = np.asarray(colors)
    if colors.dtype != np.uint8:
        colors = np.clip(np.round(colors.astype(np.float64).reshape(L, 3) * 255), 0, 255).astype(np.uint8)
    offsets = np.zeros(L + 1, np.int64)
    offsets[1:] = np.cumsum([len(v) for v in views]) if L else []
    view_ids = (np.concatenate([np.asarray(v, np.int32) for v in views]) if L
                else np.zeros(0, np.int32))
    points = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    pc = np.zeros((len(points), 3), np.uint8) if point_colors is None else np.asarray(point_colors)
    if pc.dtype != np.uint8:
        pc = np.clip(np.round(pc.astype(np.float64) * 255), 0, 255).astype(np.uint8)
    pl = np.zeros(len(points), np.int32) if point_line is None else np.asarray(point_line, np.int32)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:  # a file object: np.savez must not append ".npz" to the name
            np.savez(f, segments=segments, n_views=np.asarray(n_views, np.int32), view_ids=view_ids,
                     view_offsets=offsets, colors=colors.reshape(L, 3), points=points,
                     point_colors=pc.reshape(-1, 3), point_line=pl)
    return path


def read_lines_npz(path: str | Path) -> dict[str, np.ndarray | list[np.ndarray]]:
    """Read ``lines3d.npz``; ``views`` is rebuilt as a list of camera-index arrays."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no lines file at {path}")
    with np.load(path) as z:
        out = {k: z[k] for k in z.files}
    off = out["view_offsets"]
    out["views"] = [out["view_ids"][off[k]:off[k + 1]] for k in range(len(off) - 1)]
    return out


EXTRACT_FILES = ("cues_by_type.ply", "lines3d.npz", "lines3d.ply", "plane_anchors.npz", "depth_alignments.json")
"""What `geocues extract` writes beside cues.ply before its report.json, which it writes last."""


def unfinished_extract(cues: str | Path) -> str | None:
    """A sentence when the cue folder (``cues``: the folder or its cues.ply) holds files of `geocues
    extract` but no report.json: an extract killed among its writes, whose files may mix two runs (an
    --overwrite with other options); None for a finished extract or a cues.ply made otherwise."""
    cues = Path(cues)
    folder = cues if cues.is_dir() else cues.parent
    found = [name for name in EXTRACT_FILES if (folder / name).exists()]
    if not found or (folder / "report.json").is_file():
        return None
    return (f"{folder} holds files of `geocues extract` ({', '.join(found)}) but not the report.json it writes "
            "last: an extract killed among its writes? Its files may mix two runs; run the same `geocues extract` "
            "again")


def read_cue_report(cues: str | Path) -> dict:
    """The report.json `geocues extract` wrote beside the cues (``cues``: the folder or its cues.ply);
    {} when there is none or it cannot be read (cue folders made otherwise)."""
    cues = Path(cues)
    report = (cues if cues.is_dir() else cues.parent) / "report.json"
    try:
        return json.loads(report.read_text()) if report.is_file() else {}
    except (OSError, json.JSONDecodeError):
        return {}
