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


def missing_images_error(model_dir: Path, paths: list[Path]) -> FileNotFoundError | None:
    """One error for every image a model lists that is not on disk (the count and the first three), or None."""
    gone = [p for p in paths if not Path(p).is_file()]
    if not gone:
        return None
    if len(gone) == 1:
        return FileNotFoundError(f"image listed in {model_dir} is missing on disk: {gone[0]}")
    more = f" and {len(gone) - 3} more" if len(gone) > 3 else ""
    return FileNotFoundError(f"{len(gone)} of {len(paths)} images listed in {model_dir} are missing on disk: "
                             + ", ".join(str(p) for p in gone[:3]) + more)
