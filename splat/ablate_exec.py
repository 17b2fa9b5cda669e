"""How `splat ablate` runs its rows: one after another, in worker processes (``jobs``) with a
progress bar per row drawn here, or as Ray tasks (``ray``: "auto", "local" or a cluster address)."""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import signal
import threading
import time
from pathlib import Path
from typing import Callable

from geocues.logs import LevelFormatter
from splat.checkpoint import TrainingInterrupted


def execute(todo: list[dict], on_done: Callable[[dict, dict], None], run_row: Callable[[dict], dict], *,
            jobs: int = 1, num_threads: int = 0, ray: str | None = None) -> None:
    """``on_done(spec, run_row(spec | {"threads": n}))`` for every spec of ``todo``, as each finishes.
    ``run_row`` must be a module-level function (it is pickled to the workers)."""
    if not todo:
        return
    if ray is not None:
        import ray as ray_  # optional extra: pip install .[ray]

        if not ray_.is_initialized():
            ray_.init(address=None if ray == "local" else ray)
        threads = num_threads or 1
        remote = ray_.remote(num_cpus=threads)(run_row)
        pending = {remote.remote({**spec, "threads": threads}): spec for spec in todo}
        while pending:
            ready, _ = ray_.wait(list(pending), num_returns=1)
            spec = pending.pop(ready[0])
            on_done(spec, ray_.get(ready[0]))
        return
    if jobs == 1:
        for spec in todo:
            on_done(spec, run_row({**spec, "threads": num_threads or None}))
        return
    import concurrent.futures as cf
    import multiprocessing as mp

    from tqdm import tqdm

    threads = num_threads or max(1, (os.cpu_count() or 1) // jobs)
    ctx = mp.get_context("spawn")
    stop = ctx.Event()  # set when the command is stopped: a worker starts no further row
    with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_worker_init,
                                initargs=(stop,)) as pool:
        futures = {pool.submit(_start_row, run_row, {**spec, "threads": threads}): spec for spec in todo}
        # The workers draw no bars (parallel bars interleave): one bar per row here, read from the
        # step its run last logged.
        bars = {fut: tqdm(total=spec["train_config"]["iters"], desc=f"{spec['row']} s{spec['seed']}",
                          unit="it", position=i, leave=True) for i, (fut, spec) in enumerate(futures.items())}
        pending = set(futures)
        try:
            while pending:
                done, pending = cf.wait(pending, timeout=2.0, return_when=cf.FIRST_COMPLETED)
                for fut in pending:
                    bars[fut].update(max(0, logged_step(futures[fut]) - bars[fut].n))
                for fut in done:
                    bar = bars[fut]
                    bar.update(bar.total - bar.n)
                    bar.set_postfix_str("scored")
                    on_done(futures[fut], fut.result())
        except BaseException as exc:  # Ctrl-C, SIGTERM, a row that failed: stop the other rows too
            stop.set()
            _stop_workers(pool, pending)
            if isinstance(exc, KeyboardInterrupt):
                name = exc.args[0] if exc.args else "SIGINT"
                raise TrainingInterrupted(f"stopped by {name}; the running rows wrote their checkpoints",
                                          name) from None
            raise
        finally:
            for bar in bars.values():
                bar.close()


def _stop_workers(pool, pending: set) -> None:
    """SIGTERM to every worker (each in a session of its own, so a terminal's Ctrl-C reached only
    this process): a row in training finishes its step and writes its checkpoint, a row being scored
    stops. Waits for them, so nothing is left writing when the command returns."""
    import concurrent.futures as cf

    for fut in pending:
        fut.cancel()  # rows not handed to a worker yet
    for proc in list(getattr(pool, "_processes", {}).values()):
        if proc.is_alive():
            try:
                os.kill(proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    cf.wait(pending)


def logged_step(spec: dict) -> int:
    """The last step a row's (unfinished or finished) run wrote to its train_log.jsonl, 0 if none."""
    for name in ("train.partial", "train"):
        try:
            with open(Path(spec["out"]) / name / "train_log.jsonl", "rb") as f:
                f.seek(0, 2)
                f.seek(max(0, f.tell() - 4096))
                for line in reversed(f.read().splitlines()):
                    try:
                        return int(json.loads(line)["step"]) + 1
                    except (ValueError, KeyError, TypeError):
                        continue
        except OSError:
            continue
    return 0


_STOP = None  # in a worker: the parent's stop event
_PARENT = None  # in a worker: the command's process id


def exit_with_parent(parent: int, every: float = 1.0, grace: float = 120.0) -> None:
    """In a worker: once ``parent`` is gone, SIGTERM to itself (a row in training writes its checkpoint
    and stops), and leave after ``grace`` seconds whatever it does. Killed outright (SIGKILL, the OOM
    killer), the command sends its workers nothing, and their own sessions keep a group kill from them:
    they trained on as orphans beside the rerun's workers on the same rows, then waited forever to hand
    in their results (kill audit)."""
    while os.getppid() == parent:
        time.sleep(every)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(grace)
    os._exit(1)


def _start_row(run_row: Callable[[dict], dict], spec: dict) -> dict:
    """``run_row(spec)`` in a worker, unless the command was stopped before the row started; a worker
    whose command is gone by the end of the row leaves at once (nobody will read its result)."""
    if _STOP is not None and _STOP.is_set():
        raise TrainingInterrupted(f"{spec['row']} seed {spec['seed']} not started: the command was stopped")
    try:
        return run_row(spec)
    finally:
        if _PARENT is not None and os.getppid() != _PARENT:
            os._exit(1)


def _worker_init(stop=None) -> None:
    from functools import partialmethod

    import tqdm

    global _STOP, _PARENT
    parent = multiprocessing.parent_process()  # the command, even if it died before this ran (getppid: 1 then)
    _STOP, _PARENT = stop, parent.pid if parent is not None else os.getppid()

    os.setsid()  # a terminal's Ctrl-C goes to the parent alone, which stops each worker once (_stop_workers)
    threading.Thread(target=exit_with_parent, args=(_PARENT,), daemon=True, name="exit-with-parent").start()

    tqdm.tqdm.__init__ = partialmethod(tqdm.tqdm.__init__, disable=True)  # bars of parallel rows interleave
    handler = logging.StreamHandler()
    handler.setFormatter(LevelFormatter())
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
