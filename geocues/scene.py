"""The ``Scene`` type: a posed COLMAP scene folder with optional priors and ground truth.

Layout of a scene folder::

    SCENE/images/<name>             RGB images (names as in the model)
    SCENE/sparse/0/cameras|images|points3D.{bin,txt}   (or SCENE/sparse/)
    SCENE/priors/depth/<stem>.npy   optional monocular depth (H x W float32, metres, 0 = invalid), or
                                    disparity (inverse depth up to scale and shift) with scene.json
                                    {"priors": {"depth_kind": "disparity"}}
                         <stem>.png 16-bit, divided by scene.json "depth_png_scale" (units per metre)
    SCENE/priors/normal/<stem>.npy  optional normals (H x W x 3 float32, camera frame, facing camera)
                          <stem>.png 8/16-bit, [0, max] mapped to [-1, 1]
    SCENE/gt/mesh.ply               optional ground-truth mesh
    SCENE/scene.json                optional metadata (priors' provenance, PNG scales, ...)

A nerfstudio scene is read too: a folder with ``transforms.json`` (and no COLMAP model), or that
file itself; its cameras are converted once, in geocues.nerfstudio_io, and its frames' depth files
are the depth priors (priors/ is still read for the others).

Conventions (docs/conventions.md): metres, world-to-camera OpenCV cameras, COLMAP pixel centres.
"""

from __future__ import annotations

import json
import logging
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geocues.colmap_io import PINHOLE_MODELS, RawPoints, find_model_dir, read_model
from geocues.photos import IMAGE_EXTS, is_image, list_images, missing_images_error  # noqa: F401  (re-exported)
from geocues.logs import warn_once
from geocues.photos import is_8bit_grey, listed, read_image_size, rotation_hint, transparency_warning
from geocues.nerfstudio_io import find_transforms, read_transforms
from geocues.scene_priors import ScenePriors, load_npy

log = logging.getLogger(__name__)

ARBITRARY_SCALE = "arbitrary"  # scene.json "scale" of a model mapped from images alone (rescale removes it)
OWN_FRAME = "mapped from images"  # scene.json "frame" of such a model: origin and axes its own (kept)


def no_images_folder(image_dir: Path) -> FileNotFoundError:
    """The error for a scene without ``images/``, with the fix when the scene folder holds the photos itself."""
    image_dir = Path(image_dir)
    given = image_dir.parent
    own = [p for p in given.iterdir() if is_image(p)] if given.is_dir() else []
    if not given.exists():
        return FileNotFoundError(f"the scene folder {given} does not exist")
    if not own and (given / "transforms.json").is_file():  # a nerfstudio scene with frames in rgb/, ...
        return FileNotFoundError(f"no images folder at {image_dir}: {given}/transforms.json keeps its frames "
                                 f"elsewhere{_frames_folder(given)}, and this step reads photos in COLMAP's layout, "
                                 f"SCENE/images/: link that folder as {image_dir}")
    if not own:
        return FileNotFoundError(f"no images folder at {image_dir}")
    fix = (f"pass the scene folder above it, {given.parent}" if given.name == "images"
           else f"move them into {image_dir}/ and pass {given}")
    return FileNotFoundError(f"no images folder at {image_dir}; {given} holds {len(own)} images itself, but a "
                             f"scene keeps them in images/ (COLMAP's layout): {fix}")


def _frames_folder(root: Path) -> str:
    """" (in X/)" naming the folder of a transforms.json's first frame, or "" when it cannot be read."""
    try:
        first = Path(json.loads((root / "transforms.json").read_text())["frames"][0]["file_path"])
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return ""
    return f" (in {first.parent}/)" if str(first.parent) not in ("", ".") else ""


MIN_SIDE = 8  # pixels: the smallest image side a downscale may leave

GT_MESH_FILES = ("gt/mesh.ply", "reference_mesh.ply")  # the scene layout's, then a dataset's at its root (ICL-NUIM)


def gt_mesh_file(root: Path) -> Path | None:
    """The scene's ground-truth mesh: SCENE/gt/mesh.ply, else SCENE/reference_mesh.ply; None without one."""
    return next((Path(root) / f for f in GT_MESH_FILES if (Path(root) / f).is_file()), None)


