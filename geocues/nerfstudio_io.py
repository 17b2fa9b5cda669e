"""nerfstudio ``transforms.json`` scenes, read (and written) at the project boundary.

The format (docs.nerf.studio, "Data conventions"; what ``ns-process-data`` writes)::

    {"camera_model": "OPENCV", "fl_x": .., "fl_y": .., "cx": .., "cy": .., "w": .., "h": ..,
     "k1": 0, "k2": 0, "p1": 0, "p2": 0,               # intrinsics: top level, or per frame (wins)
     "frames": [{"file_path": "images/0001.png",        # relative to the file's folder
                 "transform_matrix": [[...4x4...]],    # camera-to-world, OpenGL camera axes
                 "depth_file_path": "depth/0001.png"}, ...],   # optional
     "ply_file_path": "sparse_pc.ply",                  # optional points (x y z, red green blue)
     "applied_transform": [[...3x4...]]}                # optional: what ns-process-data did to the
                                                        # COLMAP world
Conversions, each once and here:

- camera axes: OpenGL (x right, y up, z back) -> OpenCV (x right, y down, z forward), by negating
  the second and third columns of the camera-to-world rotation; then world-to-camera R = Rc2w^T,
  t = -R c.
- ``applied_transform`` (ns-process-data swaps the COLMAP world's y and z) is undone, for the poses
  and the points alike, so a scene converted from COLMAP keeps the COLMAP world (and its gt/mesh.ply).
- pixel centres: nerfstudio's cx, cy are COLMAP's (ns-process-data copies them; its rays go through
  pixel centres at +0.5), so K is taken as it is.

Only pinhole cameras are read: a camera_model other than PINHOLE / SIMPLE_PINHOLE / OPENCV /
SIMPLE_RADIAL / RADIAL, or any non-zero distortion coefficient, is refused naming the frame and field.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geocues.colmap_io import RawImage, RawPoints

log = logging.getLogger(__name__)

INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
PINHOLE_LIKE = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL")
GL_TO_CV = np.diag([1.0, -1.0, -1.0])  # camera axes, both ways (x right; y, z flipped)
# ns-process-data's world change (keep_original_world_coordinate=False): x, z, -y
NS_APPLIED_TRANSFORM = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0]])


@dataclass
class TransformsScene:
    """What a transforms.json holds, in the project's conventions (world-to-camera OpenCV)."""

    path: Path  # the transforms.json
    images: list[RawImage]  # sorted by name; name = file_path relative to images/ (or to the folder)
    image_paths: list[Path]  # [len(images)] the image files
    points: RawPoints  # from ply_file_path (no tracks), or empty
    depth_paths: dict[str, Path] = field(default_factory=dict)  # image name -> depth_file_path
    sources: list[Path] = field(default_factory=list)  # every file read (for cache keys)


def find_transforms(root: Path) -> Path | None:
    """``root`` itself if it is a .json file, else ``root/transforms.json`` if it exists."""
    root = Path(root)
    if root.is_file() and root.suffix == ".json":
        return root
    cand = root / "transforms.json"
    return cand if cand.is_file() else None


def _number(path: Path, where: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ValueError(f"{path}: {where} has '{key}' = {value!r}, expected a finite number")
    return float(value)


def _name_for(folder: Path, file_path: str) -> tuple[str, Path]:
    """(name, path) of a frame's image: the name is relative to ``folder/images`` when the file is
    inside it (as in a COLMAP scene), else to ``folder``."""
    path = Path(os.path.normpath(folder / file_path))
    for base in (folder / "images", folder):
        try:
            return path.relative_to(Path(os.path.normpath(base))).as_posix(), path
        except ValueError:
            continue
    return path.as_posix(), path  # an absolute path outside the folder


def _pose(path: Path, where: str, m) -> tuple[np.ndarray, np.ndarray]:
    """transform_matrix (camera-to-world, OpenGL camera axes) -> world-to-camera OpenCV (R, t)."""
    try:
        T = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {where}: 'transform_matrix' is not a matrix of numbers") from None
    if T.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"{path}: {where} has a 'transform_matrix' of shape {T.shape}, expected 4x4")
    if not np.isfinite(T).all():
        row, col = np.argwhere(~np.isfinite(T))[0]
        raise ValueError(f"{path}: {where} has a non-finite 'transform_matrix' (row {row}, column {col}: "
                         f"{T[row, col]})")
    if T.shape == (4, 4) and not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise ValueError(f"{path}: {where}: the last row of 'transform_matrix' is {T[3].tolist()}, "
                         f"not [0, 0, 0, 1]")
    Rc2w = T[:3, :3] @ GL_TO_CV  # OpenGL camera axes -> OpenCV, once, here
    if not np.allclose(Rc2w.T @ Rc2w, np.eye(3), atol=1e-5) or np.linalg.det(Rc2w) < 0:
        raise ValueError(f"{path}: {where}: 'transform_matrix' is not a rotation and a translation "
                         f"(scaled or mirrored camera axes)")
    R = Rc2w.T
    return R, -R @ T[:3, 3]


