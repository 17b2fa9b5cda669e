"""Plane anchors: where each image's own plane cues put its weak-texture surfaces, per image.

`geocues extract` cuts the weak-texture regions of every image with a plane (from the aligned depth
prior, or prior-free from the line and SfM cues that pin it) and keeps the points that the other
images confirm (geocues.plane_merge). Before those points are merged into voxels, each one is still
known to lie on a ray of the image that made it, so that image certainly sees it: nothing stands
between its camera and the point. ``CUES/plane_anchors.npz`` keeps them, image by image, and the
trainer projects an image's points into its own view only (no visibility guess) to anchor that
view's rendered depth where the depth prior has none -- or where there is no prior at all
(`splat train --loss.plane-anchor`, splat/views.py). Points are stored in world coordinates, so a
view at any training resolution gets its anchor map by projection (:func:`anchor_depth`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

PLANE_ANCHORS_FILE = "plane_anchors.npz"


@dataclass
class PlaneAnchors:
    """The kept plane points of every image: ``xyz`` [M, 3] world (float32), ``normal`` [M, 3] their
    plane's unit normal, ``view`` [M] the index into ``names`` of the image whose plane put the point
    there."""

    names: list[str]
    xyz: np.ndarray
    normal: np.ndarray
    view: np.ndarray

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, np.float32).reshape(-1, 3)
        self.normal = np.asarray(self.normal, np.float32).reshape(-1, 3)
        self.view = np.asarray(self.view, np.int64).reshape(-1)
        if not len(self.view) == len(self.xyz) == len(self.normal):
            raise ValueError(f"plane anchors: {len(self.xyz)} points, {len(self.normal)} normals and "
                             f"{len(self.view)} view indices")
        if len(self.view) and not (0 <= self.view.min() and self.view.max() < len(self.names)):
            raise ValueError(f"plane anchors: view index outside 0..{len(self.names) - 1}")
        order = np.argsort(self.view, kind="stable")
        self.xyz, self.normal, self.view = self.xyz[order], self.normal[order], self.view[order]
        self._start = np.searchsorted(self.view, np.arange(len(self.names) + 1))
        self._index = {n: i for i, n in enumerate(self.names)}

    def of(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """([m, 3] world points, [m, 3] their normals) of image ``name`` (empty if it has none)."""
        i = self._index.get(name)
        if i is None:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
        sl = slice(self._start[i], self._start[i + 1])
        return self.xyz[sl], self.normal[sl]

    def of_views(self, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """The points and normals of every image in ``names`` (those it has), in one array each."""
        keep = np.isin(np.asarray(self.names, dtype=object)[self.view], np.asarray(list(names), dtype=object))
        return self.xyz[keep], self.normal[keep]

    def counts(self) -> dict[str, int]:
        return {n: int(self._start[i + 1] - self._start[i]) for i, n in enumerate(self.names)}


def write_plane_anchors(out_dir: str | Path, names: list[str], xyz: np.ndarray, normal: np.ndarray,
                        view: np.ndarray) -> Path:
    """Write ``OUT/plane_anchors.npz`` atomically."""
    from geocues.atomic import atomic_path

    pa = PlaneAnchors(list(names), xyz, normal, view)
    path = Path(out_dir) / PLANE_ANCHORS_FILE
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, names=np.array(pa.names, dtype=str), xyz=pa.xyz, normal=pa.normal,
                            view=pa.view.astype(np.int32))
    return path


def plane_anchors_path(cues: str | Path) -> Path:
    """Where the plane anchors of a `geocues extract` folder are (``cues``: the folder or a file in it)."""
    folder = Path(cues)
    return (folder if folder.is_dir() else folder.parent) / PLANE_ANCHORS_FILE


def load_plane_anchors(cues: str | Path) -> PlaneAnchors:
    """The plane anchors of a `geocues extract` folder (``cues`` is the folder or a file in it).
    FileNotFoundError, naming the fix, for cue folders written before the file existed."""
    path = plane_anchors_path(cues)
    if not path.is_file():
        raise FileNotFoundError(f"{path.parent} has no {PLANE_ANCHORS_FILE} (written by `geocues extract` since "
                                f"plane anchors exist): run `geocues extract` again into a new folder")
    with np.load(path) as z:
        return PlaneAnchors([str(n) for n in z["names"]], z["xyz"], z["normal"], z["view"])


def _pixels(xyz: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, height: int, width: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixel rule of the anchors: a point falls in the COLMAP pixel that contains its projection
    (pixel (i, j) covers [j, j+1) x [i, i+1)). Returns, for the finite points of ``xyz`` [m, 3]
    (world, float64) in front of the camera ``x_cam = R X + t`` that fall inside the image: their
    indices into ``xyz``, camera-frame coordinates [k, 3], columns [k] and rows [k] (floats)."""
    idx = np.flatnonzero(np.isfinite(xyz).all(1))
    with np.errstate(over="ignore", invalid="ignore"):  # huge coordinates: dropped by the tests below
        # (R @ X^T)^T: the same products as X @ R^T, through BLAS (5x faster for a million points)
        Xc = (R @ xyz[idx].T).T + np.asarray(t, np.float64)
        z = Xc[:, 2]
        front = z > 1e-6
        idx, Xc, z = idx[front], Xc[front], z[front]
        uv = Xc @ K.T
        col = np.floor(uv[:, 0] / z)
        row = np.floor(uv[:, 1] / z)
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height) & np.isfinite(z)
    return idx[inside], Xc[inside], col[inside], row[inside]


