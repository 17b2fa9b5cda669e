"""Guarded numerics for the training loop: find a bad step, say what went wrong, roll back.

Every iteration the trainer asks :meth:`NumericsGuard.check` whether the step it just took is
sound: a finite loss and finite loss terms, finite gradients (checked through their sums: one
NaN or Inf makes the sum non-finite), finite parameters after the optimizer step, a loss not far
above its running level (forgotten after each opacity reset of the density control, whose next
losses are high by design), and Gaussians still inside the scene's bounds. On the first bad step the
trainer rolls back to the last good snapshot and the guard lowers the learning rate of the
parameters that went wrong (all of them when it cannot tell); after ``max_rollbacks`` bad steps in
a row without passing the snapshot, training stops with :class:`TrainingDiverged`, which names what
went wrong and where the last good checkpoint is.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
from torch import Tensor

log = logging.getLogger(__name__)


class TrainingDiverged(RuntimeError):
    """Training could not be kept finite / bounded by rolling back and lowering learning rates."""


@dataclass
class GuardConfig:
    """The numerics guard of the training loop."""

    enabled: bool = True
    """Check every step and roll back bad ones (off: the plain loop, NaN and all)."""
    snapshot_every: int = 50
    """Keep an in-memory snapshot of the last good state every this many steps."""
    max_rollbacks: int = 5
    """Stop with an error after this many bad steps in a row (no good snapshot in between)."""
    lr_factor: float = 0.3
    """Multiply the learning rate of the offending parameters by this on each rollback."""
    spike_factor: float = 20.0
    """A loss above this times its running mean (after warm-up) is divergence."""
    max_outside: float = 0.25
    """Divergence when more than this fraction of the Gaussians leaves the scene bounds."""
    bounds_mult: float = 20.0
    """Scene bounds: the cue cloud's centre +- this times the scene scale."""

    def validate(self) -> None:
        """Raise ValueError naming the first impossible --guard.* setting (a NaN spike factor trained to
        the end and failed writing report.json; --guard.bounds-mult 0 'diverged' at step 0)."""
        if self.snapshot_every < 1 or self.max_rollbacks < 1:
            raise ValueError(f"--guard.snapshot-every and --guard.max-rollbacks must be >= 1, got "
                             f"{self.snapshot_every}, {self.max_rollbacks}")
        if not 0 < self.lr_factor < 1:
            raise ValueError(f"--guard.lr-factor must be in (0, 1), got {self.lr_factor}")
        if not (math.isfinite(self.spike_factor) and self.spike_factor > 1):
            raise ValueError(f"--guard.spike-factor is a multiple of the loss's running mean and must be a finite "
                             f"number > 1, got {self.spike_factor}")
        if not 0 < self.max_outside <= 1:
            raise ValueError(f"--guard.max-outside is a fraction of the Gaussians and must be in (0, 1], got "
                             f"{self.max_outside}")
        if not (math.isfinite(self.bounds_mult) and self.bounds_mult >= 1):
            raise ValueError(f"--guard.bounds-mult must be a finite number >= 1 (bounds smaller than the scene "
                             f"call its own Gaussians divergent), got {self.bounds_mult}")


def divergence_hint(event: dict) -> str:
    """What to change after a divergence, from its event: the loss terms that went bad first point at
    their weights and inputs (a prior of 1e30, --loss.lambda-depth 1e38), a loss spike at the weights,
    anything else at the learning rates first (the advice was the learning rates whatever the cause)."""
    if event.get("terms"):
        return (f"The loss term{'s' * (len(event['terms']) > 1)} {', '.join(map(str, event['terms']))} went bad first: "
                "check their weights (--loss.lambda-*) and what they read (the scene's depth/normal priors, the "
                "cues), then the learning rates (--lr.*)")
    if "running mean" in event["reason"]:
        return ("Lower their learning rates (--lr.*) or the loss weights you raised (--loss.lambda-*: a large "
                "weight makes the loss jump between views by nature; --guard.spike-factor tolerates more)")
    return ("Lower their learning rates (--lr.*), or check the loss weights you raised (--loss.lambda-*) and the "
            "inputs (the scene's priors, the cues, --background)")


def _not_finite(tensors: dict[str, Tensor], extra: Tensor | None = None) -> list:
    """The names of the tensors whose sum is not finite, in one copy from the device (one wait for a
    GPU, not one per tensor); with ``extra`` (a 0-dim tensor) its value is appended to the list."""
    flags = [torch.isfinite(t.sum()).logical_not().float() for t in tensors.values()]
    if extra is not None:
        flags.append(extra.float())
    values = torch.stack(flags).tolist() if flags else []
    bad = [k for k, v in zip(tensors, values) if v]
    return bad + (values[-1:] if extra is not None else [])