def rescale_hint(root: Path) -> str:
    """How to make the scene at ``root`` metric (the end of every not-metric warning)."""
    return (f"make it metric with `geocues rescale {shlex.quote(str(root))} -o OUT --scale S` (metres per unit), --from-priors "
            "(metric depth priors) or, as a guess, --median-depth 2 (photos taken about 2 m from what they show)")


@dataclass
class Camera:
    """One posed view. Intrinsics are for the (possibly downscaled) size ``width`` x ``height``."""

    index: int  # position in Scene.cameras (name order)
    image_id: int  # COLMAP image id
    name: str  # image file name relative to SCENE/images
    image_path: Path
    width: int
    height: int
    K: np.ndarray  # [3, 3] float64, COLMAP pixel convention (top-left pixel centre = (0.5, 0.5))
    R: np.ndarray  # [3, 3] world-to-camera rotation
    t: np.ndarray  # [3] world-to-camera translation (metres)
    source_width: int = 0  # the photo's own size before --downscale (0: width / height)
    source_height: int = 0

    @property
    def source_size(self) -> tuple[int, int]:
        """The photo's own (width, height), before any ``--downscale``."""
        return self.source_width or self.width, self.source_height or self.height

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, [3]."""
        return -self.R.T @ self.t

    @property
    def world_to_camera(self) -> np.ndarray:
        """[4, 4] world-to-camera matrix."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points X [N, 3] -> (uv [N, 2] pixels, z [N] depth; z <= 0 is behind)."""
        Xc = np.asarray(X, dtype=np.float64) @ self.R.T + self.t
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (Xc[:, :2] / z[:, None]) * np.diag(self.K)[:2] + self.K[:2, 2]
        return uv, z

    def pixel_rays(self) -> np.ndarray:
        """Camera-frame ray directions (z = 1) through every pixel centre, [H, W, 3]."""
        i, j = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        return self.rays_at(i, j)

    def rays_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``pixel_rays()[rows, cols]`` without the whole image's grid: [..., 3], z = 1."""
        x = (np.asarray(cols) + 0.5 - self.K[0, 2]) / self.K[0, 0]
        y = (np.asarray(rows) + 0.5 - self.K[1, 2]) / self.K[1, 1]
        return np.stack([x, y, np.ones_like(x, dtype=np.float64)], axis=-1)


def held_out(index: int, test_every: int) -> bool:
    """Whether view ``index`` (name order) is a held-out test view: every ``test_every``-th (0: none), as 3DGS."""
    return test_every > 0 and index % test_every == 0


def upsampling_warning(downscale: float, work: str, own_size: str) -> str | None:
    """The sentence for a ``downscale`` below 1 (the photos upsampled: interpolated pixels, no detail,
    more ``work``), None otherwise; ``own_size`` names what --downscale 1 does instead."""
    if not downscale < 1:
        return None
    return (f"--downscale {downscale:g} is below 1: the photos are UPSAMPLED {1 / downscale:g}x (interpolated "
            f"pixels, no detail gained, {1 / downscale ** 2:.3g}x the {work}); --downscale 1 {own_size}")


def downscaled_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    """The image size a ``downscale`` gives (each side rounded on its own, at least 1 px)."""
    return max(1, int(round(width / downscale))), max(1, int(round(height / downscale)))


@dataclass
class Points3D:
    """SfM points of the model (possibly empty)."""

    ids: np.ndarray  # [N] int64 COLMAP ids
    xyz: np.ndarray  # [N, 3] float64
    rgb: np.ndarray  # [N, 3] uint8
    error: np.ndarray  # [N] reprojection error, pixels
    track_length: np.ndarray  # [N] int32
    visible_in: dict[int, np.ndarray] = field(default_factory=dict)  # camera index -> point indices

    def __len__(self) -> int:
        return len(self.ids)


def _has_colmap_model(root: Path) -> bool:
    try:
        find_model_dir(root)
        return True
    except (FileNotFoundError, ValueError):
        return False


