"""Caches and skip keys follow the content of what they read, not only its path (regression:
`geocues extract` after a scene was regenerated at the same path served the old scene's cues, and
with --overwrite the stale line cache gave 0 LINE cues); unknown cue types are an error."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

import geocues.extract as ex
from cues_synth import fake_line_cues, make_room_scene
from geocues.cue_io import CueCloud, read_cues_ply, write_cues_ply
from geocues.lines.config import LineConfig
from geocues.lines.detect import detect_all
from geocues.scene import Scene
from geocues.texture import TextureConfig, file_stamp, load_or_compute


def _regenerate(root, seed):
    shutil.rmtree(root)
    return make_room_scene(root, n_views=16, priors="all", seed=seed)


def test_file_stamp_changes_when_a_file_is_rewritten(tmp_path):
    f = tmp_path / "a.png"
    f.write_bytes(b"1234")
    before = file_stamp(f)
    f.write_bytes(b"12345")
    assert file_stamp(f) != before
    os.utime(f, ns=(1, 1))
    same_size = file_stamp(f)
    os.utime(f, ns=(2, 2))
    assert file_stamp(f) != same_size  # same size, new mtime
    assert file_stamp(tmp_path / "missing.png", None) == "-|-"


def test_texture_and_line_caches_miss_after_the_images_change(tmp_path):
    root = make_room_scene(tmp_path / "room", n_views=4, priors="none")
    scene = Scene.load(root)
    cam = scene.cameras[0]
    cfg = TextureConfig()
    _, hit = load_or_compute(cam.image_path, lambda: scene.load_image(0), cfg, tmp_path / "tex", (cam.width, cam.height))
    _, hit2 = load_or_compute(cam.image_path, lambda: scene.load_image(0), cfg, tmp_path / "tex", (cam.width, cam.height))
    assert (hit, hit2) == (False, True)
    segs, stats = detect_all(scene, LineConfig(), tmp_path / "lines")
    assert detect_all(scene, LineConfig(), tmp_path / "lines")[1]["cached"] == 4
    import cv2

    img = cv2.imread(str(cam.image_path))
    cv2.imwrite(str(cam.image_path), 255 - img)  # the same path, other content
    _, hit3 = load_or_compute(cam.image_path, lambda: scene.load_image(0), cfg, tmp_path / "tex", (cam.width, cam.height))
    assert hit3 is False
    assert detect_all(scene, LineConfig(), tmp_path / "lines")[1]["cached"] == 3


def test_extract_into_the_same_folder_after_the_scene_was_regenerated(tmp_path, monkeypatch):
    monkeypatch.setattr(ex, "_run_lines", lambda scene, cfg, cache: fake_line_cues(scene.cameras))
    root = make_room_scene(tmp_path / "room", n_views=16, priors="all", seed=0)
    out = ex.run(None, root, tmp_path / "cues")
    old = read_cues_ply(out / "cues.ply")
    assert ex.run(None, root, out) == out  # unchanged scene: skipped
    _regenerate(root, seed=1)  # other SfM points and priors at the same path
    with pytest.raises(ValueError, match="another configuration or scene"):
        ex.run(None, root, out)  # never the old scene's cues without a word
    new = read_cues_ply(ex.run(None, root, out, overwrite=True) / "cues.ply")
    fresh = read_cues_ply(ex.run(None, root, tmp_path / "fresh") / "cues.ply")
    assert new.counts() == fresh.counts()
    # extraction is deterministic per seed: bit-identical cues (regression: Open3D's threaded
    # segment_plane gave 2,805 and 2,807 PLANE cues on two runs of one scene)
    np.testing.assert_array_equal(new.xyz, fresh.xyz)
    np.testing.assert_array_equal(new.cue_type, fresh.cue_type)
    np.testing.assert_array_equal(new.normal, fresh.normal)
    assert not np.array_equal(np.sort(old.xyz, axis=0), np.sort(new.xyz, axis=0))


def test_unknown_cue_type_is_an_error_naming_the_file(tmp_path):
    cloud = CueCloud.make(np.zeros((3, 3)), np.zeros((3, 3)), 0)
    cloud.cue_type[:] = [0, 7, 7]
    path = write_cues_ply(tmp_path / "cues.ply", cloud)
    with pytest.raises(ValueError, match=r"cues.ply: unknown cue_type values \[7\] in 2 points"):
        read_cues_ply(path)
