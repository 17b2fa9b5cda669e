"""The `floor` row's GT depth read at the wrong scale is named (splat.floor.depth_scale_warning)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from cues_synth import make_room_scene, render

from geocues.scene import Scene
from splat.floor import depth_scale_warning


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = make_room_scene(tmp_path_factory.mktemp("floor_row") / "room", n_views=8, w=64, h=48)
    depths = {}
    for cam in Scene.load(root, check_priors=False).cameras:
        _, depth, _ = render(cam.K, cam.R, cam.t, cam.width, cam.height)
        depths[cam.stem] = depth.astype(np.float32)
    return root, depths


def _write(folder, depths, per_metre: float | None):
    folder.mkdir(parents=True, exist_ok=True)
    for stem, d in depths.items():
        if per_metre is None:
            np.save(folder / f"{stem}.npy", d)
        else:
            cv2.imwrite(str(folder / f"{stem}.png"), np.round(d * per_metre).astype(np.uint16))
    return folder


@pytest.mark.parametrize("per_metre, read_at, warned", [(1000, 1000, False), (5000, 1000, True), (1000, 5000, True),
                                                        (5000, 5000, False)])
def test_a_png_scale_that_disagrees_with_the_points_is_named(room, tmp_path, per_metre, read_at, warned):
    """ICL-NUIM's TUM-format PNGs are 1/5000 m; read at the default 1000 the floor was fused 5x too deep
    in silence, and every 'C-L1 / floor' read against it."""
    root, depths = room
    scene = Scene.load(root, check_priors=False)
    folder = _write(tmp_path / "depth", depths, per_metre)
    said = depth_scale_warning(scene, folder, read_at, scene.train_indices)
    assert (said is not None) == warned, said
    if warned:
        assert f"about {per_metre} would match" in said and f"--gt-depth-png-scale ({read_at}" in said


def test_metre_maps_of_another_unit_are_named_without_a_png_scale(room, tmp_path):
    root, depths = room
    scene = Scene.load(root, check_priors=False)
    assert depth_scale_warning(scene, _write(tmp_path / "m", depths, None), 1000, scene.train_indices) is None
    doubled = {k: 2 * v for k, v in depths.items()}
    said = depth_scale_warning(scene, _write(tmp_path / "m2", doubled, None), 1000, scene.train_indices)
    assert said is not None and said.startswith(f"the GT depth in {tmp_path / 'm2'} is 2x")
    assert "png-scale" not in said and "a scene not in its GT's unit" in said
