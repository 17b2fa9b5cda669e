"""A scene's priors as files on disk: where each image's depth and normal prior is, how it is read
(.npy as stored, PNG through scene.json's scale / channel mapping), the scene.json options that say
what they hold (depth_kind, normal_axes) and the checks a user's files need. :class:`ScenePriors` is
the part of :class:`geocues.scene.Scene` that reads them (it uses the scene's ``root``, ``metadata``,
``depth_files`` and ``camera(i)``).

Conventions (docs/conventions.md): depth in metres (0 = invalid), normals unit camera-frame vectors
facing the camera (all-zero, or black in a PNG, = invalid).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("geocues.scene")  # the scene's messages, under the logger they always had


def _read_png(path: Path, what: str) -> np.ndarray:
    """An image file as stored (any bit depth, channels BGR), else ValueError naming it (OpenCV
    returns None for a damaged or truncated file)."""
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"cannot read the {what} {path} (damaged, truncated or not an image)")
    return raw


def load_npy(path: Path, what: str, mmap_mode: str | None = None) -> np.ndarray:
    """np.load with an error that names the file (truncated or foreign .npy files)."""
    try:
        return np.load(path, mmap_mode=mmap_mode)
    except (ValueError, OSError, EOFError) as exc:
        if "allow_pickle" in str(exc):  # numpy's guess for a file without the .npy magic: not an array file
            try:
                head = Path(path).read_bytes()[:6]
            except OSError:
                head = b""
            if head != b"\x93NUMPY":
                raise ValueError(f"cannot read the {what} {path}: it is not a .npy file (numpy.save writes "
                                 "one; no .npy header)") from None
        raise ValueError(f"cannot read the {what} {path} ({exc})") from None


class ScenePriors:
    """Prior access of :class:`geocues.scene.Scene` (a mixin: the scene provides root, metadata,
    depth_files, cameras and camera(i))."""

    def _say_non_finite(self, kind: str, path: Path, count: int) -> None:
        """A prior file's non-finite pixels, said once per file; a warning for the scene's first file of
        each kind, debug lines for the rest (priors that mark what a network did not see with NaN have
        it in every file: hundreds of warnings said nothing more than the first)."""
        said = self.__dict__.setdefault("_non_finite_said", {})
        if path in said.setdefault(kind, set()):
            return
        first = not said[kind]
        said[kind].add(path)
        log.log(logging.WARNING if first else logging.DEBUG, "%s prior %s: %d non-finite pixels set invalid (0)%s",
                kind, path, count, f"; the other {kind} priors' are logged at debug level (-v)" if first else "")

    def _prior_path(self, kind: str, i: int) -> Path | None:
        if kind == "depth" and i in self.depth_files:  # named by transforms.json (depth_file_path)
            return self.depth_files[i]
        folder, stem = self.root / "priors" / kind, self.camera(i).stem
        for ext in (".npy", ".png"):  # stem + ext: with_suffix would make frame.0001 -> frame.npy
            if (folder / (stem + ext)).is_file():
                return folder / (stem + ext)
        return None

    def stray_priors(self, kind: str) -> list[Path]:
        """Files in priors/<kind>/ that are no image's prior: named after no image stem (00005_depth.npy,
        00005.png.npy) or in a format that is not read (.exr, .tif, .PNG): ignored, so listed for a
        warning. Depth files a transforms.json names for its frames are priors wherever they are."""
        folder = self.root / "priors" / kind
        if not folder.is_dir():
            return []
        used = {c.stem + ext for c in self.cameras for ext in (".npy", ".png")}
        named = {p.resolve() for p in self.depth_files.values()} if kind == "depth" else set()
        return sorted(p for p in folder.iterdir() if p.name not in used and not p.name.startswith(".")
                      and p.resolve() not in named)

    def depth_prior_path(self, i: int) -> Path | None:
        return self._prior_path("depth", i)

    def normal_prior_path(self, i: int) -> Path | None:
        return self._prior_path("normal", i)

    @property
    def has_depth_priors(self) -> bool:
        return any(self.depth_prior_path(i) is not None for i in range(len(self.cameras)))

    @property
    def has_normal_priors(self) -> bool:
        return any(self.normal_prior_path(i) is not None for i in range(len(self.cameras)))

    def depth_prior(self, i: int) -> np.ndarray | None:
        """Depth prior of camera ``i`` at the scene's scale, [H, W] float32 (0 = invalid), as stored:
        z-depth (metres up to scale and shift), or disparity when :attr:`depth_kind` says so."""
        import cv2

        path = self.depth_prior_path(i)
        if path is None:
            return None
        if path.suffix == ".npy":
            d = load_npy(path, "depth prior").astype(np.float32)
        else:
            d = _read_png(path, "depth prior").astype(np.float32) / self._depth_png_scale(path)
        if d.ndim != 2:
            raise ValueError(f"the depth prior {path} has shape {d.shape}; expected [H, W]")
        bad = ~np.isfinite(d)
        if bad.any():  # NaN / Inf are invalid pixels (0), counted
            self._say_non_finite("depth", path, int(bad.sum()))
            d[bad] = 0.0
        cam = self.camera(i)
        if d.shape != (cam.height, cam.width):  # nearest keeps 0 = invalid intact
            d = cv2.resize(d, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
        return d

    def normal_prior(self, i: int) -> np.ndarray | None:
        """Normal prior of camera ``i``, [H, W, 3] float32 unit, camera frame (zeros = invalid)."""
        import cv2

        path = self.normal_prior_path(i)
        if path is None:
            return None
        if path.suffix == ".npy":
            n = load_npy(path, "normal prior").astype(np.float32)
        else:
            raw = _read_png(path, "normal prior")
            if raw.ndim != 3 or raw.shape[2] != 3:
                raise ValueError(f"the normal prior {path} has shape {raw.shape}; expected an RGB image [H, W, 3]")
            raw = raw[:, :, ::-1]
            n = raw.astype(np.float32) / float(np.iinfo(raw.dtype).max) * 2.0 - 1.0
            n[(raw == 0).all(-1)] = 0.0  # black: no normal (a PNG cannot hold the .npy's all-zero vector)
        if n.ndim != 3 or n.shape[2] != 3:
            raise ValueError(f"the normal prior {path} has shape {n.shape}; expected [H, W, 3]")
        if self.normal_axes == "opengl":  # OpenGL camera axes (x right, y up, z back) -> OpenCV, once, here
            n = n * np.array([1.0, -1.0, -1.0], np.float32)
        bad = ~np.isfinite(n).all(-1)
        if bad.any():
            self._say_non_finite("normal", path, int(bad.sum()))
            n[bad] = 0.0
        cam = self.camera(i)
        if n.shape[:2] != (cam.height, cam.width):
            n = cv2.resize(n, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        return np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)

    def _depth_png_scale(self, path: Path) -> float:
        """scene.json's ``depth_png_scale`` (PNG units per metre; for disparity, any positive factor),
        a positive number, else ValueError naming the PNG and the key."""
        scale = self.metadata.get("depth_png_scale")
        what = ("units per metre, e.g. 1000 for millimetres" if self.depth_kind == "depth"
                else "any positive factor for disparity, e.g. 1")
        if scale is None:
            raise ValueError(f"{path} is a PNG depth prior but {self.root / 'scene.json'} has no "
                             f"'depth_png_scale' ({what})")
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"{self.root / 'scene.json'}: depth_png_scale must be a positive number ({what}), "
                             f"got {scale!r}")
        return float(scale)

    def _prior_option(self, key: str, allowed: tuple[str, ...]) -> str:
        """scene.json ``{"priors": {key: value}}``, one of ``allowed`` (the first is the default)."""
        priors = self.metadata.get("priors")
        value = priors.get(key, allowed[0]) if isinstance(priors, dict) else allowed[0]
        if value not in allowed:
            raise ValueError(f"{self.root / 'scene.json'}: priors.{key} must be "
                             f"{' or '.join(map(repr, allowed))}, got {value!r}")
        return value

    @property
    def normal_axes(self) -> str:
        """Camera axes of the normal priors: "opencv" (default) or "opengl" (scene.json
        ``{"priors": {"normal_axes": "opengl"}}``), converted to OpenCV when loaded."""
        return self._prior_option("normal_axes", ("opencv", "opengl"))

    @property
    def depth_kind(self) -> str:
        """What the depth priors hold: "depth" (z-depth up to scale and shift, the default) or
        "disparity" (inverse depth up to scale and shift, as Depth-Anything and MiDaS write it;
        scene.json ``{"priors": {"depth_kind": "disparity"}}``). The maps are loaded as stored;
        the depth alignment fits each kind its own way (geocues.depth_align)."""
        return self._prior_option("depth_kind", ("depth", "disparity"))

    def normals_facing_away(self, max_images: int = 5) -> float | None:
        """Share of valid normal-prior pixels (of up to ``max_images`` images, as loaded) that face
        away from the camera (n . viewing ray > 0). Visible surfaces face the camera, so a large
        share means the priors use other camera axes (OpenGL's y up, z back). None: no priors."""
        idx = [i for i in range(len(self.cameras)) if self.normal_prior_path(i) is not None]
        if not idx:
            return None
        away = total = 0
        for i in idx[:: max(1, len(idx) // max_images)][:max_images]:
            n = self.normal_prior(i)
            rays = self.camera(i).pixel_rays()
            valid = np.linalg.norm(n, axis=-1) > 0.5
            dots = (n * rays.reshape(n.shape)).sum(-1)
            away += int((dots[valid] > 0).sum())
            total += int(valid.sum())
        return away / total if total else None
