"""The `--overwrite` guard in every command (issue 14, one CLI style): a command pointed at a finished
output stops before any work with one error line that says `--overwrite`, exit code 1, the output
untouched; with `--overwrite` it is replaced (checked end to end for the cheap commands).
`splat ablate` is the exception: running it again resumes (tests/test_ablate.py covers its
`--overwrite`, which starts again from nothing)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cues_synth import make_room_scene, room_mesh
from geocues.cue_io import CueCloud, write_cues_ply

OLD = "an earlier finished output"


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    import open3d as o3d

    base = tmp_path_factory.mktemp("guard")
    root = make_room_scene(base / "room", n_views=6, w=64, h=48, priors="none")
    V, T, _ = room_mesh()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
    (root / "gt").mkdir()
    o3d.io.write_triangle_mesh(str(root / "gt" / "mesh.ply"), mesh)
    write_cues_ply(base / "cues" / "cues.ply",
                   CueCloud.make(np.random.default_rng(0).uniform(0, 3, (200, 3)), np.full((200, 3), 0.5), 2))
    run = base / "run"  # a finished `splat train` folder as far as the guards look
    run.mkdir()
    (run / "report.json").write_text("{}")
    return base, root


def _main(prog: str):
    from cli.evaluate_cli import main as evaluate
    from cli.geocues_cli import main as geocues
    from cli.splat_cli import main as splat

    return {"geocues": geocues, "splat": splat, "evaluate": evaluate}[prog]


def _finished(path, kind: str):
    """Put an earlier finished output at ``path``: a file, or a folder holding ``kind``."""
    if kind == "file":
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(OLD)
        return path
    path.mkdir(parents=True, exist_ok=True)
    marker = path / kind
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"config_key": "another configuration"}) if kind == "report.json"
                      else json.dumps({"rescaled": {"scale": 3.0}, "priors": {"simulated": True}}) if kind == "scene.json"
                      else OLD)  # scene.json: what rescale / simulate-priors write into theirs
    return marker


# (command, output to put there first and what marks it finished); {R} the scene, {B} the base folder
CASES = [
    (["geocues", "sfm", "{R}", "-o", "{B}/sfm"], "{B}/sfm", "sfm_report.json"),
    (["geocues", "undistort", "{R}", "-o", "{B}/und"], "{B}/und", "sparse/0/cameras.txt"),
    (["geocues", "mvs", "{R}", "-o", "{B}/mvs"], "{B}/mvs", "mvs_report.json"),
    (["geocues", "rescale", "{R}", "-o", "{B}/metric", "--scale", "2"], "{B}/metric", "scene.json"),
    (["geocues", "extract", "{R}", "-o", "{B}/cues_old"], "{B}/cues_old", "report.json"),
    (["splat", "train", "{R}", "-c", "{B}/cues", "-o", "{B}/train", "--iters", "2"], "{B}/train", "cfg_args"),
    (["splat", "render", "{B}/run", "-o", "{B}/renders"], "{B}/renders", "views.json"),
    (["splat", "mesh", "{B}/run", "-o", "{B}/remesh.ply"], "{B}/remesh.ply", "file"),
    (["splat", "bench", "-o", "{B}/bench.json", "--sizes", "8", "8", "--counts", "10"], "{B}/bench.json", "file"),
    (["splat", "view", "{B}/run", "--screenshot", "{B}/view.png"], "{B}/view.png", "file"),
    (["evaluate", "{R}/gt/mesh.ply", "{R}", "-o", "{B}/metrics.json"], "{B}/metrics.json", "file"),
    (["evaluate", "mesh", "{R}/gt/mesh.ply", "{R}", "-o", "{B}/metrics2.json"], "{B}/metrics2.json", "file"),
    (["evaluate", "cues", "{B}/cues", "{R}", "-o", "{B}/cue_metrics.json"], "{B}/cue_metrics.json", "file"),
    (["evaluate", "report", "{B}/run"], "{B}/run", "report.md"),
    (["evaluate", "make-room", "{B}/made", "--no-sfm"], "{B}/made", "make_room_report.json"),
]


def _case_id(cmd: list[str]) -> str:
    return " ".join(cmd[:2]) if not cmd[1].startswith("{") else f"{cmd[0]} (default command)"


@pytest.mark.parametrize("cmd, out, kind", CASES, ids=[_case_id(c[0]) for c in CASES])
def test_a_finished_output_needs_overwrite(room, capsys, cmd, out, kind):
    base, root = room
    fill = {"{R}": str(root), "{B}": str(base)}

    def sub(a: str) -> str:
        for k, v in fill.items():
            a = a.replace(k, v)
        return a

    marker = _finished(Path(sub(out)), kind)
    before = marker.read_text()
    prog, *args = [sub(a) for a in cmd]
    code = _main(prog)(args)
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert code == 1, err
    assert len(errors) == 1 and "Traceback" not in err, err
    assert "--overwrite" in errors[0], errors[0]
    assert marker.read_text() == before  # untouched


def test_overwrite_replaces_the_output(room, capsys):
    """The cheap commands, end to end: with --overwrite the earlier output is replaced."""
    base, root = room
    for prog, args, out in [
        ("evaluate", [str(root / "gt" / "mesh.ply"), str(root), "-o", str(base / "m.json"), "--n-samples", "5000",
                      "--mode", "surface"],
         base / "m.json"),
        ("evaluate", ["cues", str(base / "cues"), str(root), "-o", str(base / "c.json"), "--n-gt-samples", "5000"],
         base / "c.json"),
        ("geocues", ["rescale", str(root), "-o", str(base / "r"), "--scale", "2"], base / "r" / "scene.json"),
    ]:
        marker = _finished(out.parent, out.name) if out.name == "scene.json" else _finished(out, "file")
        before = marker.read_text()
        assert _main(prog)(args) == 1
        assert out.read_text() == before
        assert _main(prog)(args + ["--overwrite"]) == 0, capsys.readouterr().err
        data = json.loads(out.read_text())  # a whole new JSON file, not the old text
        assert data and out.read_text() != before
    assert json.loads((base / "m.json").read_text())["chamfer_l1"] < 1e-4  # the GT against itself
    assert json.loads((base / "r" / "scene.json").read_text())["rescaled"]["scale"] == 2.0
    assert sorted(p.name for p in (base / "r").iterdir()) == ["gt", "images", "scene.json", "sparse"]
    assert not list(base.glob(".*"))  # no temporary sibling left behind


# A command pointed at its own input, or at a folder holding it: refused with --overwrite too, the input
# untouched (`splat train SCENE -c CUES -o SCENE --overwrite` deleted the scene; `splat render RUN -o RUN
# --overwrite` the run). {R} the scene, {B} the base folder holding it and the cues, {B}/run a run.
INPUT_CASES = [
    (["splat", "train", "{R}", "-c", "{B}/cues", "-o", "{R}", "--iters", "2"], "the scene"),
    (["splat", "train", "{R}", "-c", "{B}/cues", "-o", "{B}", "--iters", "2"], "the scene"),
    (["splat", "train", "{R}", "-c", "{B}/cues", "-o", "{B}/cues", "--iters", "2"], "the cues"),
    (["splat", "render", "{B}/run", "-o", "{B}/run"], "the run"),
    (["geocues", "rescale", "{R}", "-o", "{B}", "--scale", "2"], "the scene"),
    (["geocues", "sfm", "{R}", "-o", "{B}"], "the scene"),
    (["geocues", "mvs", "{R}", "-o", "{B}"], "the scene"),
    (["geocues", "undistort", "{R}", "-o", "{B}"], "the scene"),
    (["evaluate", "simulate-priors", "{R}", "-o", "{B}"], "the scene"),
    (["geocues", "extract", "{R}", "-o", "{R}"], "the scene"),
    # inside the photos: the output's files would be taken for photos (sfm -o SCENE/images/map wrote a
    # scene there, linking images/images to itself)
    (["geocues", "sfm", "{R}", "-o", "{R}/images/map"], "the scene's photos folder"),
    (["geocues", "extract", "{R}", "-o", "{R}/images/cues"], "the scene's photos folder"),
]


def _tree(folder: Path) -> list[tuple[str, int]]:
    return sorted((str(p.relative_to(folder)), p.stat().st_size) for p in folder.rglob("*") if p.is_file())


@pytest.mark.parametrize("cmd, named", INPUT_CASES, ids=[" ".join(c[0][:2]) + f" -o {c[0][c[0].index('-o') + 1]}"
                                                         for c in INPUT_CASES])
def test_an_output_that_is_or_holds_an_input_is_refused_even_with_overwrite(room, capsys, cmd, named):
    base, root = room
    before = _tree(base)
    prog, *args = [a.replace("{R}", str(root)).replace("{B}", str(base)) for a in cmd]
    code = _main(prog)(args + ["--overwrite"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err, err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1 and named in errors[0] and "choose another output folder" in errors[0], err
    assert _tree(base) == before  # nothing deleted, nothing added


@pytest.mark.parametrize("prog, args", [
    ("splat", ["train", "{R}", "-c", "{B}/cues", "--iters", "2"]),
    ("splat", ["render", "{B}/run"]),
    ("evaluate", ["make-room", "--no-sfm"]),
    ("geocues", ["rescale", "{R}", "--scale", "2"]),
], ids=["splat train", "splat render", "evaluate make-room", "geocues rescale"])
@pytest.mark.parametrize("overwrite", [False, True])
def test_a_folder_that_is_not_the_commands_output_is_never_replaced(room, capsys, prog, args, overwrite):
    """These commands replace their output folder whole: a folder of other files (a user's notes,
    other runs) is refused with and without --overwrite, where `splat train -o FOLDER` deleted them."""
    base, root = room
    other = base / f"someone_else_{prog}_{args[0]}_{overwrite}"
    (other / "another_run").mkdir(parents=True)
    (other / "notes.txt").write_text("mine")
    args = [a.replace("{R}", str(root)).replace("{B}", str(base)) for a in args]
    args = args[:1] + [str(other)] + args[1:] if args[0] == "make-room" else args + ["-o", str(other)]
    code = _main(prog)(args + (["--overwrite"] if overwrite else []))
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err, err
    assert "choose a new or empty folder" in err and "notes.txt" in err, err
    assert (other / "notes.txt").read_text() == "mine" and (other / "another_run").is_dir()


def test_the_guard_is_not_fooled_by_lookalike_or_hidden_folders(room, capsys):
    """A review found three holes: an extract's folder has a report.json too (splat train took it for a
    run and replaced it with --overwrite), a folder holding only .git was replaced without
    --overwrite, and every user scene has a scene.json (rescale replaced one with --overwrite), or
    is the source a derived scene's images/ link to (rescale DERIVED -o SOURCE deleted the photos)."""
    import shutil

    base, root = room
    cues_like = base / "an_extract"
    cues_like.mkdir()
    (cues_like / "report.json").write_text(json.dumps({"config_key": "x"}))
    dot_git = base / "a_repo"
    (dot_git / ".git").mkdir(parents=True)
    (dot_git / ".git" / "HEAD").write_text("ref")
    user_scene = base / "user_scene"
    shutil.copytree(root, user_scene)
    (user_scene / "scene.json").write_text(json.dumps({"depth_png_scale": 1000}))
    derived = base / "derived"
    assert _main("geocues")(["rescale", str(user_scene), "-o", str(derived), "--scale", "2"]) == 0
    assert (derived / "images").is_symlink()
    capsys.readouterr()
    for prog, args, kept in [
        ("splat", ["train", str(root), "-c", str(base / "cues"), "-o", str(cues_like), "--iters", "2", "--overwrite"],
         cues_like / "report.json"),
        ("splat", ["train", str(root), "-c", str(base / "cues"), "-o", str(dot_git), "--iters", "2"], dot_git / ".git" / "HEAD"),
        ("geocues", ["rescale", str(root), "-o", str(user_scene), "--scale", "2", "--overwrite"], user_scene / "scene.json"),
        ("geocues", ["rescale", str(derived), "-o", str(user_scene), "--scale", "2", "--overwrite"],
         next((user_scene / "images").iterdir())),
    ]:
        before = kept.read_bytes()
        assert _main(prog)(args) == 1, args
        err = capsys.readouterr().err
        assert "choose a" in err and "Traceback" not in err, err
        assert kept.read_bytes() == before
    from geocues.atomic import check_not_input

    with pytest.raises(ValueError, match="holds what the scene's (images|gt) links to"):  # the link guard on its own
        check_not_input(user_scene, {"scene": derived})
