"""Triangle geometry of the benchmark rooms: quads, boxes and cylinders with texture frames.

Every planar piece carries a *texture frame* (origin, unit u axis, unit v axis in its plane) so that
the procedural albedo (``textures.py``) is a function of the 2D surface position ``(u, v)`` in
metres, and a *material* index. Normals follow the winding and always point into the free space of
the room: the room shell faces inward, furniture faces outward. Quads never share vertices with
other quads, so per-vertex normals equal the face normals (flat shading, exact GT normals).

World frame: metres, z up, floor at z = 0, the room spans [0, W] x [0, D] x [0, H].
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass
class Material:
    """A surface appearance: a texture family (``kind``), a base linear-RGB albedo and parameters."""

    name: str  # unique, e.g. "wall_south", "poster_2"
    kind: str  # texture family, see textures.ALBEDO_FUNCTIONS
    color: list[float]  # [3] linear RGB base albedo in [0, 1]
    params: dict = field(default_factory=dict)  # JSON-serialisable, kind-specific


@dataclass
class RoomMesh:
    """The assembled room: triangles with per-triangle material and texture frame."""

    vertices: np.ndarray  # [V, 3] float64 metres
    triangles: np.ndarray  # [F, 3] int32
    tri_material: np.ndarray  # [F] int32 index into materials
    tri_frame: np.ndarray  # [F] int32 index into frames
    frames: np.ndarray  # [Nf, 3, 3] float64 rows: origin, u axis, v axis
    materials: list[Material]
    boxes: list[tuple[np.ndarray, np.ndarray]]  # axis-aligned bounds (lo [3], hi [3]) of objects

    @property
    def face_normals(self) -> np.ndarray:
        """Unit normals from the winding, [F, 3] (they face the room's free space)."""
        v = self.vertices[self.triangles]  # [F, 3, 3]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def material_colors(self) -> np.ndarray:
        """Base albedo of each triangle's material, [F, 3]."""
        cols = np.array([m.color for m in self.materials], dtype=np.float64)
        return cols[self.tri_material]

    def to_legacy(self, colors: bool = True):
        """Open3D legacy TriangleMesh with vertex normals (= face normals) and base colours."""
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            vertices=o3d.utility.Vector3dVector(self.vertices),
            triangles=o3d.utility.Vector3iVector(self.triangles.astype(np.int32)))
        mesh.compute_vertex_normals(normalized=True)
        if colors:
            vcol = np.zeros_like(self.vertices)
            vcol[self.triangles.reshape(-1)] = np.repeat(self.material_colors(), 3, axis=0)
            mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(vcol, 0.0, 1.0) ** (1 / 2.2))
        return mesh

    def raycasting_scene(self):
        """An Open3D RaycastingScene holding this mesh (geometry id 0)."""
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            vertex_positions=o3d.core.Tensor(self.vertices.astype(np.float32)),
            triangle_indices=o3d.core.Tensor(self.triangles.astype(np.uint32)))
        return scene

    def write_ply(self, path: Path) -> Path:
        """Write the mesh (vertices, triangles, vertex normals, base colours) as binary PLY."""
        import open3d as o3d

        path = Path(path)
        ok = o3d.io.write_triangle_mesh(filename=str(path), mesh=self.to_legacy(), write_ascii=False)
        if not ok:
            raise OSError(f"Open3D could not write the mesh to {path}")
        return path