class NumericsGuard:
    """State of the guard over one run (module docstring)."""

    def __init__(self, cfg: GuardConfig, centre: Tensor, scene_scale: float) -> None:
        self.cfg = cfg
        self.centre = centre.detach().float()
        self.radius = cfg.bounds_mult * scene_scale
        self.loss_mean: float | None = None
        self.n_good = 0
        self.bad_in_row = 0
        self.lr_mult: dict[str, float] = {}
        self.events: list[dict] = []

    def check_step(self, step: int, loss: float, terms: dict[str, float], params) -> dict | None:
        """After backward, before the optimizer step: None if the loss, its terms and the gradients
        are finite and the loss is not far above its running level, else a report."""
        if not self.cfg.enabled:
            return None
        bad_terms = [k for k, v in terms.items() if not math.isfinite(v)]
        bad_grads = _not_finite({k: p.grad for k, p in params.items() if p.grad is not None})
        if not math.isfinite(loss) or bad_terms:
            return self._event(step, "non-finite loss", bad_terms, bad_grads, params, grads=True)
        if bad_grads:
            return self._event(step, "non-finite gradients", bad_terms, bad_grads, params, grads=True)
        if self.loss_mean is not None and self.n_good > 20 and loss > self.cfg.spike_factor * self.loss_mean:
            return self._event(step, f"loss {loss:.4g} is {loss / self.loss_mean:.0f}x its running mean "
                               f"{self.loss_mean:.4g}", [], [], params)
        self.loss_mean = loss if self.loss_mean is None else 0.98 * self.loss_mean + 0.02 * loss
        self.n_good += 1
        return None

    def check_params(self, step: int, params) -> dict | None:
        """After the optimizer step: None if every parameter is finite and the Gaussians stay
        inside the scene bounds, else a report."""
        if not self.cfg.enabled:
            return None
        means = params["means"].detach()
        outside = (means - self.centre).abs().amax(-1) > self.radius
        share = outside.float().mean() if len(means) else means.new_zeros(())
        bad_values = _not_finite({k: p.detach() for k, p in params.items()}, extra=share)
        share = bad_values.pop()
        if bad_values:
            return self._event(step, "non-finite parameters after the optimizer step", [], bad_values, params)
        if len(means) and share > self.cfg.max_outside:
            event = self._event(step, f"{share:.0%} of the Gaussians left the scene bounds", [], [], params)
            event["params"] = ["means"]
            event["gaussians"] = {"means": {"count": int(outside.sum()), "first": torch.where(outside)[0][:5].tolist()}}
            return event
        return None

    def _event(self, step: int, reason: str, bad_terms: list, keys: list, params, grads: bool = False) -> dict:
        rows = {}
        for key in keys:
            t = params[key].grad if grads else params[key].detach()
            bad = ~torch.isfinite(t.reshape(len(t), -1)).all(-1)
            rows[key] = {"count": int(bad.sum()), "first": torch.where(bad)[0][:5].tolist()}
        event = {"step": step, "reason": reason, "terms": bad_terms,
                 "params": sorted(keys) or sorted(params.keys()), "gaussians": rows}
        self.events.append(event)
        return event

    def on_rollback(self, event: dict) -> None:
        """Count the bad step; lower the offending learning rates (``lr_mult``, which the trainer
        applies on top of its schedule); raise after too many in a row."""
        self.bad_in_row += 1
        if self.bad_in_row > self.cfg.max_rollbacks:
            raise TrainingDiverged(
                f"training diverged at step {event['step']}: {event['reason']} "
                f"({self.bad_in_row - 1} rollbacks in a row did not help; offending parameters "
                f"{', '.join(event['params'])}). {divergence_hint(event)}")
        for key in event["params"]:
            self.lr_mult[key] = self.lr_mult.get(key, 1.0) * self.cfg.lr_factor
        log.warning("step %d: %s (loss terms %s; Gaussians %s); rolled back to the last good state, "
                    "learning rate x%.2g for %s", event["step"], event["reason"], event["terms"],
                    event["gaussians"] or "-", self.cfg.lr_factor, ", ".join(event["params"]))

    def on_opacity_reset(self) -> None:
        """The density control set every opacity near zero: the next losses are far above the
        running level by design (the model repaints itself), not divergence. Forget the level and
        warm up again."""
        self.loss_mean, self.n_good = None, 0

    def on_snapshot(self) -> None:
        self.bad_in_row = 0
