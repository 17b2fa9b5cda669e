"""COLMAP model I/O at the project boundary.

Everything that touches pycolmap's conventions lives here: pycolmap's ``Rotation3d.quat`` is
``xyzw`` and the project uses ``wxyz``; ``image.cam_from_world()`` is a method in pycolmap 4.2.
Readers go through pycolmap (binary or text); the writer emits COLMAP's text format (simple, exact,
diffable) and can convert it to binary with pycolmap.
"""

from __future__ import annotations

import json
import logging
import shlex
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geocues.atomic import atomic_dir

log = logging.getLogger(__name__)

# Camera models read as they are; every other model has distortion and must be undistorted first.
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
# Models that are a pinhole when every distortion parameter is 0 (dataset converters often write
# OPENCV with zeros); the fisheye models are not: their projection differs even then.
ZERO_DISTORTION_PINHOLES = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def camera_distortion(cam) -> tuple[float, ...]:
    """A pycolmap camera's extra (distortion) parameters: k1, k2, p1, p2, ... (() for a pinhole)."""
    return tuple(float(cam.params[i]) for i in cam.extra_params_idxs())


def is_pinhole(model: str, distortion) -> bool:
    """True when a camera of COLMAP ``model`` with these extra (distortion) parameters projects as a
    pinhole: PINHOLE / SIMPLE_PINHOLE, or a radial / OpenCV model whose distortion is exactly 0."""
    return model in PINHOLE_MODELS or (model in ZERO_DISTORTION_PINHOLES and not np.any(np.asarray(distortion)))


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """pycolmap ``Rotation3d.quat`` (x, y, z, w) -> project convention (w, x, y, z)."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def quat_wxyz_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> 3x3 rotation matrix."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


@dataclass
class RawImage:
    """One registered image as stored in the model (before any downscaling)."""

    image_id: int
    camera_id: int
    name: str
    model: str  # COLMAP camera model name, e.g. "PINHOLE"
    width: int
    height: int
    K: np.ndarray  # [3, 3] intrinsics, COLMAP pixel convention
    R: np.ndarray  # [3, 3] world-to-camera rotation
    t: np.ndarray  # [3] world-to-camera translation
    distortion: tuple[float, ...] = ()  # the model's extra parameters (k1, k2, p1, p2, ...); () for a pinhole

    @property
    def pinhole(self) -> bool:
        """Projects as a pinhole with ``K`` (:func:`is_pinhole`)."""
        return is_pinhole(self.model, self.distortion)


@dataclass
class RawPoints:
    """3D points of a model with their tracks."""

    ids: np.ndarray  # [N] int64 COLMAP point3D ids
    xyz: np.ndarray  # [N, 3] float64, metres
    rgb: np.ndarray  # [N, 3] uint8
    error: np.ndarray  # [N] float64 mean reprojection error, pixels
    track_length: np.ndarray  # [N] int32
    track_image_ids: list[np.ndarray]  # N arrays of the image ids observing each point

    @staticmethod
    def empty() -> "RawPoints":
        return RawPoints(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                         np.zeros(0), np.zeros(0, np.int32), [])


def find_model_dir(scene_or_model: Path) -> Path:
    """Return the folder holding cameras/images/points3D for ``SCENE`` (``sparse/0``, ``sparse``) or
    for a model folder given directly. Raises FileNotFoundError naming the folder otherwise."""
    p = Path(scene_or_model)
    if not p.exists():
        raise FileNotFoundError(f"scene folder does not exist: {p}")
    if not p.is_dir():
        raise ValueError(f"{p} is a file; a scene is a folder (images/ and sparse/0/ with a COLMAP model)")
    for cand in (p / "sparse" / "0", p / "sparse", p):
        if any((cand / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return cand
    raise FileNotFoundError(f"no cameras.txt or cameras.bin in {p}, {p / 'sparse'} or {p / 'sparse' / '0'}"
                            + _no_model_hint(p))


def _unfinished_sfm_hint(p: Path) -> str:
    """What a `geocues sfm -o p` that wrote no model left: a failure (its reason) or a stop (the
    command to run again, and whether that reuses the features)."""
    try:
        state = json.loads((p / "cache" / "sfm" / "state.json").read_text())
    except (OSError, ValueError):
        state = {}
    if state.get("failed"):
        return f"; the `geocues sfm` run that wrote {p} failed: {state['failed']}"
    scene = shlex.quote(state["scene"]) if state.get("scene") else "SCENE"
    flags = "".join(f" {f}" for f in state.get("flags", []))
    done = ("it reuses the features and matches" if state.get("match") else "it reuses the features"
            if state.get("extract") else "it starts again (it was stopped while extracting features)")
    return (f"; {p} holds an unfinished `geocues sfm {scene} -o {shlex.quote(str(p))}{flags}` (stopped before it "
            f"wrote the model): run that command again, {done}")


def _no_model_hint(p: Path) -> str:
    """What the user most likely meant when SCENE holds no COLMAP model."""
    from geocues.photos import is_image, list_images

    others = sorted(d for d in (p / "sparse").glob("*") if any(d.glob("cameras.*"))) if (p / "sparse").is_dir() else []
    if others:
        return f"; {others[0]} holds a model: move (or link) it to {p / 'sparse' / '0'}"
    if (p / "cache" / "sfm").is_dir() and not (p / "sfm_report.json").is_file():
        return _unfinished_sfm_hint(p)
    if p.name == "images" and any(is_image(f) for f in p.iterdir()):
        return f"; {p} looks like a scene's images folder: pass the scene folder above it, {p.parent}"
    if (p / "cues.ply").is_file():
        return (f"; {p} is a cue folder (cues.ply from `geocues extract`): a command takes it with -c/--cues, "
                "and the scene folder (images/ and its COLMAP model) as SCENE")
    if (p / "cfg_args").is_file() or (p / "point_cloud").is_dir():
        return (f"; {p} is a training run (`splat train -o`): `splat render`, `splat view`, `splat mesh` and "
                "`evaluate report` take it as RUN; SCENE is the folder it was trained on")
    if (p / "images").is_dir() and list_images(p / "images"):
        return (f"; {p / 'images'} holds photos without a model: `geocues sfm {shlex.quote(str(p))} -o MAP` makes one from the "
                "images alone (README, \"Your own photos\")")
    return ""


def _check_text_model(model_dir: Path) -> None:
    """The mistakes of hand-written or converted text models that pycolmap reports without naming the
    file or the line: an image line without its (possibly empty) line of 2D points after it, an image
    whose camera id cameras.txt lacks."""
    cams, imgs = model_dir / "cameras.txt", model_dir / "images.txt"
    if not (cams.is_file() and imgs.is_file()):
        return
    camera_lines = [(k + 1, ln.split()) for k, ln in enumerate(cams.read_text(errors="replace").splitlines())
                    if ln.strip() and not ln.lstrip().startswith("#")]
    for n, fields in camera_lines:
        _check_camera_line(cams, n, fields)
    camera_ids = {fields[0] for _, fields in camera_lines}
    lines = [(k + 1, ln) for k, ln in enumerate(imgs.read_text(errors="replace").splitlines())
             if not ln.lstrip().startswith("#")]
    while lines and not lines[-1][1].strip():  # trailing empty lines: the last image's empty 2D points and blanks
        lines.pop()
    for (n, line), (n_next, following) in zip(lines[0::2], lines[1::2] + [(0, "")]):
        fields = line.split()
        if len(fields) < 10:
            raise ValueError(f"{imgs}: line {n} should be an image (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME), "
                             f"got {line.strip()[:80]!r}; every image takes two lines, the second its 2D points "
                             "(an empty line when it has none)")
        if fields[8] not in camera_ids:
            raise ValueError(f"{imgs}: line {n}: image {fields[9]} uses camera {fields[8]}, which {cams} does not list")
        nxt = following.split()
        if len(nxt) >= 10 and len(nxt) % 3 != 0:  # an image line where its 2D points should be
            raise ValueError(f"{imgs}: line {n_next} looks like another image, where the 2D points of image "
                             f"{fields[9]} (line {n}) belong; every image takes two lines, the second empty "
                             "when it has no points")


def _check_camera_line(path: Path, n: int, fields: list[str]) -> None:
    """CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]: the parameter count the model takes (pycolmap's own check
    said only "Check failed: camera.VerifyParams()")."""
    import pycolmap

    if len(fields) < 4:
        raise ValueError(f"{path}: line {n} should be a camera (CAMERA_ID MODEL WIDTH HEIGHT PARAMS...), got "
                         f"{' '.join(fields)[:80]!r}")
    try:
        info = pycolmap.Camera.create_from_model_name(1, fields[1], 1.0, 1, 1).params_info
    except (ValueError, RuntimeError):
        raise ValueError(f"{path}: line {n}: camera {fields[0]} has an unknown model {fields[1]!r}") from None
    names = [s.strip() for s in info.split(",")]
    if len(fields) - 4 != len(names):
        raise ValueError(f"{path}: line {n}: camera {fields[0]} ({fields[1]}) takes {len(names)} parameters "
                         f"({' '.join(names)}), got {len(fields) - 4}")


def load_reconstruction(model_dir: Path):
    """pycolmap's Reconstruction of the model in ``model_dir``, with errors that name the folder. A posed
    model without a points3D file (cameras and images only: `geocues sfm`'s input) is read as one
    without points."""
    import pycolmap

    model_dir = Path(model_dir)
    for stem in ("cameras", "images"):
        if not any((model_dir / f"{stem}.{ext}").is_file() for ext in ("bin", "txt")):
            raise FileNotFoundError(f"no {stem}.txt or {stem}.bin in {model_dir}")
    if (model_dir / "images.bin").is_file() and (model_dir / "images.txt").is_file():
        newer = (model_dir / "images.txt").stat().st_mtime > (model_dir / "images.bin").stat().st_mtime
        log.warning("%s holds a binary and a text model: the binary one (*.bin) is read%s", model_dir,
                    "; images.txt is newer (edited?): remove the .bin files to read it" if newer else "")
    else:
        _check_text_model(model_dir)
    try:
        if any((model_dir / f"points3D.{ext}").is_file() for ext in ("bin", "txt")):
            return pycolmap.Reconstruction(str(model_dir))
        import tempfile

        with tempfile.TemporaryDirectory(prefix="indoorgs_model_") as tmp:
            for f in model_dir.iterdir():  # cameras, images (rigs, frames): small
                if f.is_file() and f.suffix in (".bin", ".txt"):
                    shutil.copyfile(f, Path(tmp) / f.name)
            if (model_dir / "images.bin").is_file():
                (Path(tmp) / "points3D.bin").write_bytes(np.uint64(0).tobytes())
            else:
                (Path(tmp) / "points3D.txt").write_text("# no points\n")
            log.info("%s has no points3D file: read as a model without points", model_dir)
            return pycolmap.Reconstruction(tmp)
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on broken files
        hint = ""
        if "hasdataid" in str(exc).lower() and any((model_dir / f"{n}.{e}").is_file()
                                                for n in ("rigs", "frames") for e in ("txt", "bin")):
            hint = ("; its rigs and frames files disagree with its images file (an image's camera or id edited "
                    "by hand?): edit them alike, or remove both and COLMAP reads one rig per camera")
        raise ValueError(f"could not read COLMAP model in {model_dir}: {exc}{hint}") from exc


def read_model(model_dir: Path) -> tuple[list[RawImage], RawPoints]:
    """Read a COLMAP model (binary or text) with pycolmap; images sorted by name."""
    model_dir = Path(model_dir)
    rec = load_reconstruction(model_dir)

    images: list[RawImage] = []
    for image_id in rec.reg_image_ids():
        im = rec.images[image_id]
        cam = rec.cameras[im.camera_id]
        pose = im.cam_from_world()  # a method in pycolmap 4.2
        images.append(RawImage(
            image_id=int(image_id), camera_id=int(im.camera_id), name=im.name,
            model=cam.model.name, width=int(cam.width), height=int(cam.height),
            K=np.asarray(cam.calibration_matrix(), dtype=np.float64),
            R=np.asarray(pose.rotation.matrix(), dtype=np.float64),
            t=np.asarray(pose.translation, dtype=np.float64),
            distortion=camera_distortion(cam),
        ))
    images.sort(key=lambda r: r.name)

    n = len(rec.points3D)
    if n == 0:
        return images, RawPoints.empty()
    ids = np.empty(n, np.int64)
    xyz = np.empty((n, 3))
    rgb = np.empty((n, 3), np.uint8)
    err = np.empty(n)
    tlen = np.empty(n, np.int32)
    tracks: list[np.ndarray] = []
    for k, (pid, pt) in enumerate(sorted(rec.points3D.items())):  # deterministic order
        ids[k], xyz[k], rgb[k], err[k] = pid, pt.xyz, pt.color, pt.error
        elems = pt.track.elements
        tlen[k] = len(elems)
        tracks.append(np.fromiter((e.image_id for e in elems), dtype=np.int64, count=len(elems)))
    return images, RawPoints(ids, xyz, rgb, err, tlen, tracks)


def write_model(model_dir: Path, images: list[RawImage], points: RawPoints | None = None,
                binary: bool = False) -> Path:
    """Write a COLMAP model (text, or binary via pycolmap) atomically into ``model_dir``.

    Cameras are deduplicated by ``camera_id``; only PINHOLE intrinsics are written (fx, fy, cx, cy).
    Points are written without 2D observations (their tracks list image ids only), which COLMAP
    accepts; use pycolmap's triangulation to make full tracks.
    """
    model_dir = Path(model_dir)
    if not images:
        raise ValueError(f"refusing to write an empty model to {model_dir}: no images")
    with atomic_dir(model_dir) as tmp:
        cams: dict[int, RawImage] = {}
        for im in images:
            cams.setdefault(im.camera_id, im)
        with open(tmp / "cameras.txt", "w") as f:
            f.write("# Camera list with one line of data per camera:\n"
                    "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
            for cid, im in sorted(cams.items()):
                K = im.K
                f.write(f"{cid} PINHOLE {im.width} {im.height} "
                        f"{K[0, 0]:.10g} {K[1, 1]:.10g} {K[0, 2]:.10g} {K[1, 2]:.10g}\n")
        with open(tmp / "images.txt", "w") as f:
            f.write("# Image list with two lines of data per image:\n"
                    "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                    "#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
            for im in images:
                q = rotmat_to_quat_wxyz(im.R)
                f.write(f"{im.image_id} {' '.join(f'{v:.12g}' for v in q)} "
                        f"{' '.join(f'{v:.12g}' for v in im.t)} {im.camera_id} {im.name}\n\n")
        with open(tmp / "points3D.txt", "w") as f:
            f.write("# 3D point list with one line of data per point:\n"
                    "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
            if points is not None:
                for k in range(len(points.ids)):
                    x, y, z = points.xyz[k]
                    r, g, b = (int(v) for v in points.rgb[k])
                    f.write(f"{points.ids[k]} {x:.10g} {y:.10g} {z:.10g} {r} {g} {b} {points.error[k]:.6g}\n")
        if binary:
            import pycolmap

            rec = pycolmap.Reconstruction(str(tmp))
            for stem in ("cameras", "images", "points3D"):
                (tmp / f"{stem}.txt").unlink()
            rec.write_binary(str(tmp))
    return model_dir
