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
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, str(marker)], stdout=subprocess.PIPE, text=True,
                              env=env)
    child = int(parent.stdout.readline())
    try:
        assert not marker.exists()
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 20
        while not marker.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert marker.read_text() == "stopped"
    finally:
        try:
            os.kill(child, signal.SIGKILL)  # gone already, unless the test failed
        except ProcessLookupError:
            pass
    # a worker whose row ends after its command is gone leaves at once (nobody reads the result), one
    # whose command lives returns it
    row = ("import os, splat.ablate_exec as m; m._PARENT = {}; "
           "print('returned', m._start_row(lambda spec: 7, {{'row': 'r', 'seed': 0}}))")
    gone = subprocess.run([sys.executable, "-c", row.format(-5)], capture_output=True, text=True, env=env)
    alive = subprocess.run([sys.executable, "-c", row.format("os.getppid()")], capture_output=True, text=True, env=env)
    assert (gone.returncode, gone.stdout) == (1, "") and (alive.returncode, alive.stdout) == (0, "returned 7\n")


def test_a_run_killed_while_published_is_published_by_the_rerun(tmp_path, caplog):
    """Killed between its report.json (written last) and the rename of OUT.partial onto OUT, a finished
    run was taken for an unfinished one: the rerun removed it ("removing the unfinished run") and trained
    again; under --overwrite, killed between replace_dir's two renames, the old run stayed as a hidden
    .OUT.old. The rerun publishes it and removes what it replaced; the same command then ends as done,
    one with other options says OUT holds a finished run."""
    import pytest

    from splat.train import TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=6, w=64, h=48)
    write_cues_ply(tmp_path / "cues" / "cues.ply", surface_cues(root, n_plane=500))
    cfg = TrainConfig(iters=2, mesh=False, test_every=0, checkpoints=(1.0,), loss=_no_anchor())
    out = tmp_path / "run"
    run(cfg, root, tmp_path / "cues", out)
    made = (out / "point_cloud.ply").read_bytes()
    (out / "ckpt").mkdir()  # killed before the checkpoint was removed, too
    out.rename(tmp_path / "run.partial")  # the state of the kill
    (tmp_path / ".run.old").mkdir()  # and the run an --overwrite was replacing
    folder = (tmp_path / "run.partial").stat().st_ino  # a run trained again would be published as another folder
    caplog.clear()  # the first training's lines
    with caplog.at_level("INFO", logger="splat"):  # (an earlier CLI test may have left splat at WARNING)
        assert run(cfg, root, tmp_path / "cues", out) == out
    assert "run.partial held a finished run (killed while it was moved into place): published to" in caplog.text
    assert "done: the run had finished before the kill" in caplog.text and "training 2 iterations" not in caplog.text
    assert out.stat().st_ino == folder
    assert (out / "point_cloud.ply").read_bytes() == made and not (tmp_path / "run.partial").exists()
    assert not (out / "ckpt").exists() and not (tmp_path / ".run.old").exists()
    out.rename(tmp_path / "run.partial")
    with pytest.raises(ValueError, match="holds a finished run; pass --overwrite"):  # another run's options
        run(TrainConfig(iters=3, mesh=False, test_every=0, checkpoints=(1.0,), loss=_no_anchor()), root,
            tmp_path / "cues", out)
    assert (out / "point_cloud.ply").read_bytes() == made


def test_a_checkpoint_reaches_the_disk_before_its_rename(tmp_path, monkeypatch):
    """A power cut after the rename of an unsynced checkpoint can leave an empty last.pt (the run then
    cannot resume: "not a readable training checkpoint"): checkpoints are fsynced before the rename and
    their folder after it; other atomic writes (per-image caches) are not worth the wait."""
    from geocues import atomic
    from splat import checkpoint

    synced = []
    real = os.fsync
    monkeypatch.setattr(atomic.os, "fsync", lambda fd: (synced.append(os.fstat(fd).st_ino), real(fd)))
    with atomic.atomic_path(tmp_path / "cache.npy") as tmp:
        tmp.write_bytes(b"x")
    assert synced == []
    checkpoint.save(tmp_path / "ckpt" / "last.pt", {"step": 3}, {})
    assert synced == [(tmp_path / "ckpt" / "last.pt").stat().st_ino, (tmp_path / "ckpt").stat().st_ino]
    assert checkpoint.torch.load(tmp_path / "ckpt" / "last.pt", weights_only=False)["step"] == 3


def test_a_second_run_into_the_same_out_is_refused_while_the_first_runs(tmp_path):
    """Two `splat train -o OUT` at once: the second removed the first's unfinished OUT.partial, or (with
    the publishing of a finished one) published it under the first, which then failed to and lost it
    (review). OUT is locked while a run writes it, and the lock goes with the run."""
    import pytest

    from geocues.atomic import output_lock
    from splat.train import TrainConfig, run

    root = make_room_scene(tmp_path / "room", n_views=6, w=64, h=48)
    write_cues_ply(tmp_path / "cues" / "cues.ply", surface_cues(root, n_plane=500))
    cfg = TrainConfig(iters=2, mesh=False, test_every=0, checkpoints=(1.0,), loss=_no_anchor())
    out = tmp_path / "run"
    with output_lock(out, "splat train"):  # the first run, still writing
        with pytest.raises(ValueError, match=r"another splat train is writing .*run now \(it holds .*\.run\.lock\)"):
            run(cfg, root, tmp_path / "cues", out)
        assert not (tmp_path / "run.partial").exists()
    run(cfg, root, tmp_path / "cues", out)
    assert (out / "report.json").is_file() and not (tmp_path / ".run.lock").exists()


def test_the_lock_leaves_nothing_and_stands_aside_for_the_path_checks(tmp_path):
    """The lock is made beside OUT before the command's checks: a command that fails leaves neither the
    lock nor the folders made for it, and an OUT under a file still gets the command's one line (the lock
    first raised FileExistsError with a traceback)."""
    import pytest

    from geocues.atomic import check_output_dir, output_lock

    with pytest.raises(ValueError, match="bad scene"), output_lock(tmp_path / "new" / "deep" / "run", "splat train"):
        assert (tmp_path / "new" / "deep" / ".run.lock").is_file()
        raise ValueError("bad scene")
    assert not (tmp_path / "new").exists()
    (tmp_path / "afile").write_text("")
    with pytest.raises(ValueError, match="afile is a file, not a folder"), output_lock(tmp_path / "afile" / "run", "x"):
        check_output_dir(tmp_path / "afile" / "run")
