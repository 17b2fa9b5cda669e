"""Which files of a scene's images/ folder are photos, their names as COLMAP gives them, and what a
photo or map file holds (its size, an alpha channel, its bit depth, an EXIF rotation)."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Sequence

import numpy as np

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")  # compared in lower case: .JPG, .Jpeg too


def is_image(path: Path) -> bool:
    """A photo by its file name (any case of the extensions COLMAP and OpenCV both read)."""
    return Path(path).suffix.lower() in IMAGE_EXTS


def list_images(image_dir: Path) -> list[str]:
    """The photos in ``image_dir`` as COLMAP names them (relative, '/'-separated), sorted: its own files,
    or, when it holds none, those in its subfolders (a capture kept as images/seq1/...). Hidden files
    and folders are not photos (macOS writes ._NAME.JPG beside each photo on some drives)."""
    image_dir = Path(image_dir)
    own = sorted(p.name for p in image_dir.iterdir() if p.is_file() and is_image(p) and not p.name.startswith("."))
    if own:
        return own
    return sorted(rel.as_posix() for rel in (p.relative_to(image_dir) for p in image_dir.rglob("*")
                                             if p.is_file() and is_image(p))
                  if not any(part.startswith(".") for part in rel.parts))


def missing_images_error(model_dir: Path, paths: list[Path]) -> FileNotFoundError | None:
    """One error for every image a model lists that is not on disk (the count and the first three), or None."""
    gone = [p for p in paths if not Path(p).is_file()]
    if not gone:
        return None
    if len(gone) == 1:
        return FileNotFoundError(f"image listed in {model_dir} is missing on disk: {gone[0]}")
    return FileNotFoundError(f"{len(gone)} of {len(paths)} images listed in {model_dir} are missing on disk: "
                             + listed([str(p) for p in gone]))


def photos_in_subfolders(image_dir: Path) -> int:
    """How many photos lie in subfolders of ``image_dir`` that :func:`list_images` leaves out
    (it takes only the folder's own files when there are any)."""
    image_dir = Path(image_dir)
    if not any(p.is_file() and is_image(p) and not p.name.startswith(".") for p in image_dir.iterdir()):
        return 0
    return sum(1 for p in image_dir.rglob("*") if p.is_file() and is_image(p) and p.parent != image_dir
               and not any(part.startswith(".") for part in p.relative_to(image_dir).parts))


def listed(paths: list[str], more: int = 3) -> str:
    """The first ``more`` names, then how many more ("a, b, c and 4 more")."""
    return ", ".join(paths[:more]) + (f" and {len(paths) - more} more" if len(paths) > more else "")


def _check_one(path: Path, name: str, bad: list[str], sizes: dict) -> None:
    """Decode one photo (a JPEG at 1/8 scale): its size into ``sizes``, or why not into ``bad``."""
    from PIL import Image

    try:
        if path.stat().st_size == 0:
            raise OSError("empty file")
        with Image.open(path) as im:
            size = im.size
            if im.format == "JPEG":
                im.draft("RGB", (max(1, size[0] // 8), max(1, size[1] // 8)))
            im.load()
    except (OSError, ValueError, SyntaxError) as e:  # PIL raises each of them for a damaged file
        bad.append(f"{path} ({e})")
        return
    sizes.setdefault(size, []).append(name)


def check_photos(image_dir: Path, names: list[str]) -> dict[tuple[int, int], list[str]]:
    """Check the photos ``names`` of ``image_dir`` before feature extraction and group them by pixel
    size ((width, height) -> names, the stored pixels: EXIF orientation is not applied, as COLMAP).

    ValueError listing every photo that cannot be decoded (empty, not an image, truncated: COLMAP
    extracted from the part before the cut and `geocues undistort` filled the rest grey), names with
    whitespace (COLMAP's pair lists are whitespace-separated: no pair of them was ever matched) and
    two photos with one file stem in different subfolders (their priors and outputs share a name).
    A JPEG is decoded at 1/8 scale, which still reads every byte (211 ICL photos: 0.4 s)."""
    from PIL import Image

    bad, sizes = [], {}
    limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # a 200 MP phone photo is a photo, not a bomb
    try:
        for name in names:
            _check_one(Path(image_dir) / name, name, bad, sizes)
    finally:
        Image.MAX_IMAGE_PIXELS = limit
    if bad:
        raise ValueError(f"cannot read {len(bad)} of {len(names)} photos: {listed(bad)}; "
                         "replace or remove them")
    spaced = [n for n in names if any(ch.isspace() for ch in n)]
    if spaced:
        raise ValueError(f"{len(spaced)} photo names hold a space ({listed(spaced)}): COLMAP's pair lists are "
                         "whitespace-separated, so they cannot be matched; rename them (e.g. spaces to '_')")
    seen: dict[str, str] = {}
    for n in names:
        if seen.setdefault(Path(n).stem, n) != n:
            raise ValueError(f"photos {seen[Path(n).stem]} and {n} in {image_dir} share the file stem "
                             f"'{Path(n).stem}', which names their priors and outputs: rename one "
                             f"(e.g. {n.replace('/', '_')})")
    return sizes


def rotation_hint(path: Path, stored: tuple[int, int], model: tuple[int, int]) -> str:
    """The likely cause when a photo's sides are the model's swapped and it carries an EXIF rotation."""
    if stored != model[::-1]:
        return ""
    try:
        from PIL import Image

        with Image.open(path) as img:
            turned = img.getexif().get(0x0112, 1) in (5, 6, 7, 8)  # Orientation: a quarter turn
    except Exception:  # noqa: BLE001  (a hint only: the size error stands on its own)
        return ""
    return ("; the file carries an EXIF rotation tag, which this toolkit does not apply (it reads the stored "
            "pixels, docs/scenes.md): the model was made from the rotated photos, so save the photos rotated "
            "(e.g. PIL.ImageOps.exif_transpose) or map the stored ones again") if turned else ""


def transparent_fraction(path: Path) -> float:
    """The fraction of a photo's pixels that are transparent or partly so (0 without an alpha channel;
    only a photo with one is decoded, once per version of the file in a process)."""
    try:
        st = Path(path).stat()
    except OSError:
        return 0.0  # missing: the loader's own error names it
    return _transparent_fraction(str(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=4096)
def _transparent_fraction(path: str, mtime_ns: int, size: int) -> float:
    from PIL import Image

    try:
        with Image.open(path) as im:
            if "A" not in im.getbands() and "transparency" not in im.info:
                return 0.0
            alpha = np.asarray(im.convert("RGBA"))[..., 3]
    except OSError:
        return 0.0  # unreadable: the loader's own error names it
    return float((alpha < 255).mean())


def transparency_warning(paths: Sequence[Path]) -> str | None:
    """The warning for photos with transparent pixels: images are read as RGB (as COLMAP reads them), so
    those pixels train as whatever colour they store."""
    fractions = [(path, f) for path in paths if (f := transparent_fraction(path)) > 0]
    if not fractions:
        return None
    path, f = fractions[0]
    who = f"{path} has" if len(fractions) == 1 else f"{len(fractions)} of the {len(paths)} photos have"
    return (f"{who} an alpha channel ({'' if len(fractions) == 1 else f'{path.name}: '}{100 * f:.0f}% of its pixels "
            "transparent or partly so): images are read as RGB, so those pixels train as the colour they store; "
            "composite the photos onto a background (or mask them out) first")


def is_8bit_grey(path: Path) -> bool:
    """Whether an image file is a one-channel 8-bit (or palette) image (header only)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.mode in ("1", "L", "P")
    except OSError:
        return False  # unreadable: the loader's own error names it


def read_image_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size  # (width, height)
    except (UnidentifiedImageError, OSError) as exc:
        size = path.stat().st_size if path.exists() else 0
        raise ValueError(f"cannot read the image {path} ({'empty file' if size == 0 else type(exc).__name__})") from None
