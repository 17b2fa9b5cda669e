"""evaluation.mesh_files: a mesh file is scored whole or refused (Open3D's readers dropped an OBJ's
quads, read half of a truncated OFF and crashed on a malformed PLY, all without an error)."""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d
import plyfile
import pytest

from evaluation.mesh_files import fan_triangulate, read_mesh_file
from evaluation.surfaces import load_mesh

CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
CUBE_QUADS = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def _obj(path, faces):
    lines = [f"v {x} {y} {z}" for x, y, z in CUBE_V] + ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def _ply(path, faces, text):
    v = np.array([tuple(p) for p in CUBE_V], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    f = np.empty(len(faces), dtype=[("vertex_indices", "O")])
    f["vertex_indices"] = [np.asarray(x, "i4") for x in faces]
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(f, "face")],
                    text=text).write(str(path))
    return path


def test_fan_triangulate_keeps_area_and_counts_short_faces():
    tris, dropped = fan_triangulate([np.array([0, 1, 2, 3]), np.array([4, 5]), np.array([0, 1, 2])])
    assert tris.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 2]] and dropped == 1


@pytest.mark.parametrize("faces", [CUBE_QUADS, [[0, 3, 2], [0, 2, 1]] + CUBE_QUADS[1:]], ids=["quads", "mixed"])
def test_obj_polygons_are_scored_whole(tmp_path, faces):
    """A cube of quads (or two triangles and five quads) read from OBJ: all six sides (Open3D kept
    the triangles only: one side of six, or 'no triangles')."""
    mesh = load_mesh(_obj(tmp_path / "cube.obj", faces))
    assert len(mesh.faces) == 12 and mesh.areas.sum() == pytest.approx(6.0)


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_ply_polygons_are_triangulated(tmp_path, text):
    mesh = load_mesh(_ply(tmp_path / "cube.ply", [[0, 3, 2], [0, 2, 1]] + CUBE_QUADS[1:], text))
    assert len(mesh.faces) == 12 and mesh.areas.sum() == pytest.approx(6.0)


def test_ply_triangles_read_as_open3d_reads_them(tmp_path):
    """The oracle: Open3D's reader on a well-formed triangle PLY (binary, double vertices, normals)."""
    rng = np.random.default_rng(0)
    src = o3d.geometry.TriangleMesh.create_sphere(radius=0.7, resolution=12)
    src.vertices = o3d.utility.Vector3dVector(np.asarray(src.vertices) + rng.normal(0, 0.01, (len(src.vertices), 3)))
    src.compute_vertex_normals()
    path = tmp_path / "sphere.ply"
    o3d.io.write_triangle_mesh(str(path), src)
    ref = o3d.io.read_triangle_mesh(str(path))
    vertices, faces = read_mesh_file(path)
    np.testing.assert_array_equal(vertices, np.asarray(ref.vertices))
    np.testing.assert_array_equal(faces, np.asarray(ref.triangles))


def test_short_faces_are_dropped_with_a_warning(tmp_path, caplog):
    path = _ply(tmp_path / "lines.ply", [[0, 1, 2], [3, 4]], text=True)
    with caplog.at_level(logging.WARNING, logger="evaluation.mesh_files"):
        mesh = load_mesh(path)
    assert len(mesh.faces) == 1 and "1 of 2 faces have fewer than 3 corners" in caplog.text


def test_damaged_files_are_errors_naming_them(tmp_path):
    bad = tmp_path / "rows.ply"  # face rows without their counts: Open3D ended the process (SIGSEGV)
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n0 1 2\n0 1 7\n")
    with pytest.raises(ValueError, match="rows.ply is truncated or damaged"):
        load_mesh(bad)
    ok = _ply(tmp_path / "cube.ply", CUBE_QUADS, text=False)
    cut = tmp_path / "cut.ply"
    cut.write_bytes(ok.read_bytes()[:-20])
    with pytest.raises(ValueError, match="cut.ply is truncated or damaged"):
        load_mesh(cut)
    with pytest.raises(ValueError, match="index.obj is damaged"):
        load_mesh(_obj(tmp_path / "index.obj", [[0, 1, 2], [0, 1, 9]]))
    with pytest.raises(ValueError, match=r"notes.txt: not a mesh format this reads \(PLY, OBJ"):
        (tmp_path / "notes.txt").write_text("hello")
        load_mesh(tmp_path / "notes.txt")


def test_truncated_off_is_an_error(tmp_path):
    """Open3D read the faces before the cut and returned them without an error."""
    src = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=20)
    path = tmp_path / "sphere.off"
    o3d.io.write_triangle_mesh(str(path), src, write_ascii=True)
    assert len(read_mesh_file(path)[1]) == len(src.triangles)
    cut = tmp_path / "cut.off"
    text = path.read_text()
    cut.write_text(text[: len(text) * 9 // 10])  # most faces, the last ones cut
    with pytest.raises(ValueError, match=rf"cut.off is truncated or damaged: read .* of {len(src.triangles)} faces"):
        load_mesh(cut)


@pytest.mark.parametrize("layout", ["texcoord_first", "vertex_index", "big_endian_uint"])
def test_ply_face_layouts(tmp_path, layout):
    """The face's index list is found by its name, not its place: a face listing texcoords first was read
    as 8 triangles [0, 0, 0] (the texcoords as indices) without an error."""
    v = np.array([tuple(p) for p in CUBE_V], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    name = "vertex_index" if layout == "vertex_index" else "vertex_indices"
    fields = ([("texcoord", "O")] if layout == "texcoord_first" else []) + [(name, "O")]
    f = np.empty(2, dtype=fields)
    f[name] = [np.array([0, 1, 2], "u4" if layout == "big_endian_uint" else "i4"), np.array([0, 2, 3], "i4")]
    if layout == "texcoord_first":
        f["texcoord"] = [np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], "f4")] * 2
    el = plyfile.PlyElement.describe(f, "face", len_types={name: "u1", "texcoord": "u1"},
                                     val_types={name: "u4" if layout == "big_endian_uint" else "i4", "texcoord": "f4"})
    path = tmp_path / "two.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"), el],
                    byte_order=">" if layout == "big_endian_uint" else "<").write(str(path))
    vertices, faces = read_mesh_file(path)
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3]] and len(vertices) == 8
