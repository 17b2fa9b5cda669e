"""Reading a triangle mesh file a user brings, so that what is scored is the whole file or an error.

Open3D's readers return what they managed to read without an error: a truncated PLY or OFF,
an OBJ's quads and n-gons (dropped: one face of six of a cube scored), and a PLY whose faces are
malformed ends the process (a segmentation fault in its polygon triangulation). So:

- PLY is read with plyfile (a triangle mesh's faces memory-mapped in one pass; polygons are
  triangulated as fans, faces of fewer than 3 corners dropped with a warning); a truncated or
  malformed file is an error naming it;
- OBJ is read with trimesh (polygons triangulated; materials skipped);
- OFF, STL, GLB/GLTF and FBX with Open3D, an OFF's declared counts checked against what was read.

Returns (vertices [V, 3] float64, faces [F, 3] int64); the caller checks the indices
(``evaluation.surfaces.TriMesh``).
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

FORMATS = (".ply", ".obj", ".off", ".stl", ".glb", ".gltf", ".fbx")


def fan_triangulate(polygons: list[np.ndarray] | np.ndarray) -> tuple[np.ndarray, int]:
    """Triangles [T, 3] of polygons given as index arrays (corner 0 joined to each later edge), and
    the number of polygons of fewer than 3 corners left out."""
    tris, dropped = [], 0
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.int64)
        if len(poly) < 3:
            dropped += 1
            continue
        k = np.arange(1, len(poly) - 1)
        tris.append(np.stack([np.full_like(k, poly[0]), poly[k], poly[k + 1]], axis=1))
    return (np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)), dropped


INDEX_LISTS = ("vertex_indices", "vertex_index")


def _ply_face_list(path: Path) -> str | None:
    """The name of the face element's list of vertex indices in a PLY header: vertex_indices or
    vertex_index, else its only integer list (a face may list texcoords first: taking the first list
    read them as indices)."""
    from splat.mesh_post import ply_header

    lists = [(p[4], p[3]) for name, _, props in ply_header(path) if name == "face"  # (name, item type)
             for p in props if len(p) == 5 and p[1] == "list"]
    named = [n for n, _ in lists if n in INDEX_LISTS]
    ints = [n for n, t in lists if "int" in t or t in ("char", "uchar", "short", "ushort")]
    return named[0] if named else ints[0] if len(ints) == 1 else None


def _read_plydata(path: Path, name: str | None):
    import plyfile

    with warnings.catch_warnings():  # numpy's "input contained no data" on a damaged text PLY
        warnings.simplefilter("ignore", UserWarning)
        try:  # a triangle mesh: one pass, memory-mapped
            return plyfile.PlyData.read(str(path), known_list_len={"face": {name: 3}} if name else None)
        except Exception:  # noqa: BLE001 - polygons of other sizes, or a damaged file: read again to say which
            try:
                return plyfile.PlyData.read(str(path))
            except Exception as e:  # noqa: BLE001 - plyfile's parse errors have no common base class
                raise ValueError(f"{path} is truncated or damaged: {e}") from None


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of a PLY file (module docstring)."""

    try:
        name = _ply_face_list(path)
    except OSError as e:
        raise ValueError(f"{path}: cannot read it ({e})") from None
    ply = _read_plydata(path, name)
    names = [el.name for el in ply.elements]
    if "vertex" not in names or not {"x", "y", "z"} <= {p.name for p in ply["vertex"].properties}:
        raise ValueError(f"{path}: no vertex element with x, y, z")
    v = ply["vertex"]
    vertices = np.stack([np.asarray(v[c], dtype=np.float64) for c in "xyz"], axis=1)
    if "face" not in names or name is None or len(ply["face"].data) == 0:
        raise ValueError(f"{path}: no triangles in this file (a point cloud, or an empty mesh)")
    faces = ply["face"][name]
    if faces.dtype != object and faces.ndim == 2:
        return vertices, faces.astype(np.int64)
    lengths = np.fromiter((len(f) for f in faces), np.int64, len(faces))
    if (lengths == 3).all():  # triangles read on the slow path (another list property beside them)
        return vertices, np.stack(faces).astype(np.int64)
    tris, dropped = fan_triangulate(faces)
    if dropped:
        log.warning("%s: %d of %d faces have fewer than 3 corners and are left out", path, dropped, len(faces))
    if len(tris) > len(faces) - dropped:
        log.info("%s: %d polygons triangulated into %d triangles", path, len(faces) - dropped, len(tris))
    return vertices, tris


def _off_counts(path: Path) -> tuple[int, int] | None:
    """(vertices, faces) an OFF file declares, or None when its header does not parse."""
    tokens: list[str] = []
    with open(path, "rb") as f:
        for line in f:  # "OFF", then "V F E" (on the same line or the next), comments after '#'
            tokens += line.split(b"#")[0].decode(errors="replace").split()
            if len(tokens) >= 4:
                break
    if tokens and tokens[0].endswith("OFF"):
        tokens = tokens[1:]
    try:
        return int(tokens[0]), int(tokens[1])
    except (IndexError, ValueError):
        return None


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        mesh = trimesh.load(str(path), file_type="obj", process=False, force="mesh", skip_materials=True)
    except Exception as e:  # noqa: BLE001 - trimesh raises IndexError, ValueError, ... on a bad file
        raise ValueError(f"{path} is damaged: {type(e).__name__}: {e}") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise ValueError(f"{path}: no faces in this file (a point cloud, lines only, or an empty mesh)")
    return np.asarray(mesh.vertices, dtype=np.float64), faces


def read_mesh_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3] float64, faces [F, 3] int64) of a mesh file (module docstring); errors
    (ValueError, FileNotFoundError) name the file."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"{path}: not a mesh format this reads ({', '.join(f[1:].upper() for f in FORMATS)})")
    if suffix == ".ply":
        return read_ply(path)
    if suffix == ".obj":
        return read_obj(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(filename=str(path))
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    if len(faces) == 0:
        raise ValueError(f"{path}: no triangles in this file (empty mesh, point cloud or unreadable)")
    if suffix == ".off":  # Open3D returns what it read of a truncated file without error
        want = _off_counts(path)
        if want is not None and (len(mesh.vertices) < want[0] or len(faces) < want[1]):
            raise ValueError(f"{path} is truncated or damaged: read {len(mesh.vertices)} of {want[0]} vertices "
                             f"and {len(faces)} of {want[1]} faces (as triangles)")
    return np.asarray(mesh.vertices, dtype=np.float64), faces


__all__ = ["FORMATS", "fan_triangulate", "read_mesh_file", "read_obj", "read_ply"]
