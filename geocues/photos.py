"""Which files of a scene's images/ folder are photos, and their names as COLMAP gives them."""

from __future__ import annotations

from pathlib import Path

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