class MeshBuilder:
    """Collects quads, boxes and cylinders with their materials and texture frames."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.tri_material: list[int] = []
        self.tri_frame: list[int] = []
        self.frames: list[np.ndarray] = []
        self.materials: list[Material] = []
        self.boxes: list[tuple[np.ndarray, np.ndarray]] = []
        self._nv = 0

    # ------------------------------------------------------------------ materials
    def material(self, name: str, kind: str, color, **params) -> int:
        """Register a material and return its index."""
        if any(m.name == name for m in self.materials):
            raise ValueError(f"duplicate material name {name!r}")
        col = [float(np.clip(c, 0.0, 1.0)) for c in color]
        self.materials.append(Material(name=name, kind=kind, color=col, params=params))
        return len(self.materials) - 1

    # ------------------------------------------------------------------ primitives
    def _add(self, verts: np.ndarray, tris: np.ndarray, mat: int, frame: np.ndarray) -> None:
        self.frames.append(np.asarray(frame, dtype=np.float64))
        self.vertices.append(np.asarray(verts, dtype=np.float64))
        self.triangles.append(np.asarray(tris, dtype=np.int64) + self._nv)
        self._nv += len(verts)
        self.tri_material.extend([mat] * len(tris))
        self.tri_frame.extend([len(self.frames) - 1] * len(tris))

    def quad(self, center, u_axis, v_axis, half_u: float, half_v: float, mat: int,
             origin=None) -> None:
        """Rectangle centred at ``center`` spanning +-half_u along u, +-half_v along v.
        The normal is u x v; the texture origin defaults to the (-u, -v) corner."""
        c, u, v = (np.asarray(a, dtype=np.float64) for a in (center, u_axis, v_axis))
        corners = np.stack([c - half_u * u - half_v * v, c + half_u * u - half_v * v,
                            c + half_u * u + half_v * v, c - half_u * u + half_v * v])  # [4, 3]
        o = corners[0] if origin is None else np.asarray(origin, dtype=np.float64)
        self._add(corners, np.array([[0, 1, 2], [0, 2, 3]]), mat, np.stack([o, u, v]))

    def box(self, center, size, mat, axis_x=(1.0, 0.0, 0.0), skip: tuple[str, ...] = ("bottom",),
            face_mats: dict[str, int] | None = None, inward: bool = False,
            obstacle: bool = True) -> None:
        """Box with horizontal local axes ``axis_x`` and ``axis_y = z x axis_x`` (size = extents
        along x, y, z). Faces: left/right (-x/+x), back/front (-y/+y), bottom/top; ``skip`` drops
        faces (e.g. the bottom resting on the floor, the back against a wall). ``inward`` makes the
        normals point into the box (the room shell)."""
        c = np.asarray(center, dtype=np.float64)
        ax = np.asarray(axis_x, dtype=np.float64)
        ax = ax / np.linalg.norm(ax)
        if abs(ax[2]) > 1e-9:
            raise ValueError(f"axis_x must be horizontal, got {tuple(ax)}")
        ay = np.cross(Z_UP, ax)
        half = np.asarray(size, dtype=np.float64) / 2.0
        faces = {"left": (-ax, half[0]), "right": (ax, half[0]), "back": (-ay, half[1]),
                 "front": (ay, half[1]), "bottom": (-Z_UP, half[2]), "top": (Z_UP, half[2])}
        extent = {"left": (half[1], half[2]), "right": (half[1], half[2]),
                  "back": (half[0], half[2]), "front": (half[0], half[2]),
                  "bottom": (half[0], half[1]), "top": (half[0], half[1])}
        for name, (out_n, dist) in faces.items():
            if name in skip:
                continue
            n = -out_n if inward else out_n
            if abs(n[2]) < 0.5:  # vertical face: v up, u = v x n
                v = Z_UP.copy()
                u = np.cross(v, n)
                hu, hv = extent[name]
            else:  # horizontal face: u along the box's x axis
                u = ax.copy()
                v = np.cross(n, u)
                hu, hv = extent[name]
            self.quad(c + out_n * dist, u, v, hu, hv, (face_mats or {}).get(name, mat))
        if obstacle:
            corners = c + np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                                    for sz in (-1, 1)]) * half @ np.stack([ax, ay, Z_UP])
            self.boxes.append((corners.min(axis=0), corners.max(axis=0)))

    def cylinder(self, center_xy, z0: float, z1: float, radius: float, mat: int,
                 segments: int = 24, top: bool = True, top_mat: int | None = None) -> None:
        """Vertical prism approximating a cylinder (outward normals, no bottom). The side's texture
        u coordinate is the arc length, continuous around the circumference."""
        cx, cy = float(center_xy[0]), float(center_xy[1])
        ang = np.linspace(0.0, 2 * np.pi, segments + 1)
        ring = np.stack([cx + radius * np.cos(ang), cy + radius * np.sin(ang)], axis=1)  # [S+1, 2]
        seg_len = float(np.linalg.norm(ring[1] - ring[0]))
        for k in range(segments):
            p0 = np.array([ring[k, 0], ring[k, 1], z0])
            p1 = np.array([ring[k + 1, 0], ring[k + 1, 1], z0])
            tang = (p1 - p0) / seg_len
            centre = (p0 + p1) / 2 + Z_UP * (z1 - z0) / 2
            # u = tangent, v = up: u x v = tangent x z points outward for a counter-clockwise ring
            self.quad(centre, tang, Z_UP, seg_len / 2, (z1 - z0) / 2, mat,
                      origin=p0 - tang * (k * seg_len))
        if top:
            rim = np.concatenate([ring[:-1], np.full((segments, 1), z1)], axis=1)  # [S, 3]
            verts = np.concatenate([[[cx, cy, z1]], rim])
            tris = np.array([[0, 1 + k, 1 + (k + 1) % segments] for k in range(segments)])
            self._add(verts, tris, mat if top_mat is None else top_mat,
                      np.stack([[cx - radius, cy - radius, z1], [1.0, 0, 0], [0, 1.0, 0]]))
        self.boxes.append((np.array([cx - radius, cy - radius, z0]),
                           np.array([cx + radius, cy + radius, z1])))

    # ------------------------------------------------------------------ result
    def build(self) -> RoomMesh:
        """Assemble the collected pieces into one RoomMesh."""
        if not self.triangles:
            raise ValueError("the mesh builder holds no geometry")
        mesh = RoomMesh(vertices=np.concatenate(self.vertices),
                        triangles=np.concatenate(self.triangles).astype(np.int32),
                        tri_material=np.asarray(self.tri_material, np.int32),
                        tri_frame=np.asarray(self.tri_frame, np.int32),
                        frames=np.stack(self.frames), materials=list(self.materials),
                        boxes=list(self.boxes))
        log.debug("room mesh: %d vertices, %d triangles, %d materials", len(mesh.vertices),
                  len(mesh.triangles), len(mesh.materials))
        return mesh
