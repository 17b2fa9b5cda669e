"""`geocues info` ends with what to run next: the first step the scene lacks, then the chain to a mesh."""

from __future__ import annotations

import json
import shlex
import subprocess
from pathlib import Path

import pytest

from cues_synth import make_room_scene
from geocues.advice import next_steps
from geocues.scene import Scene
from test_scene import make_scene


def _commands(scene_dir: Path, **kw) -> list[str]:
    from geocues.rescale import metric_warning

    s = Scene.load(scene_dir, allow_distorted=True, **kw)
    return [cmd for cmd, _ in next_steps(s, not_metric=metric_warning(s) is not None)]


@pytest.fixture(scope="module")
def rooms(tmp_path_factory):
    base = tmp_path_factory.mktemp("advice")
    return (make_room_scene(base / "with priors", n_views=4, w=64, h=48, priors="all"),
            make_room_scene(base / "bare", n_views=4, w=64, h=48, priors="none"))


def test_each_missing_step_comes_first(tmp_path, rooms):
    make_scene(tmp_path / "posed")  # a posed model without points
    cmds = _commands(tmp_path / "posed")
    assert cmds[0] == f"geocues sfm {tmp_path / 'posed'} -o {tmp_path / 'posed_sfm'}"
    assert cmds[1] == f"geocues info {tmp_path / 'posed_sfm'}"

    cams = tmp_path / "posed" / "sparse" / "0" / "cameras.txt"
    cams.write_text("1 SIMPLE_RADIAL 64 48 60 32 24 0.05\n")
    assert _commands(tmp_path / "posed")[0].startswith(f"geocues undistort {tmp_path / 'posed'} -o ")

    with_priors, bare = rooms
    meta = json.loads((bare / "scene.json").read_text()) if (bare / "scene.json").is_file() else {}
    arbitrary = tmp_path / "arbitrary"
    subprocess.run(["cp", "-r", str(bare), str(arbitrary)], check=True)
    (arbitrary / "scene.json").write_text(json.dumps({**meta, "scale": "arbitrary"}))
    cmds = _commands(arbitrary)
    assert cmds[0].startswith(f"geocues rescale {arbitrary} -o ") and cmds[0].endswith("--median-depth 2")


def test_the_chain_follows_the_priors(rooms):
    with_priors, bare = rooms
    q = shlex.quote
    cmds = _commands(with_priors)
    cues, run = q(f"{with_priors}_cues"), q(f"{with_priors}_run")
    assert cmds[0] == f"geocues extract {q(str(with_priors))} -o {cues}"
    assert cmds[1].startswith(f"splat train {q(str(with_priors))} -c {cues} -o {run}") and "--preset" not in cmds[1]
    # the folder's name has a space: quoted, the command survives the shell
    assert shlex.split(cmds[0]) == ["geocues", "extract", str(with_priors), "-o", f"{with_priors}_cues"]
    cmds = _commands(bare)
    mvs = f"{bare}_mvs"
    assert cmds[0] == f"geocues mvs {bare} -o {mvs}"
    assert cmds[1] == f"geocues extract {mvs} -o {bare}_cues --preset mvs"
    assert cmds[2].startswith(f"splat train {mvs} -c {bare}_cues -o {bare}_run --preset mvs")


def test_info_prints_them(rooms, capsys):
    from cli.geocues_cli import main

    _, bare = rooms
    assert main(["info", str(bare)]) == 0
    out = capsys.readouterr().out.splitlines()
    at = next(k for k, line in enumerate(out) if line.startswith("next"))
    assert out[at].split(None, 1)[1].startswith("# no depth priors")
    assert out[at + 1].strip() == f"geocues mvs {bare} -o {bare}_mvs"
    assert any(line.startswith("warning    only 4 images:") for line in out)  # too few for a room


def test_a_geocues_mvs_scene_is_advised_its_recipe(rooms, tmp_path):
    from geocues.mvs import MVS_PRIORS

    with_priors, _ = rooms
    mvs = tmp_path / "room_mvs"
    subprocess.run(["cp", "-r", str(with_priors), str(mvs)], check=True)
    meta = json.loads((mvs / "scene.json").read_text()) if (mvs / "scene.json").is_file() else {}
    (mvs / "scene.json").write_text(json.dumps({**meta, "priors": MVS_PRIORS}))
    cmds = _commands(mvs)
    assert cmds[0] == f"geocues extract {mvs} -o {mvs}_cues --preset mvs"
    assert cmds[1].startswith(f"splat train {mvs} -c {mvs}_cues -o {mvs}_run --preset mvs")


def test_a_focal_length_in_another_unit_is_named(rooms):
    """fx 1e6 or 1 on 320-px images trained to an empty mesh with no word on the cameras."""
    from dataclasses import replace

    from geocues.advice import fov_warning

    s = Scene.load(rooms[1])
    assert fov_warning(s) is None  # the test rooms' cameras
    for fx, fov in ((1e6, "0.00367 deg"), (1.0, "176 deg")):
        K = s.cameras[0].K.copy()
        K[0, 0] = fx
        odd = Scene.load(rooms[1])
        odd.cameras[0] = replace(odd.cameras[0], K=K)
        msg = fov_warning(odd)
        assert msg is not None and msg.startswith("1 camera(s) have a horizontal field of view outside 10-150") and fov in msg, msg


def test_info_on_a_folder_of_photos_says_the_first_step(tmp_path, capsys):
    """README: `geocues info SCENE` at any step says what to run next; on the first step, photos
    without a model, it was an error."""
    import numpy as np
    from PIL import Image

    from cli.geocues_cli import main

    photos = tmp_path / "my photos"
    (photos / "images").mkdir(parents=True)
    for k in range(3):
        Image.fromarray(np.full((24, 32, 3), 40 * k, np.uint8)).save(photos / "images" / f"{k}.jpg")
    assert main(["info", str(photos)]) == 0
    out = capsys.readouterr().out
    assert f"photos     3 in {photos / 'images'} (no camera model yet" in out
    assert f"geocues sfm '{photos}' -o '{tmp_path / 'my photos_map'}'" in out
    (photos / "sparse" / "1").mkdir(parents=True)  # COLMAP's mapper left its model there: not "no model yet"
    (photos / "sparse" / "1" / "cameras.txt").write_text("# an empty model\n")
    assert main(["info", str(photos)]) == 1
    assert f"{photos / 'sparse' / '1'} holds a model: move (or link) it to" in capsys.readouterr().err


def test_info_counts_photos_the_model_does_not_use(tmp_path, capsys):
    """Photos added to images/ after SfM are ignored by every command: `geocues info` names them."""
    import shutil

    from cli.geocues_cli import main
    from cues_synth import make_room_scene

    root = make_room_scene(tmp_path / "room", n_views=4, w=64, h=48, priors="none")
    assert main(["info", str(root)]) == 0
    assert "not in the model" not in capsys.readouterr().out
    first = sorted((root / "images").iterdir())[0]
    shutil.copy(first, root / "images" / f"zz_added{first.suffix}")
    assert main(["info", str(root)]) == 0
    out = capsys.readouterr().out
    assert f"photos     1 in {root / 'images'} are not in the model and are not used (zz_added" in out
    assert "photos added after SfM need `geocues sfm` again" in out
    (root / "scene.json").write_text('{"sfm_registered": {"images": 4, "photos": 5}}')  # sfm's own model
    assert main(["info", str(root)]) == 0
    out = capsys.readouterr().out
    assert "`geocues sfm` could not register them" in out and "added after SfM" not in out
