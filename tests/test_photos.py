"""geocues.photos: the photos of a folder are checked before SIFT (damaged files, names COLMAP's pair
lists cannot hold, shared stems) and grouped by size; photos a nested layout leaves out are counted."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from geocues.photos import check_photos, photos_in_subfolders


def _photo(path: Path, size=(64, 48), seed=0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.random.default_rng(seed).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path, quality=95)
    return path


def test_sizes_are_grouped(tmp_path):
    for i in range(3):
        _photo(tmp_path / f"{i}.jpg")
    _photo(tmp_path / "portrait.jpg", size=(48, 64))
    _photo(tmp_path / "x.png", size=(80, 60))
    names = sorted(p.name for p in tmp_path.iterdir())
    sizes = check_photos(tmp_path, names)
    assert sizes == {(64, 48): ["0.jpg", "1.jpg", "2.jpg"], (48, 64): ["portrait.jpg"], (80, 60): ["x.png"]}


def test_damaged_photos_are_listed(tmp_path):
    """An empty file and a text file named .jpg gave a PIL traceback deep in the extraction; a
    truncated JPEG went through the whole chain (undistort filled its lower part grey)."""
    good = _photo(tmp_path / "a.jpg")
    (tmp_path / "empty.jpg").write_bytes(b"")
    (tmp_path / "notes.jpg").write_text("not a photo")
    whole = _photo(tmp_path / "whole.jpg", size=(320, 240), seed=1).read_bytes()
    (tmp_path / "cut.jpg").write_bytes(whole[: len(whole) // 3])
    with pytest.raises(ValueError) as e:
        check_photos(tmp_path, ["a.jpg", "cut.jpg", "empty.jpg", "notes.jpg"])
    msg = str(e.value)
    assert msg.startswith("cannot read 3 of 4 photos: ")
    assert "cut.jpg (image file is truncated" in msg and "empty.jpg (empty file)" in msg and "notes.jpg" in msg
    assert str(good) not in msg


def test_names_colmap_cannot_pair_and_shared_stems(tmp_path):
    _photo(tmp_path / "IMG 0001.jpg")
    _photo(tmp_path / "b.jpg")
    with pytest.raises(ValueError, match=r"1 photo names hold a space \(IMG 0001.jpg\).*rename them"):
        check_photos(tmp_path, ["IMG 0001.jpg", "b.jpg"])
    _photo(tmp_path / "cam0" / "0.jpg")
    _photo(tmp_path / "cam1" / "0.jpg")
    with pytest.raises(ValueError, match=r"cam0/0.jpg and cam1/0.jpg .* share the file stem '0'.*cam1_0.jpg"):
        check_photos(tmp_path, ["cam0/0.jpg", "cam1/0.jpg"])


def test_photos_left_out_of_a_nested_layout_are_counted(tmp_path):
    for rel in ["seq0/0.jpg", "seq0/1.jpg", "seq1/a/2.jpg", ".hidden/3.jpg"]:
        _photo(tmp_path / rel)
    assert photos_in_subfolders(tmp_path) == 0  # no photo of its own: the subfolders are the scene
    _photo(tmp_path / "top.jpg")
    assert photos_in_subfolders(tmp_path) == 3  # now only top.jpg is


def test_hints_quote_a_path_with_a_space(tmp_path):
    """`geocues info 'my photos'` suggested `geocues sfm .../my photos -o MAP`: pasted, two arguments."""
    from geocues.colmap_io import find_model_dir

    photos = tmp_path / "my photos"
    _photo(photos / "images" / "a.jpg")
    with pytest.raises(FileNotFoundError) as e:
        find_model_dir(photos)
    assert f"`geocues sfm '{photos}' -o MAP`" in str(e.value)


def test_a_photo_above_pils_pixel_limit_is_a_photo(tmp_path, monkeypatch):
    """PIL refuses images over ~179 MP as decompression bombs (a 200 MP phone photo): a traceback."""
    from PIL import Image

    _photo(tmp_path / "big.jpg", size=(64, 48))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # 64 x 48 is "too large" now
    assert check_photos(tmp_path, ["big.jpg"]) == {(64, 48): ["big.jpg"]}
    assert Image.MAX_IMAGE_PIXELS == 1000  # put back
