"""TSDF meshing of rendered depth: fuse per-view depth (and colour) into a truncated signed distance
volume, extract the zero level set with marching cubes, clean it (DESIGN.md, "Meshing").

The trainer renders the expected (or, with ``--tsdf.depth median``, the median) depth of every
training view, masks it by alpha and hands each view
to :func:`fuse_views`, then :func:`clean_mesh` and :func:`write_mesh` (splat/mesh_post.py, with the
canonical vertex order; the options are :class:`TSDFConfig`, splat/tsdf_config.py).

Backend: Open3D's ``t.geometry.VoxelBlockGrid`` (a hash map of 16^3-voxel blocks, attributes
``tsdf``, ``weight`` and ``color`` in float32). Open3D 0.20's legacy ``ScalableTSDFVolume`` returns
empty meshes, so it is not used. The grid is fed float32 depth in metres (``depth_scale=1``) with
float32 colour in [0, 1]: its kernels take float32 depth with float32 colour or uint16 depth with
uint8 colour, nothing else. Each fused view adds 1 to the weight of every voxel it updates, so the
weight of a voxel is the number of views that observed it; extraction keeps voxels whose weight is
*strictly greater* than ``weight_threshold`` (measured on 0.20: threshold 1.0 on a single view gives
an empty mesh, 0.99 does not).

Pixel convention (docs/conventions.md): COLMAP, pixel (row i, col j) covers ``[j, j+1) x [i, i+1)``
with its centre at ``(j + 0.5, i + 0.5)``, and its depth is the z-depth along the ray through that
centre. Open3D's integration kernel projects a voxel with ``u = fx x/z + cx`` and reads the pixel
``(int(u), int(v))`` -- truncation, so the pixel read is the COLMAP pixel that contains the voxel's
projection. K therefore goes to Open3D *unshifted* (:data:`OPEN3D_PIXEL_SHIFT` = 0). Subtracting
half a pixel from cx, cy, as one would for a convention with pixel centres on integers, biases a
slanted surface by half a pixel's footprint times the slope (tests/test_mesh.py measures both).
The same kernel only accepts ``u <= W - 1`` and ``v <= H - 1``, which drops the last column and row
of every image; :meth:`TSDFFuser.integrate` repeats the last column and row once so the whole
image is used. Colour is looked up at the depth pixel's index (a 1-pixel border keeps Open3D's
float round trip of that index inside the image; see :meth:`TSDFFuser.integrate`).

Block allocation: Open3D's ``compute_unique_block_coordinates(depth, ...)`` unprojects only every
4th pixel (and the image size divided by 4), at integer pixel coordinates, so the last rows and
columns can fall into blocks that are never allocated and never fused (measured: a 40 x 30 image
lost its bottom 3 rows). Here every valid pixel is back-projected through its COLMAP centre and
the blocks within ``sdf_trunc`` of those points are allocated (the point-cloud overload).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from typing import TYPE_CHECKING, Iterable

import numpy as np
from tqdm import tqdm

from splat.camera import check_pinhole
from splat.mesh_post import canonical_order, clean_mesh, write_mesh
from splat.tsdf_config import TSDFConfig, open3d_device

if TYPE_CHECKING:  # Open3D is imported where it is used: splat.train imports this module on
    import open3d as o3d  # machines that train without meshing (no Open3D there)

log = logging.getLogger(__name__)

OPEN3D_PIXEL_SHIFT = 0.0
"""Added to cx, cy before they go to Open3D. 0: its integration reads pixel ``(int(u), int(v))``,
which is the COLMAP pixel containing ``(u, v)`` (module docstring; tests/test_mesh.py checks it)."""


def _as_depth(depth: np.ndarray, where: str) -> np.ndarray:
    """[H, W] float32 metres with NaN, Inf and negative values set to 0 (= invalid)."""
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.shape[0] < 1 or depth.shape[1] < 1:
        raise ValueError(f"{where}: depth must be [H, W], got shape {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f"{where}: depth must be float z-depth in metres, got dtype {depth.dtype}")
    depth = depth.astype(np.float32, copy=True)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def _as_rgb(rgb: np.ndarray, shape: tuple[int, int], where: str) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1] (non-finite values set to 0)."""
    rgb = np.asarray(rgb)
    if rgb.shape != (*shape, 3):
        raise ValueError(f"{where}: rgb must be [H, W, 3] = {(*shape, 3)} to match the depth map, "
                         f"got {rgb.shape}")
    if not np.issubdtype(rgb.dtype, np.floating):
        raise ValueError(f"{where}: rgb must be float in [0, 1], got dtype {rgb.dtype}")
    rgb = np.nan_to_num(rgb.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return np.clip(rgb, 0.0, 1.0)


def open3d_intrinsics(K: np.ndarray) -> np.ndarray:
    """The [3, 3] matrix to give Open3D for a COLMAP-convention K (``OPEN3D_PIXEL_SHIFT`` added
    to cx, cy; see the module docstring for why the shift is 0)."""
    K = np.array(K, dtype=np.float64)
    K[0, 2] += OPEN3D_PIXEL_SHIFT  # COLMAP pixel centre (j + 0.5) -> Open3D's int(u) lookup
    K[1, 2] += OPEN3D_PIXEL_SHIFT
    return K


def backproject(depth: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray) -> np.ndarray:
    """World points [N, 3] of the valid pixels (depth > 0) of a z-depth map [H, W] (metres), each on
    the ray through its COLMAP pixel centre (j + 0.5, i + 0.5)."""
    i, j = np.nonzero(depth > 0)
    z = depth[i, j].astype(np.float64)
    x_cam = np.stack([(j + 0.5 - K[0, 2]) / K[0, 0] * z, (i + 0.5 - K[1, 2]) / K[1, 1] * z, z], axis=1)
    R, t = world_to_cam[:3, :3], world_to_cam[:3, 3]
    return (x_cam - t) @ R  # R^T (x_cam - t), row form


class TSDFFuser:
    """Accumulates views in an Open3D ``VoxelBlockGrid`` TSDF; :meth:`extract_mesh` meshes it.

    Views come either all with colour or all without (a view without colour would still add to the
    weights that average the colours and darken them).
    """

    def __init__(self, cfg: TSDFConfig | None = None) -> None:
        import open3d as o3d
        self.cfg = cfg or TSDFConfig()
        self.cfg.validate()
        self.device = o3d.core.Device(open3d_device(self.cfg.device))
        f32 = o3d.core.float32
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"), attr_dtypes=(f32, f32, f32),
            attr_channels=((1), (1), (3)), voxel_size=self.cfg.voxel_size, block_resolution=16,
            block_count=self.cfg.block_count, device=self.device)
        self.n_views = 0  # views integrated, including ones without a valid pixel
        self.n_fused = 0  # views with at least one valid pixel
        self.n_valid_pixels = 0
        self.n_beyond = 0  # otherwise valid depths dropped for lying beyond depth_max
        self.with_color: bool | None = None  # fixed by the first view

    @property
    def n_blocks(self) -> int:
        """Number of allocated 16^3-voxel blocks."""
        return int(self.grid.hashmap().size())

    def integrate(self, depth: np.ndarray, rgb: np.ndarray | None, K: np.ndarray,
                  world_to_cam: np.ndarray) -> int:
        """Fuse one view; return its number of valid depth pixels.

        depth: [H, W] float z-depth in metres, 0 = invalid (NaN, Inf and negatives count as 0).
        rgb: [H, W, 3] float in [0, 1], or None (then every view must come without colour).
        K: [3, 3] intrinsics, COLMAP pixel convention (pixel (i, j) centre at (j + 0.5, i + 0.5)).
        world_to_cam: [4, 4] world-to-camera transform, OpenCV axes (x right, y down, z forward).
        """
        import open3d as o3d
        where = f"view {self.n_views}"
        depth = _as_depth(depth, where)
        K, T = check_pinhole(K, world_to_cam, where)
        with_color = rgb is not None
        rgb = _as_rgb(rgb, depth.shape, where) if with_color else None
        if self.with_color is not None and with_color != self.with_color:
            raise ValueError(f"{where}: rgb is {'given' if with_color else 'None'} but earlier views "
                             f"came {'with' if self.with_color else 'without'} colour; mix neither")
        self.with_color = with_color
        self.n_views += 1
        beyond = depth > self.cfg.depth_max
        self.n_beyond += int(np.count_nonzero(beyond))
        depth[beyond] = 0.0
        n_valid = int(np.count_nonzero(depth))
        self.n_valid_pixels += n_valid
        if n_valid == 0:
            log.debug("%s: no valid depth pixel, nothing to fuse", where)
            return 0
        self.n_fused += 1
        points = backproject(depth, K, T).astype(np.float32)  # [N, 3] world, one per valid pixel
        # Open3D reads pixel (int(u), int(v)) but only for u <= W - 1, v <= H - 1: repeat the last
        # column and row so that u in (W - 1, W) and v in (H - 1, H) read the last pixel too.
        depth = np.pad(depth, ((0, 1), (0, 1)), mode="edge")
        Kt = o3d.core.Tensor(open3d_intrinsics(K))  # COLMAP pixel convention, shift 0 (docstring)
        Tt = o3d.core.Tensor(np.ascontiguousarray(T))
        mult = self.cfg.trunc / self.cfg.voxel_size
        d_img = o3d.t.geometry.Image(o3d.core.Tensor(depth)).to(self.device)
        blocks = self.grid.compute_unique_block_coordinates(
            pcd=o3d.t.geometry.PointCloud(o3d.core.Tensor(points)).to(self.device),
            trunc_voxel_multiplier=mult)
        if with_color:
            # Open3D finds the colour pixel by unprojecting the depth pixel index with the depth K
            # and projecting with the colour K, then rounding; in float32 that lands a hair below 0
            # on the first row/column and fails its bounds test (the voxel's colour is then
            # averaged with nothing, i.e. darkened). A 1-pixel border and cx, cy + 1 keep it inside.
            rgb = np.ascontiguousarray(np.pad(rgb, ((1, 1), (1, 1), (0, 0)), mode="edge"))
            Kc = open3d_intrinsics(K)
            Kc[0, 2] += 1.0
            Kc[1, 2] += 1.0
            c_img = o3d.t.geometry.Image(o3d.core.Tensor(rgb)).to(self.device)
            self.grid.integrate(block_coords=blocks, depth=d_img, color=c_img, depth_intrinsic=Kt,
                                color_intrinsic=o3d.core.Tensor(Kc), extrinsic=Tt, depth_scale=1.0,
                                depth_max=self.cfg.depth_max, trunc_voxel_multiplier=mult)
        else:
            self.grid.integrate(block_coords=blocks, depth=d_img, intrinsic=Kt, extrinsic=Tt,
                                depth_scale=1.0, depth_max=self.cfg.depth_max,
                                trunc_voxel_multiplier=mult)
        return n_valid

    def _warn_beyond_depth_max(self, share: float = 0.05) -> None:
        """Say when more than ``share`` of the depths were beyond ``depth_max`` and left out: a room's
        depths are under 10 m, so that many means a scene in another unit (an images-only SfM) or a
        hall, and the surfaces they saw are missing from the mesh."""
        total = self.n_beyond + self.n_valid_pixels
        if total and self.n_beyond > share * total:
            log.warning("TSDF: %.0f %% of the depths (%d of %d pixels) lie beyond depth_max %g and were left "
                        "out, so what they saw is missing from the mesh; if the scene is not in metres "
                        "(`geocues info SCENE` warns), make it metric with `geocues rescale`, else raise "
                        "--tsdf.depth-max", 100 * self.n_beyond / total, self.n_beyond, total, self.cfg.depth_max)

    def effective_weight_threshold(self) -> float:
        """``weight_threshold``, lowered to ``n_fused - 1`` when no voxel could exceed it (a voxel's
        weight is at most the number of views with valid depth)."""
        thr = float(self.cfg.weight_threshold)
        if self.n_fused <= thr:
            low = float(max(self.n_fused - 1, 0))
            log.warning("TSDF: %d view(s) with valid depth fused but weight_threshold is %g (a voxel "
                        "needs more views than that); using %g", self.n_fused, thr, low)
            return low
        return thr

    def max_weight(self) -> float:
        """The largest weight (views fused) of any allocated voxel; 0 when none."""
        import open3d as o3d

        idx = self.grid.hashmap().active_buf_indices().to(o3d.core.int64)
        if idx.shape[0] == 0:
            return 0.0
        return float(self.grid.attribute("weight")[idx].cpu().numpy().max())

    def extract_mesh(self) -> o3d.geometry.TriangleMesh:
        """Marching cubes on the fused TSDF: a legacy Open3D mesh with vertex normals (from the
        TSDF gradient, facing the free space) and, when views had colour, vertex colours in [0, 1].
        Empty (with a warning) when nothing valid was fused."""
        import open3d as o3d
        self._warn_beyond_depth_max()
        if self.n_blocks == 0:
            log.warning("TSDF: no valid depth in %d view(s); the mesh is empty", self.n_views)
            return o3d.geometry.TriangleMesh()
        thr = self.effective_weight_threshold()
        tmesh = self.grid.extract_triangle_mesh(weight_threshold=thr)
        mesh = canonical_order(tmesh.to_legacy())
        if not self.with_color:
            mesh.vertex_colors = o3d.utility.Vector3dVector(np.zeros((0, 3)))
        if len(mesh.triangles) == 0:
            most = self.max_weight()
            log.warning("TSDF: marching cubes found no surface (%d views, %d blocks, weight > %g)%s",
                        self.n_views, self.n_blocks, thr,
                        f"; no voxel was seen by more than {most:g} view(s) (a sparse capture): "
                        f"--tsdf.weight-threshold {max(most - 1, 0):g} keeps what {most:g} saw "
                        f"(`splat mesh RUN --tsdf.weight-threshold {max(most - 1, 0):g}` on a finished run)"
                        if 0 < most <= thr else "")
        return mesh


