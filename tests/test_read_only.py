"""A read-only output folder: every command that writes stops before any work with one line naming
the folder, exit code != 0, no traceback, and an earlier good output in it is kept.

The tests run as root, which ignores file permissions; the commands therefore run in a child
process without CAP_DAC_OVERRIDE (``setpriv --bounding-set``), which makes permissions bind root
as they bind any user."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cues_synth import make_room_scene
from geocues.cue_io import CueCloud, write_cues_ply

REPO = Path(__file__).resolve().parents[1]

CHILD = """
import contextlib, io, json, sys
from cli.evaluate_cli import main as evaluate
from cli.geocues_cli import main as geocues
from cli.splat_cli import main as splat
mains = {"geocues": geocues, "splat": splat, "evaluate": evaluate}
results = []
for prog, *args in json.loads(sys.argv[1]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = mains[prog](args)
    results.append({"cmd": [prog, *args], "code": code, "err": err.getvalue()})
print(json.dumps(results))
"""


def _unprivileged() -> list[str]:
    if os.geteuid() != 0:
        return []
    if shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv (util-linux): permissions cannot bind root here")
    return ["setpriv", "--bounding-set=-dac_override,-dac_read_search"]


def _run(cmds: list[list[str]], home: Path) -> list[dict]:
    env = dict(os.environ, INDOORGS_CACHE=str(home / "cache"), MPLCONFIGDIR=str(home / "mpl"))
    proc = subprocess.run([*_unprivileged(), sys.executable, "-c", CHILD, json.dumps(cmds)], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_read_only_output_folders(tmp_path):
    root = make_room_scene(tmp_path / "room", n_views=8, w=64, h=48, priors="all")
    write_cues_ply(tmp_path / "cues" / "cues.ply",
                   CueCloud.make(np.random.default_rng(0).uniform(0, 3, (200, 3)), np.full((200, 3), 0.5), 2))
    ro = tmp_path / "ro"
    kept = ro / "old_cues"
    kept.mkdir(parents=True)
    (kept / "cues.ply").write_bytes(b"an earlier good result")
    (tmp_path / "home").mkdir()
    os.chmod(kept, 0o555)
    os.chmod(ro, 0o555)
    try:
        results = _run([
            ["geocues", "extract", str(root), "-o", str(ro / "cues")],
            ["geocues", "extract", str(root), "-o", str(kept), "--overwrite"],
            ["geocues", "sfm", str(root), "-o", str(ro / "sfm")],
            ["splat", "train", str(root), "-c", str(tmp_path / "cues"), "-o", str(ro / "run"), "--iters", "2"],
            ["splat", "ablate", str(root), "-c", str(tmp_path / "cues"), "-o", str(ro / "abl"), "--iters", "2"],
            ["evaluate", "make-room", str(ro / "room")],
        ], tmp_path / "home")
    finally:
        os.chmod(ro, 0o755)
        os.chmod(kept, 0o755)
    for r in results:
        errors = [line for line in r["err"].splitlines() if ": error: " in line]
        assert r["code"] not in (0, None), r
        assert len(errors) == 1 and "Traceback" not in r["err"], r
        assert "cannot write the output folder" in errors[0] and "not writable" in errors[0], errors[0]
        assert str(ro) in errors[0], errors[0]
        # stopped before any work: no per-image progress, nothing but the probe ever touched RO
        assert "lines: 2D segments" not in r["err"] and "training" not in r["err"], r
    assert sorted(p.name for p in ro.iterdir()) == ["old_cues"]
    assert (kept / "cues.ply").read_bytes() == b"an earlier good result"