class Scene(ScenePriors):
    """A posed scene read from a COLMAP model or a nerfstudio transforms.json; build it with :meth:`Scene.load`."""

    def __init__(self, root: Path, cameras: list[Camera], points: Points3D, metadata: dict,
                 test_every: int, downscale: float, model_dir: Path,
                 depth_files: dict[int, Path] | None = None, sources: list[Path] | None = None):
        self.root, self.cameras, self.points, self.metadata = root, cameras, points, metadata
        self.test_every, self.downscale, self.model_dir = test_every, downscale, model_dir
        self.depth_files = depth_files or {}  # camera index -> depth prior named by the scene file
        self.sources = sources or []  # files outside images/, priors/, sparse/ the scene was read from
        self.distorted_models: list[str] = []  # COLMAP models with distortion (only with allow_distorted)

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, root: str | Path, *, downscale: float = 1.0, test_every: int = 8,
             images_dir: str | Path | None = None, check_priors: bool = True,
             allow_distorted: bool = False) -> "Scene":
        """Read ``root`` (a scene folder, or a nerfstudio transforms.json). ``downscale`` divides
        image size and intrinsics; every ``test_every``-th image in name order (index % test_every
        == 0) is a test view (0 = no test views). Raises FileNotFoundError / ValueError naming the
        bad path. A distorted camera model is refused unless ``allow_distorted`` (then its
        calibration matrix is kept and the distortion ignored: for a summary, never for geometry;
        ``Scene.distorted_models`` names them)."""
        root = Path(root)
        if downscale <= 0:
            raise ValueError(f"downscale must be > 0, got {downscale}")
        if test_every < 0 or test_every == 1:
            raise ValueError(f"test_every must be 0 (no test views) or >= 2, got {test_every}")
        ns, transforms = None, find_transforms(root) if root.exists() else None
        if transforms is not None and (transforms == root or not _has_colmap_model(root)):
            ns = read_transforms(transforms)
            model_dir, scene_root, raw_images, raw_points = transforms, transforms.parent, ns.images, ns.points
        else:
            model_dir = find_model_dir(root)
            scene_root = root
            if transforms is not None:
                warn_once(log, f"{root} holds a COLMAP model ({model_dir}) and {transforms.name}: the COLMAP model is "
                          f"read; give {shlex.quote(str(transforms))} as the scene to read the other")
            if model_dir == root:  # a model folder given directly: the scene is the folder above sparse/
                scene_root = next((p for p in (root, root.parent, root.parent.parent)
                                   if (p / "images").is_dir()), root)
            raw_images, raw_points = read_model(model_dir)
        if not raw_images:
            raise ValueError(f"the COLMAP model in {model_dir} has no registered images")
        img_dir = Path(images_dir) if images_dir is not None else scene_root / "images"
        if not img_dir.is_dir() and (ns is None or images_dir is not None):
            raise no_images_folder(img_dir)
        meta_path = scene_root / "scene.json"
        metadata = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
        if ns is not None and ns.depth_paths and "depth_png_scale" not in metadata:
            metadata["depth_png_scale"] = 1000.0  # nerfstudio's depth_unit_scale_factor: millimetres

        cameras: list[Camera] = []
        paths = [ns.image_paths[k] if ns is not None and images_dir is None else img_dir / im.name
                 for k, im in enumerate(raw_images)]
        distorted = next((im for im in raw_images if not im.pinhole), None)
        if distorted is not None and not allow_distorted:
            raise ValueError(f"image {distorted.name} in {model_dir} uses the distorted camera model "
                             f"{distorted.model}; undistort the scene first: `geocues undistort {shlex.quote(str(scene_root))} -o OUT`")
        if err := missing_images_error(model_dir, paths):
            raise err
        if alpha := transparency_warning(paths):
            warn_once(log, alpha)
        for k, (im, path) in enumerate(zip(raw_images, paths)):
            w, h = read_image_size(path)
            if (w, h) != (im.width, im.height):
                raise ValueError(f"{path} is {w}x{h} but its camera in {model_dir} says "
                                 f"{im.width}x{im.height}{rotation_hint(path, (w, h), (im.width, im.height))}")
            if not (np.isfinite(im.K).all() and np.isfinite(im.R).all() and np.isfinite(im.t).all()):
                raise ValueError(f"image {im.name} in {model_dir} has a non-finite pose or intrinsics")
            nw, nh = downscaled_size(im.width, im.height, downscale)
            if min(nw, nh) < MIN_SIDE:  # 1-px images trained to a PSNR that meant nothing
                raise ValueError(f"downscale {downscale:g} makes {im.name} ({im.width}x{im.height}) {nw}x{nh} px; "
                                 f"a side under {MIN_SIDE} px shows no scene: use at most "
                                 f"{min(im.width, im.height) / MIN_SIDE:g}")
            S = np.diag([nw / im.width, nh / im.height, 1.0])  # exact under COLMAP pixel centres
            cameras.append(Camera(index=k, image_id=im.image_id, name=im.name, image_path=path, width=nw, height=nh,
                                  K=S @ im.K, R=im.R, t=im.t, source_width=im.width, source_height=im.height))
        seen: dict[str, str] = {}
        for c in cameras:  # priors, caches and per-view outputs are named by the file stem
            if seen.setdefault(c.stem, c.name) != c.name:
                raise ValueError(f"images {seen[c.stem]} and {c.name} in {model_dir} share the file stem "
                                 f"'{c.stem}', which names their priors and outputs: rename one (e.g. "
                                 f"{c.name.replace('/', '_')}) in the images folder and the model")
        points = cls._points_from_raw(raw_points, cameras)
        depth_files = {} if ns is None else {c.index: ns.depth_paths[c.name] for c in cameras
                                              if c.name in ns.depth_paths}
        scene = cls(scene_root, cameras, points, metadata, test_every, downscale, model_dir, depth_files,
                    [] if ns is None else ns.sources)
        scene.distorted_models = sorted({im.model for im in raw_images if not im.pinhole})
        if zero := sorted({im.model for im in raw_images if im.pinhole and im.model not in PINHOLE_MODELS}):
            log.info("%s: camera model %s with zero distortion, read as a pinhole", model_dir, ", ".join(zero))
        if (scene_root / "cache" / "mvs_sweep").is_dir() and not (scene_root / "mvs_report.json").is_file():
            warn_once(log, f"{scene_root} is an unfinished `geocues mvs` output (its sweeps, no mvs_report.json: "
                           "killed before it ended?): its depth priors may be missing or mix two runs; run the same "
                           "`geocues mvs` command again (the finished sweeps are cached)")
        if check_priors:
            scene._check_priors(raw_images)
        log.info("scene %s: %d images (%d train / %d test), %d points, priors: depth %d, normal %d",
                 scene_root, len(cameras), len(scene.train_indices), len(scene.test_indices),
                 len(points), sum(p is not None for p in map(scene.depth_prior_path, range(len(cameras)))),
                 sum(p is not None for p in map(scene.normal_prior_path, range(len(cameras)))))
        return scene

    @staticmethod
    def _points_from_raw(raw: RawPoints, cameras: list[Camera]) -> Points3D:
        finite = np.isfinite(raw.xyz).all(1) if len(raw.xyz) else np.zeros(0, bool)
        if not finite.all():  # dropped with a counted reason, never carried into the cues
            log.warning("SfM model: %d of %d points have non-finite coordinates and are dropped",
                        int((~finite).sum()), len(finite))
            keep = np.where(finite)[0]
            raw = RawPoints(raw.ids[keep], raw.xyz[keep], raw.rgb[keep], raw.error[keep],
                            raw.track_length[keep], [raw.track_image_ids[k] for k in keep])
        by_image_id = {c.image_id: c.index for c in cameras}
        vis: dict[int, list[int]] = {c.index: [] for c in cameras}
        for k, track in enumerate(raw.track_image_ids):
            for image_id in np.unique(track):
                if int(image_id) in by_image_id:
                    vis[by_image_id[int(image_id)]].append(k)
        return Points3D(raw.ids, raw.xyz, raw.rgb, raw.error, raw.track_length,
                        {i: np.asarray(v, np.int64) for i, v in vis.items()})

    def _check_priors(self, raw_images) -> None:
        """Every prior must be a map of the right kind; one of another size than its image is
        resized when loaded (nearest: 0 = invalid stays intact), with a warning here."""
        resized, eight_bit = [], []
        for cam, raw in zip(self.cameras, raw_images):
            for kind in ("depth", "normal"):
                path = self._prior_path(kind, cam.index)
                if path is None:
                    continue
                if kind == "depth" and path.suffix != ".npy":
                    scale = self._depth_png_scale(path)  # a PNG's unit is scene.json's: named here, not mid-extract
                    if is_8bit_grey(path):
                        eight_bit.append(path.name)
                shape = (load_npy(path, f"{kind} prior", mmap_mode="r").shape if path.suffix == ".npy"
                         else read_image_size(path)[::-1])
                want = "HxW" + ("x3" if kind == "normal" else "")
                if path.suffix == ".npy" and (len(shape) != (3 if kind == "normal" else 2)
                                              or (kind == "normal" and shape[2] != 3)):
                    raise ValueError(f"{kind} prior {path} has shape {tuple(shape)}, expected {want} "
                                     f"({raw.height}x{raw.width} for {cam.image_path.name})")
                if tuple(shape[:2]) not in {(raw.height, raw.width), (cam.height, cam.width)}:
                    resized.append(f"{kind} {path.name} {shape[1]}x{shape[0]}")
                    if abs(shape[1] / shape[0] - raw.width / raw.height) > 0.02 * raw.width / raw.height:
                        warn_once(log, f"{kind} prior {path} is {shape[1]}x{shape[0]} but its image "
                                       f"{cam.image_path.name} is {raw.width}x{raw.height}: another aspect ratio "
                                       "(is it cropped?); it is stretched to the image")
        if resized:  # warned once: `splat ablate` loads the scene again for every row
            warn_once(log, f"{len(resized)} prior maps of {self.root} are not the size of their images and are "
                           f"resized when loaded ({listed(resized)})")
        if eight_bit:  # a depth visualisation given as depth: read as 0-0.255 m at millimetres, in silence
            warn_once(log, f"{len(eight_bit)} depth priors of {self.root} are 8-bit PNGs ({listed(eight_bit)}): 256 "
                           f"levels, read as depth at most {255 / scale:.3g} scene units (255 / depth_png_scale "
                           f"{scale:g}); depth and disparity maps are 16-bit PNGs or .npy files: is it a "
                           "visualisation?")

    # ------------------------------------------------------------------ views
    @property
    def test_indices(self) -> list[int]:
        if self.test_every == 0:
            return []
        return [c.index for c in self.cameras if held_out(c.index, self.test_every)]

    @property
    def train_indices(self) -> list[int]:
        test = set(self.test_indices)
        return [c.index for c in self.cameras if c.index not in test]

    def __len__(self) -> int:
        return len(self.cameras)

    def camera(self, i: int) -> Camera:
        """Camera ``i`` (0 <= i < len): IndexError naming the scene otherwise (a -1 read the last)."""
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < len(self.cameras):
            raise IndexError(f"camera index {i!r} outside 0..{len(self.cameras) - 1} of the scene {self.root}")
        return self.cameras[i]

    def load_image(self, i: int) -> np.ndarray:
        """RGB image of camera ``i`` at the scene's scale, float32 [H, W, 3] in [0, 1]."""
        import cv2

        cam = self.camera(i)
        # the stored pixel grid, as COLMAP reads it: an EXIF orientation tag (a phone held upright) is not
        # applied, or a portrait photo would come out turned against its camera's intrinsics
        bgr = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if bgr is None:
            raise FileNotFoundError(f"could not read image {cam.image_path}")
        if bgr.shape[:2] != (cam.height, cam.width):
            bgr = cv2.resize(bgr, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        return bgr[:, :, ::-1].astype(np.float32) / 255.0

    # ------------------------------------------------------------------ priors
    @property
    def gt_mesh_path(self) -> Path | None:
        return gt_mesh_file(self.root)