def fuse_views(views: Iterable[tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]],
               cfg: TSDFConfig | None = None, progress: bool = True) -> o3d.geometry.TriangleMesh:
    """Fuse ``(depth [H, W] m, rgb [H, W, 3] or None, K [3, 3], world_to_cam [4, 4])`` tuples
    (see :meth:`TSDFFuser.integrate`) and extract the mesh (not cleaned: see :func:`clean_mesh`)."""
    cfg = cfg or TSDFConfig()
    fuser = TSDFFuser(cfg)
    log.info("TSDF fusion: %s (truncation %.4f m)", asdict(cfg), cfg.trunc)
    t0 = time.perf_counter()
    total = len(views) if hasattr(views, "__len__") else None
    quiet = {} if progress else {"disable": True}  # no disable=False: it overrode -q's default (bars on)
    for view in tqdm(views, total=total, desc="TSDF fusion", unit="view", **quiet):
        if len(view) != 4:
            raise ValueError(f"view {fuser.n_views}: expected (depth, rgb, K, world_to_cam), "
                             f"got a {len(view)}-tuple")
        fuser.integrate(*view)
    t1 = time.perf_counter()
    mesh = fuser.extract_mesh()
    log.info("TSDF fusion: %d views (%d with valid depth), %d valid pixels, %d blocks -> %d vertices, %d triangles "
             "(integrate %.2f s, extract %.2f s)", fuser.n_views, fuser.n_fused, fuser.n_valid_pixels,
             fuser.n_blocks, len(mesh.vertices), len(mesh.triangles), t1 - t0,
             time.perf_counter() - t1)
    return mesh


__all__ = ["TSDFConfig", "open3d_device", "canonical_order", "TSDFFuser", "fuse_views", "clean_mesh", "write_mesh", "open3d_intrinsics",
           "OPEN3D_PIXEL_SHIFT"]
