"""What a hard kill (SIGKILL, the OOM killer: no handler runs) leaves is named or cleaned up: an
extract killed among its writes, and `splat ablate`'s worker processes when the command is killed
(the kill audit; `geocues mvs` killed among its writes: tests/test_mvs.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

from cues_synth import make_room_scene
from geocues.cue_io import unfinished_extract, write_cues_ply
from test_train import surface_cues


def test_training_on_the_cues_of_an_unfinished_extract_is_warned_about(tmp_path, caplog):
    """`geocues extract --overwrite` with other options, killed among its writes, left a new cues.ply
    beside the old plane anchors and alignments and no report.json (which it removes first and writes
    last): `splat train` took the mix without a word."""
    from splat.train import TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=6, w=64, h=48)
    cues = tmp_path / "cues"
    write_cues_ply(cues / "cues.ply", surface_cues(root, n_plane=500))
    assert unfinished_extract(cues) is None  # a cues.ply made otherwise: nothing to say
    (cues / "plane_anchors.npz").write_bytes(b"")  # the files of an earlier extract
    (cues / "depth_alignments.json").write_text("{}")
    said = unfinished_extract(cues / "cues.ply")
    assert said is not None and "(plane_anchors.npz, depth_alignments.json) but not the report.json" in said
    with caplog.at_level("WARNING"):
        run(TrainConfig(iters=2, mesh=False, test_every=0, checkpoints=(1.0,), loss=_no_anchor()), root,
            cues / "cues.ply", tmp_path / "run")
    assert said in caplog.text
    (cues / "report.json").write_text(json.dumps({}))  # finished
    assert unfinished_extract(cues) is None


def _no_anchor():
    from splat.losses import LossConfig

    return LossConfig(lambda_anchor=0.0)


CHILD = """
import os, signal, sys, time
from splat.ablate_exec import exit_with_parent
import threading
marker = sys.argv[1]
signal.signal(signal.SIGTERM, lambda *a: (open(marker, "w").write("stopped"), os._exit(0)))
threading.Thread(target=exit_with_parent, args=(os.getppid(), 0.05, 5.0), daemon=True).start()
print(os.getpid(), flush=True)
time.sleep(60)
"""

PARENT = """
import subprocess, sys
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], sys.argv[2]], stdout=subprocess.PIPE, text=True)
print(child.stdout.readline().strip(), flush=True)
child.wait()
"""


def test_an_ablate_worker_stops_when_its_command_is_killed_outright(tmp_path):
    """`splat ablate --jobs 2` killed with SIGKILL (its workers in sessions of their own, so a group kill
    missed them too) left both workers training on as orphans beside the rerun's workers, then waiting
    forever to hand in their results. A worker whose parent is gone stops as on SIGTERM (a training row
    writes its checkpoint) and leaves."""
    marker = tmp_path / "stopped"
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, str(marker)], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    child = int(parent.stdout.readline())
    assert not marker.exists()
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 20
    while not marker.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert marker.read_text() == "stopped"
    while time.monotonic() < deadline:  # and it leaves (a zombie of whoever adopted it at most)
        try:
            with open(f"/proc/{child}/status") as f:
                if "\nState:\tZ" in f.read():
                    break
        except FileNotFoundError:
            break
        time.sleep(0.05)
    else:
        raise AssertionError(f"worker {child} still runs")