def read_transforms(path: str | Path) -> TransformsScene:
    """Read a nerfstudio transforms.json. Raises ValueError / FileNotFoundError naming the file,
    the frame and the field."""
    path = Path(path)
    folder = path.parent
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read {path} ({exc})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object with 'frames', got {type(meta).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path}: no 'frames' (a list of {{file_path, transform_matrix}})")
    A = meta.get("applied_transform")
    undo = np.eye(4)
    if A is not None:
        try:
            A4 = np.vstack([np.asarray(A, np.float64).reshape(3, 4), [0, 0, 0, 1]])
        except (TypeError, ValueError):
            A4 = np.full((4, 4), np.nan)
        if not np.isfinite(A4).all() or not np.allclose(A4[:3, :3] @ A4[:3, :3].T, np.eye(3), atol=1e-6):
            raise ValueError(f"{path}: 'applied_transform' must be a 3x4 rotation and translation, got {A!r}")
        undo = np.linalg.inv(A4)  # back to the COLMAP world
    images, paths, depth, sources = [], [], {}, [path]
    for k, fr in enumerate(frames):
        if not isinstance(fr, dict) or "file_path" not in fr:
            raise ValueError(f"{path}: frame {k} has no 'file_path'")
        where = f"frame {k} ({fr['file_path']})"
        if "transform_matrix" not in fr:
            raise ValueError(f"{path}: {where} has no 'transform_matrix'")

        def get(key, default=None):
            if key in fr:
                return fr[key]
            if key in meta:
                return meta[key]
            if default is not None:
                return default
            if "camera_angle_x" in meta or "camera_angle_x" in fr:  # the Blender / instant-ngp synthetic format
                raise ValueError(f"{path} is a Blender / instant-ngp transforms.json (camera_angle_x), which is not "
                                 "read: give nerfstudio's intrinsics fl_x = fl_y = w / (2 tan(camera_angle_x / 2)), "
                                 "cx = w / 2, cy = h / 2, w, h (pixels) and file_path with its extension")
            raise ValueError(f"{path}: {where} has no '{key}' (and the file has none at its top level)")

        fx, fy, cx, cy, w, h = (_number(path, where, key, get(key)) for key in INTRINSICS)
        model = get("camera_model", "PINHOLE")
        if model not in PINHOLE_LIKE:
            raise ValueError(f"{path}: {where} has camera_model {model!r}; only pinhole cameras are read "
                             f"({', '.join(PINHOLE_LIKE)} without distortion)")
        for key in DISTORTION:
            if _number(path, where, key, get(key, 0.0)) != 0.0:
                raise ValueError(f"{path}: {where} has lens distortion ('{key}' = {get(key)}); undistort the "
                                 f"images first (e.g. COLMAP's image_undistorter) and write a pinhole transforms.json")
        if w != int(w) or h != int(h) or w < 1 or h < 1 or fx <= 0 or fy <= 0:
            raise ValueError(f"{path}: {where} has w={w}, h={h}, fl_x={fx}, fl_y={fy}: expected positive "
                             f"integer sizes and focal lengths")
        R, t = _pose(path, where, fr["transform_matrix"])
        if A is not None:  # undo the world change: X_colmap = undo (X_ns); c2w' = undo c2w
            Ru, tu = undo[:3, :3], undo[:3, 3]
            c = Ru @ (-R.T @ t) + tu
            R = R @ Ru.T
            t = -R @ c
        name, img = _name_for(folder, str(fr["file_path"]))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        images.append(RawImage(int(fr.get("colmap_im_id", k + 1)), k + 1, name, "PINHOLE", int(w), int(h), K, R, t))
        paths.append(img)
        sources.append(img)
        if fr.get("depth_file_path"):
            dp = Path(os.path.normpath(folder / str(fr["depth_file_path"])))
            if not dp.is_file():
                raise FileNotFoundError(f"{path}: {where}: its depth_file_path is missing on disk: {dp}")
            depth[name] = dp
            sources.append(dp)
    names = [im.name for im in images]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"{path}: frames share an image: {', '.join(dup[:3])}")
    if len({im.image_id for im in images}) != len(images):  # colmap_im_id missing on some frames
        for k, im in enumerate(images):
            im.image_id = k + 1
    order = np.argsort(names, kind="stable")
    points = RawPoints.empty()
    if meta.get("ply_file_path"):
        ply = Path(os.path.normpath(folder / str(meta["ply_file_path"])))
        if not ply.is_file():
            raise FileNotFoundError(f"{path}: its ply_file_path is missing on disk: {ply}")
        points = _read_points(ply, undo)
        sources.append(ply)
    log.info("transforms.json %s: %d frames, %d points%s", path, len(images), len(points.ids),
             ", applied_transform undone" if A is not None else "")
    return TransformsScene(path, [images[i] for i in order], [paths[i] for i in order], points, depth, sources)