def anchor_depth(xyz: np.ndarray, normal: np.ndarray | None, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                 height: int, width: int, min_cos: float = 0.1) -> np.ndarray:
    """[H, W] float32 z-depth, in each pixel of the camera ``x_cam = R X + t`` with intrinsics ``K``,
    of the nearest point of ``xyz`` [m, 3] (world) that falls in it (:func:`_pixels`); 0 where none
    falls. With ``normal`` [m, 3] (the point's plane), the depth is the plane's on the ray
    through the pixel's centre, not the point's own: at a coarse training resolution a slanted floor's
    depth changes by centimetres within a pixel (rays within ``min_cos`` of grazing keep the point's)."""
    out = np.zeros((height, width), np.float32)
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    R, K = np.asarray(R, np.float64), np.asarray(K, np.float64)
    idx, Xc, col, row = _pixels(xyz, K, R, t, height, width)
    if len(idx) == 0:
        return out
    z = Xc[:, 2]
    if normal is not None:
        n = np.nan_to_num(np.asarray(normal, np.float64).reshape(-1, 3)[idx]) @ R.T  # camera frame; NaN: no plane
        ray = np.stack([col + 0.5, row + 0.5, np.ones_like(z)], 1) @ np.linalg.inv(K).T  # z = 1
        num, den = np.sum(n * Xc, 1), np.sum(n * ray, 1)
        grazing = np.abs(den) <= min_cos * np.linalg.norm(ray, axis=1) * np.linalg.norm(n, axis=1)
        z = np.where(grazing, z, num / np.where(grazing, 1.0, den))  # a zero normal is "grazing"
        z = np.where(z > 1e-6, z, Xc[:, 2])
    flat = row.astype(np.int64) * width + col.astype(np.int64)
    zbuf = np.full(height * width, np.inf)
    np.minimum.at(zbuf, flat, z)
    hit = np.isfinite(zbuf)
    out.reshape(-1)[hit] = zbuf[hit]
    return out


def anchor_normals(xyz: np.ndarray, normal: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                   height: int, width: int) -> np.ndarray:
    """[H, W, 3] float32 unit normals in the camera frame ``x_cam = R X + t``, turned to face the
    camera: in each pixel, the plane normal of the nearest point of ``xyz`` [m, 3] (world) that falls
    in it (:func:`_pixels`); zeros (a normal prior's "invalid") where none falls or the point's
    normal is zero or not finite."""
    out = np.zeros((height, width, 3), np.float32)
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    normal = np.asarray(normal, np.float64).reshape(-1, 3)
    if len(normal) != len(xyz):
        raise ValueError(f"anchor_normals: {len(xyz)} points but {len(normal)} normals")
    R = np.asarray(R, np.float64)
    idx, Xc, col, row = _pixels(xyz, np.asarray(K, np.float64), R, t, height, width)
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite normals are dropped below
        n = normal[idx] @ R.T
        norm = np.linalg.norm(n, axis=1)
    keep = np.isfinite(n).all(1) & (norm > 1e-6)
    if not keep.any():
        return out
    flat = row[keep].astype(np.int64) * width + col[keep].astype(np.int64)
    n, z, Xc = n[keep] / norm[keep, None], Xc[keep, 2], Xc[keep]
    n = np.where(np.sum(n * Xc, 1, keepdims=True) > 0, -n, n)  # face the camera
    order = np.lexsort((z, flat))  # by pixel, nearest first
    first = order[np.unique(flat[order], return_index=True)[1]]
    out.reshape(-1, 3)[flat[first]] = n[first]
    return out
