"""Training state: capture it, restore it, and keep it on disk so a run can resume.

A state holds everything the next iteration depends on: the Gaussians with ``cue_type``, every Adam
moment, the density-control accumulators, the step, the view order, every random generator (torch
global, the loss-patch generator, numpy's view-order generator), the learning-rate multipliers of
the numerics guard, the accuracy-against-time curve so far, the training seconds, and the byte
length of ``train_log.jsonl`` at that step (a resumed run cuts the log back to it, so no line is
written twice). ``capture`` clones the tensors (an in-memory snapshot the guard rolls back to);
``save`` writes one atomically as ``ckpt/last.pt`` with the run's config beside it.
"""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from geocues.atomic import atomic_path

log = logging.getLogger(__name__)

CKPT_NAME = "ckpt/last.pt"
FORMAT = 1


def capture(params, optimizers: dict, strategy_state: dict, extra: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of the training state (tensors cloned; safe to keep while training goes on)."""
    return {
        "format": FORMAT,
        "params": {k: v.detach().clone() for k, v in params.items()},
        "optimizers": {k: copy.deepcopy(opt.state_dict()) for k, opt in optimizers.items()},
        "strategy_state": {k: v.clone() if isinstance(v, torch.Tensor) else copy.deepcopy(v)
                           for k, v in strategy_state.items()},
        "torch_rng": torch.get_rng_state(),
        **copy.deepcopy(extra),
    }


def restore(snapshot: dict[str, Any], params, optimizers: dict, strategy_state: dict) -> dict[str, Any]:
    """Put ``snapshot``'s Gaussians, Adam states and density state back in place (the parameter
    objects are replaced, as density control does); returns the snapshot's other entries."""
    for key, value in snapshot["params"].items():
        params[key] = torch.nn.Parameter(value.clone().to(params[key].device))
        opt = optimizers[key]
        opt.param_groups[0]["params"] = [params[key]]
        opt.state.clear()
        sd = copy.deepcopy(snapshot["optimizers"][key])
        sd["param_groups"][0]["params"] = [0]
        opt.load_state_dict(sd)
    strategy_state.clear()
    for key, value in snapshot["strategy_state"].items():
        strategy_state[key] = value.clone() if isinstance(value, torch.Tensor) else copy.deepcopy(value)
    torch.set_rng_state(snapshot["torch_rng"])
    skip = {"format", "params", "optimizers", "strategy_state", "torch_rng"}
    return {k: copy.deepcopy(v) for k, v in snapshot.items() if k not in skip}


def save(path: str | Path, snapshot: dict[str, Any], config: dict) -> Path:
    """Write ``snapshot`` and the run's config atomically and durably (torch.save, fsync, then rename:
    a power cut leaves the previous checkpoint or this one)."""
    path = Path(path)
    with atomic_path(path, durable=True) as tmp:
        torch.save({**snapshot, "config": config}, tmp)
    log.info("checkpoint at step %d: %s", snapshot.get("step", -1), path)
    return path


def load(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save`; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path} (nothing to resume)")
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # a truncated or foreign file
        raise ValueError(f"{path} is not a readable training checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path} is not a training checkpoint of this version (format {FORMAT})")
    return data


def config_value(config: dict, dotted: str) -> Any:
    """The value at the dotted path ``dotted`` ("strategy.max_gaussians") of a nested config dict, or None."""
    node: Any = config
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


def config_diff(cfg_dict: dict, saved: dict, defaults: dict | None = None) -> list[str]:
    """Options (dotted paths) whose values differ between a config (``asdict(cfg)``) and the one a
    checkpoint was written with (compared as JSON, so tuples and lists agree); [] when equal. With
    ``defaults`` (``asdict`` of the default config), an option the checkpoint does not record and
    this config leaves at its default is not a difference: it was added to the toolkit after the
    checkpoint was written, and its default keeps the training the checkpoint's (an upgrade between
    a kill and the resume must not throw the run away)."""
    now, then = json.loads(json.dumps(cfg_dict)), json.loads(json.dumps(saved))
    dflt = json.loads(json.dumps(defaults)) if defaults is not None else {}

    def diff(a: dict, b: dict, d: dict, prefix: str) -> list[str]:
        out = []
        for k, v in a.items():
            if k not in b:
                if not (k in d and v == d[k]):
                    out.append(prefix + k)
            elif isinstance(v, dict) and isinstance(b[k], dict):
                out += diff(v, b[k], d.get(k) if isinstance(d.get(k), dict) else {}, f"{prefix}{k}.")
            elif v != b[k]:
                out.append(prefix + k)
        return out + [prefix + k for k in b if k not in a]

    return diff(now, then, dflt, "")


def numpy_rng_state(rng: np.random.Generator) -> dict:
    return copy.deepcopy(rng.bit_generator.state)


def set_numpy_rng_state(rng: np.random.Generator, state: dict) -> None:
    rng.bit_generator.state = copy.deepcopy(state)


class TrainingInterrupted(RuntimeError):
    """SIGINT / SIGTERM stopped the run after its checkpoint was written (the message says where).
    ``signal_name`` is the signal that stopped it: the command's exit code is 128 + its number (130
    for Ctrl-C, 143 for SIGTERM), as a shell reports a process the signal ended."""

    def __init__(self, message: str, signal_name: str = "SIGINT") -> None:
        super().__init__(message)
        self.signal_name = signal_name if signal_name in ("SIGINT", "SIGTERM") else "SIGINT"

    def __reduce__(self):  # across the process pool of `splat ablate --jobs` with its signal
        return type(self), (str(self), self.signal_name)

    @property
    def exit_code(self) -> int:
        return 143 if self.signal_name == "SIGTERM" else 130


class SignalCatcher:
    """Within the block, SIGINT and SIGTERM set ``caught`` (the signal's name) instead of killing
    the process, so the loop can finish its step and write a checkpoint; a second signal while the
    first is being handled stops at once (KeyboardInterrupt). Only in the main thread."""

    def __init__(self) -> None:
        self.caught: str | None = None
        self._old: dict = {}

    def _handle(self, signum, frame) -> None:
        import signal

        if self.caught is not None:
            raise KeyboardInterrupt(signal.Signals(signum).name)
        self.caught = signal.Signals(signum).name
        log.warning("%s received: stopping after this step and writing a checkpoint", self.caught)

    def __enter__(self) -> "SignalCatcher":
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        import signal

        for sig, handler in self._old.items():
            signal.signal(sig, handler)


def staging_dir(out_dir: Path) -> Path:
    """Where a run into ``out_dir`` works until it is complete: ``OUT.partial`` beside it."""
    out_dir = Path(out_dir)
    return out_dir.with_name(out_dir.name + ".partial")


def publish(work: Path, out_dir: Path) -> Path:
    """Rename the finished ``work`` folder onto ``out_dir`` (geocues.atomic.replace_dir: a previous
    run there is moved aside first and removed after)."""
    from geocues.atomic import replace_dir

    return replace_dir(work, out_dir)
