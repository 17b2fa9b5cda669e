"""`geocues undistort`: what a PINHOLE scene keeps, what a warped scene leaves behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geocues.scene import Scene


def test_undistort_of_a_pinhole_scene_keeps_its_priors(tmp_path: Path):
    """Nothing is warped in a scene already pinhole: its priors still fit the copied images (they were
    dropped with 'they would need the same warp')."""
    from cues_synth import make_room_scene
    from geocues.undistort import UndistortConfig, run

    root = make_room_scene(tmp_path / "room", n_views=4, w=64, h=48, priors="all")
    out = run(UndistortConfig(), root, tmp_path / "und")
    a, b = Scene.load(root), Scene.load(out)
    assert b.has_depth_priors
    np.testing.assert_array_equal(a.depth_prior(1), b.depth_prior(1))


@pytest.mark.parametrize("distorted", [False, True])
def test_undistort_leaves_gt_depth_of_warped_images_behind(tmp_path: Path, caplog, distorted: bool):
    """gt/ was linked whole, so a warped scene's exact depth (the ablation's floor, splat render's GT-depth
    panels) was resized onto the undistorted images without a word (new-user audit): the mesh is carried,
    the per-pixel maps only where nothing was warped."""
    from cues_synth import make_room_scene
    from geocues.undistort import UndistortConfig, run

    root = make_room_scene(tmp_path / "room", n_views=4, w=64, h=48)
    (root / "gt" / "depth").mkdir(parents=True)
    np.save(root / "gt" / "depth" / "00000.npy", np.ones((48, 64), np.float32))
    (root / "gt" / "mesh.ply").write_text("ply\n")
    if distorted:
        (root / "sparse" / "0" / "cameras.txt").write_text("1 SIMPLE_RADIAL 64 48 40 32 24 0.05\n")
    with caplog.at_level("WARNING", logger="geocues"):
        out = run(UndistortConfig(), root, tmp_path / "und")
    gt = out / "gt"
    assert (gt / "mesh.ply").read_text() == "ply\n"
    assert (gt / "depth").exists() == (not distorted)
    assert gt.is_symlink() == (not distorted)  # a real folder of links only when something stayed behind
    assert ("gt/depth not carried over" in caplog.text) == distorted, caplog.text
