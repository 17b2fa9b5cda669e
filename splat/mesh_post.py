"""A fused mesh after marching cubes: a canonical vertex and triangle order, cleaning (pymeshlab),
and writing it as a PLY atomically (splat/mesh.py fuses it)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from splat.tsdf_config import TSDFConfig

if TYPE_CHECKING:  # Open3D is imported where it is used (splat/mesh.py says why)
    import open3d as o3d

log = logging.getLogger(__name__)


def canonical_order(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """``mesh`` with its vertices sorted by position (x, then y, then z) and its triangles by their
    vertices (each rotated to start at its smallest index, so the winding is kept). Open3D's voxel
    hash map hands marching cubes its blocks in a different order on every run; in this order the same
    surface is the same file, and everything computed from it (cleaning, metrics' samples) the same."""
    import open3d as o3d

    V = np.asarray(mesh.vertices)
    F = np.asarray(mesh.triangles)
    if len(V) == 0:
        return mesh
    order = np.lexsort((V[:, 2], V[:, 1], V[:, 0]))  # [V] new -> old
    rank = np.empty(len(V), np.int64)
    rank[order] = np.arange(len(V))  # old -> new
    F = rank[F] if len(F) else F.reshape(0, 3).astype(np.int64)
    first = F.argmin(1) if len(F) else np.zeros(0, np.int64)
    F = np.take_along_axis(F, (first[:, None] + np.arange(3)) % 3, axis=1)  # cyclic: same winding
    F = F[np.lexsort((F[:, 2], F[:, 1], F[:, 0]))] if len(F) else F
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V[order]),
                                    o3d.utility.Vector3iVector(F.astype(np.int32)))
    if mesh.has_vertex_normals():
        out.vertex_normals = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_normals)[order])
    if mesh.has_vertex_colors():
        out.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_colors)[order])
    return out


def clean_mesh(mesh: o3d.geometry.TriangleMesh, cfg: TSDFConfig | None = None) -> o3d.geometry.TriangleMesh:
    """Remove duplicate vertices and faces, zero-area faces, connected components whose bounding
    box diagonal is below ``cfg.min_component_diag`` of the whole mesh's, and unreferenced
    vertices (pymeshlab); then ``cfg.smooth_iters`` Taubin steps, with the vertex normals computed
    again. Keeps vertex normals and colours. An empty mesh is returned as is."""
    import open3d as o3d
    import pymeshlab  # lazy: only the meshing stage needs it

    cfg = cfg or TSDFConfig()
    cfg.validate()
    V = np.asarray(mesh.vertices, dtype=np.float64)  # [V, 3]
    F = np.asarray(mesh.triangles, dtype=np.int32)  # [F, 3]
    if len(V) == 0 or len(F) == 0:
        log.info("clean_mesh: empty mesh (%d vertices, %d triangles), nothing to clean", len(V), len(F))
        return o3d.geometry.TriangleMesh()
    kwargs = {}
    if mesh.has_vertex_normals():
        kwargs["v_normals_matrix"] = np.asarray(mesh.vertex_normals, dtype=np.float64)
    if mesh.has_vertex_colors():
        rgb = np.clip(np.asarray(mesh.vertex_colors, dtype=np.float64), 0.0, 1.0)
        kwargs["v_color_matrix"] = np.concatenate([rgb, np.ones((len(rgb), 1))], axis=1)  # RGBA
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=V, face_matrix=F, **kwargs), "tsdf")
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    n_before = ms.current_mesh().face_number()
    if cfg.min_component_diag > 0:
        ms.meshing_remove_connected_component_by_diameter(
            mincomponentdiag=pymeshlab.PercentageValue(100.0 * cfg.min_component_diag), removeunref=True)
    ms.meshing_remove_unreferenced_vertices()
    if cfg.smooth_iters > 0 and ms.current_mesh().face_number():
        ms.apply_coord_taubin_smoothing(lambda_=0.5, mu=-0.51, stepsmoothnum=cfg.smooth_iters)
        ms.compute_normal_per_vertex()
    m = ms.current_mesh()
    out = o3d.geometry.TriangleMesh(
        vertices=o3d.utility.Vector3dVector(m.vertex_matrix()),
        triangles=o3d.utility.Vector3iVector(m.face_matrix().astype(np.int32)))
    if m.vertex_number() and mesh.has_vertex_normals():  # pymeshlab's are not unit length (area/angle sums)
        n = m.vertex_normal_matrix()
        out.vertex_normals = o3d.utility.Vector3dVector(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12))
    if m.vertex_number() and mesh.has_vertex_colors():
        out.vertex_colors = o3d.utility.Vector3dVector(m.vertex_color_matrix()[:, :3])
    log.info("clean_mesh: %d -> %d vertices, %d -> %d triangles (%d in components smaller than "
             "%.1f%% of the diagonal), %d Taubin steps", len(V), m.vertex_number(), len(F), m.face_number(),
             n_before - m.face_number(), 100.0 * cfg.min_component_diag, cfg.smooth_iters)
    return out


_EMPTY_PLY = ("ply\nformat ascii 1.0\ncomment empty TSDF mesh (splat.mesh)\nelement vertex 0\n"
              "property float x\nproperty float y\nproperty float z\nelement face 0\n"
              "property list uchar int vertex_indices\nend_header\n")


def write_mesh(mesh: o3d.geometry.TriangleMesh, path: str | Path) -> Path:
    """Write ``mesh`` as a binary PLY (vertices, triangles, normals, colours) atomically; an empty
    mesh becomes a valid PLY with no elements (Open3D refuses to write one), with a warning."""
    import open3d as o3d
    from geocues.atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"write_mesh writes PLY; the path must end in .ply, got {path}")
    verts = np.asarray(mesh.vertices)
    if len(verts) and not np.isfinite(verts).all():
        raise ValueError(f"write_mesh: {int((~np.isfinite(verts).all(1)).sum())} non-finite vertices; "
                         f"not writing {path}")
    with atomic_path(path) as tmp:
        if len(mesh.vertices) == 0:
            log.warning("write_mesh: the mesh is empty; writing an empty PLY to %s", path)
            tmp.write_text(_EMPTY_PLY)
        else:
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
                ok = o3d.io.write_triangle_mesh(filename=str(tmp), mesh=mesh, write_ascii=False,
                                                compressed=False)
            if not ok:
                raise OSError(f"Open3D could not write the mesh to {path}")
    log.info("wrote %s (%d vertices, %d triangles)", path, len(mesh.vertices), len(mesh.triangles))
    return path


def ply_header(path: str | Path) -> list[tuple[str, int, list[list[str]]]]:
    """The elements a PLY header declares, in order: (name, count, the tokens of each of its
    ``property`` lines, e.g. ["property", "list", "uchar", "int", "vertex_indices"]), without reading
    the data."""
    elements: list[tuple[str, int, list[list[str]]]] = []
    with open(path, "rb") as f:
        for _ in range(10_000):
            line = f.readline()
            if not line or line.strip() == b"end_header":
                break
            parts = line.decode(errors="replace").split()
            if len(parts) == 3 and parts[0] == "element":
                elements.append((parts[1], int(parts[2]), []))
            elif parts[:1] == ["property"] and elements:
                elements[-1][2].append(parts)
    return elements


def ply_element_counts(path: str | Path) -> dict[str, int]:
    """Element counts declared in a PLY header ({"vertex": n, "face": m, ...}), without reading the data."""
    return {name: count for name, count, _ in ply_header(path)}


__all__ = ["canonical_order", "clean_mesh", "ply_element_counts", "ply_header", "write_mesh"]