def _read_points(ply: Path, undo: np.ndarray) -> RawPoints:
    """Points of ``ply`` (x y z, red green blue) brought back to the COLMAP world; no tracks."""
    from geocues.cue_io import read_cues_ply

    cloud = read_cues_ply(ply)
    xyz = cloud.xyz @ undo[:3, :3].T + undo[:3, 3]
    n = len(xyz)
    return RawPoints(np.arange(1, n + 1, dtype=np.int64), xyz, cloud.rgb, np.zeros(n), np.zeros(n, np.int32),
                     [np.zeros(0, np.int64)] * n)


def write_transforms(path: str | Path, images: list[RawImage], image_paths: list[Path],
                     points: RawPoints | None = None, applied_transform: bool = True) -> Path:
    """Write a transforms.json as ns-process-data does for a pinhole COLMAP model: camera_model
    OPENCV with zero distortion, intrinsics at the top level when all images share them (per frame
    otherwise), camera-to-world in OpenGL axes, and with ``applied_transform`` nerfstudio's world
    change applied to poses and points (recorded in the file). Points go to ``sparse_pc.ply``."""
    from plyfile import PlyData, PlyElement

    from geocues.atomic import atomic_path

    path = Path(path)
    A = np.vstack([NS_APPLIED_TRANSFORM, [0, 0, 0, 1]]) if applied_transform else np.eye(4)
    intr = [{"fl_x": float(im.K[0, 0]), "fl_y": float(im.K[1, 1]), "cx": float(im.K[0, 2]),
             "cy": float(im.K[1, 2]), "w": int(im.width), "h": int(im.height)} for im in images]
    shared = all(d == intr[0] for d in intr)
    out: dict = {"camera_model": "OPENCV", **(intr[0] if shared else {}), "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    frames = []
    for im, img, d in zip(images, image_paths, intr):
        c2w = np.eye(4)
        c2w[:3, :3] = im.R.T @ GL_TO_CV  # OpenCV -> OpenGL camera axes
        c2w[:3, 3] = -im.R.T @ im.t
        fr = {"file_path": Path(os.path.relpath(img, path.parent)).as_posix(), "transform_matrix": (A @ c2w).tolist(),
              "colmap_im_id": int(im.image_id)}
        frames.append(fr if shared else {**fr, **d})
    out["frames"] = frames
    if applied_transform:
        out["applied_transform"] = NS_APPLIED_TRANSFORM.tolist()
    if points is not None and len(points.ids):
        xyz = points.xyz @ A[:3, :3].T + A[:3, 3]
        v = np.empty(len(xyz), [("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
        for k, axis in enumerate("xyz"):
            v[axis] = xyz[:, k]
        for k, ch in enumerate(("red", "green", "blue")):
            v[ch] = points.rgb[:, k]
        with atomic_path(path.parent / "sparse_pc.ply") as tmp:
            PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp))
        out["ply_file_path"] = "sparse_pc.ply"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(out, indent=2))
    return path


def write_colmap_model(transforms: str | Path, model_dir: str | Path) -> Path:
    """The cameras (PINHOLE, one per frame) and points of a transforms.json as a COLMAP text model in
    ``model_dir``: what the commands that work on a COLMAP model (`geocues sfm`, `rescale`, and the scene
    folders `mvs` and `simulate-priors` write) take from a nerfstudio scene. Its images must lie in
    the scene's images/ folder (their names are relative to it)."""
    from geocues.colmap_io import write_model

    ns = read_transforms(transforms)
    images_dir = Path(os.path.normpath(Path(ns.path).parent / "images"))
    outside = [p for p in ns.image_paths if not Path(p).is_relative_to(images_dir)]
    if outside:
        raise ValueError(f"{ns.path}: {len(outside)} frames' images lie outside {images_dir} (e.g. {outside[0]}): "
                         "move them into images/ to use this scene with the commands that take a COLMAP model")
    return write_model(Path(model_dir), ns.images, ns.points if len(ns.points.ids) else None)


def transforms_reconstruction(transforms: str | Path):
    """pycolmap's Reconstruction of a transforms.json's cameras (:func:`write_colmap_model` into a
    temporary folder, removed again)."""
    import tempfile

    from geocues.colmap_io import load_reconstruction

    with tempfile.TemporaryDirectory(prefix="indoorgs_ns_model_") as tmp:
        return load_reconstruction(write_colmap_model(transforms, Path(tmp) / "0"))
