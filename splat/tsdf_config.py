"""TSDF fusion and mesh-cleaning options (``--tsdf.*`` of `splat train` and `splat mesh`): the
dataclass :class:`TSDFConfig` and the device spelling Open3D takes (splat/mesh.py fuses with them)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class TSDFConfig:
    """TSDF fusion and mesh cleaning (Open3D VoxelBlockGrid, marching cubes, pymeshlab)."""

    voxel_size: float = 0.02
    """voxel edge in metres; at 2 cm exact depth meshes to within 1 mm, 1 cm costs 2.5x the time and 4x the triangles (docs/meshing.md)."""
    sdf_trunc: float | None = None
    """truncation distance of the signed distance in metres; None = 4 x voxel_size."""
    depth_max: float = 10.0
    """depths beyond this (metres) are ignored; rooms are under 10 m across."""
    weight_threshold: float = 3.0
    """marching cubes keeps voxels seen by more than this many views (Open3D's default); lowered to n - 1 when only n <= it views had valid depth (then a voxel must be seen by every one of them: near n the mesh is empty unless the views all overlap)."""
    block_count: int = 1000
    """initial capacity of the block hash map (16^3 voxels, 80 kB each, allocated up front); it grows as needed."""
    device: str = "cpu"
    """device of the voxel grid, spelled as everywhere in the toolkit: "cpu", "cuda" or "cuda:N"
    ("cuda" needs a CUDA build of Open3D; Open3D's own "CPU:0" / "CUDA:0" are accepted too)."""
    min_component_diag: float = 0.05
    """clean_mesh removes connected components whose bounding-box diagonal is below this fraction of the whole mesh's (0 keeps all)."""
    depth: str = "expected"
    """rendered depth fused for a trained model: "expected" (the alpha-normalised blend of the
    Gaussians' depth planes) or "median" (where transmittance crosses 0.5, RaDe-GS's meshing depth:
    a step from one Gaussian's plane to the next, so its meshes' normals are rougher — normal
    consistency 0.06-0.13 lower on every row of the textured-room ablation, docs/meshing.md).
    Exact depth (the floor) is fused as it is."""

    consistent_views: int | None = None
    """fuse a rendered-depth pixel only where at least this many of its ``consistency_neighbours``
    neighbouring views render a depth that agrees with it (forward-backward reprojection within
    ``consistency_px`` pixels and ``consistency_rel_depth``, the check of MVS fusion; an extension);
    None fuses every pixel. Exact depth (the floor) is never filtered."""
    max_depth_spread: float | None = None
    """fuse a rendered pixel only where its expected and median depths differ by at most this
    fraction of the depth (an extension): where they part ways the pixel mixes surfaces — an object's
    silhouette over the wall behind it, a floater — and its blended depth lies between them (the
    halos in front of ICL's chair). None fuses every pixel with alpha > 0.5."""
    consistency_neighbours: int = 4
    """views compared with each fused view (chosen as `geocues mvs` chooses them) when ``consistent_views`` is set."""
    consistency_px: float = 1.0
    """forward-backward reprojection tolerance in pixels of the rendered views."""
    consistency_rel_depth: float = 0.01
    """forward-backward depth tolerance relative to the depth."""
    smooth_iters: int = 0
    """Taubin smoothing steps clean_mesh applies last, to trained meshes and the floor alike (an
    extension; 0 = off): λ 0.5, μ -0.51, a low-pass filter with pass-band 0.04 that does not shrink
    the mesh. It flattens the bumps a few voxels wide that the Gaussians' depth planes leave in the
    fused surface; 30 steps measured on the seed-0 rooms (docs/meshing.md)."""

    @property
    def trunc(self) -> float:
        """The truncation distance in metres (``sdf_trunc`` or 4 voxels)."""
        return 4.0 * self.voxel_size if self.sdf_trunc is None else float(self.sdf_trunc)

    def validate(self) -> None:
        """Raise ValueError on an impossible setting, naming the option as `splat train` / `splat mesh` spell it."""
        for name in ("voxel_size", "sdf_trunc", "depth_max", "weight_threshold", "consistency_px",
                     "consistency_rel_depth", "max_depth_spread", "min_component_diag"):
            value = getattr(self, name)
            if value is not None and not math.isfinite(value):  # inf voxels: an empty mesh; a NaN weight a false surface
                raise ValueError(f"--tsdf.{name.replace('_', '-')} must be a finite number, got {value}")
        if not self.voxel_size > 0:
            raise ValueError(f"--tsdf.voxel-size must be positive, got {self.voxel_size}")
        if not self.trunc >= 2.0 * self.voxel_size:
            raise ValueError(f"--tsdf.sdf-trunc ({self.trunc} m) must be at least 2 voxels "
                             f"(2 x {self.voxel_size} m) for marching cubes to find the zero crossing")
        if not self.depth_max > 0:
            raise ValueError(f"--tsdf.depth-max must be positive, got {self.depth_max}")
        if self.weight_threshold < 0:
            raise ValueError(f"--tsdf.weight-threshold must be >= 0, got {self.weight_threshold}")
        if self.block_count < 1:
            raise ValueError(f"--tsdf.block-count must be >= 1, got {self.block_count}")
        open3d_device(self.device)
        if self.depth not in ("median", "expected"):
            raise ValueError(f"--tsdf.depth must be 'median' or 'expected', got {self.depth!r}")
        if self.consistent_views is not None and not 1 <= self.consistent_views <= self.consistency_neighbours:
            raise ValueError(f"--tsdf.consistent-views must be in 1..{self.consistency_neighbours} "
                             f"(--tsdf.consistency-neighbours) or unset, got {self.consistent_views}")
        if self.max_depth_spread is not None and not self.max_depth_spread > 0:
            raise ValueError(f"--tsdf.max-depth-spread must be positive or unset, got {self.max_depth_spread}")
        if not (self.consistency_px > 0 and self.consistency_rel_depth > 0):
            raise ValueError(f"--tsdf.consistency-px and --tsdf.consistency-rel-depth must be positive, got "
                             f"{self.consistency_px}, {self.consistency_rel_depth}")
        if not 0.0 <= self.min_component_diag < 1.0:
            raise ValueError(f"--tsdf.min-component-diag must be in [0, 1), got {self.min_component_diag}")
        if self.smooth_iters < 0:
            raise ValueError(f"--tsdf.smooth-iters must be >= 0, got {self.smooth_iters}")


BLOCK_BYTES = 80_000  # one 16^3 block of the voxel grid (TSDF, weight, colour), allocated up front


def check_tsdf_resources(cfg: TSDFConfig) -> None:
    """Raise ValueError before any work when fusion cannot run here: ``--tsdf.device cuda`` on an
    Open3D built without CUDA, or a ``--tsdf.block-count`` that allocates more than the machine's
    memory up front (both were tracebacks from Open3D after the work before them was done)."""
    import os

    if cfg.device.lower().startswith("cuda"):
        import open3d as o3d

        if not o3d.core.cuda.is_available():
            raise ValueError(f"--tsdf.device {cfg.device}: this Open3D build has no CUDA device; "
                             "fuse on the CPU (--tsdf.device cpu, the default)")
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not on this platform: nothing to compare with
        return
    if cfg.block_count * BLOCK_BYTES > memory:
        raise ValueError(f"--tsdf.block-count {cfg.block_count} allocates {cfg.block_count * BLOCK_BYTES / 1e9:.0f} GB "
                         f"up front; this machine has {memory / 1e9:.0f} GB (the grid grows as needed from the "
                         "default 1000)")


def open3d_device(name: str) -> str:
    """The toolkit's device spelling ("cpu", "cuda", "cuda:1") as Open3D's ("CPU:0", "CUDA:1")."""
    kind, _, index = name.strip().lower().partition(":")
    if kind not in ("cpu", "cuda") or (index and not index.isdigit()):
        raise ValueError(f"--tsdf.device must be cpu, cuda or cuda:N, got {name!r}")
    return f"{kind.upper()}:{index or 0}"
