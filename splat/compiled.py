"""torch.compile for the small element-wise graphs around the CUDA kernels of a training step.

On a GPU the torch code between the rasterizer's kernels is launch-bound: the loss terms (L1 and
SSIM of L_rgb, L_n, L_nc) and the per-pixel depth/normal maps of ``render`` are a few hundred
kernels of microseconds each per step, and the GPU waits on Python for most of the step
(docs/rasterizer.md). ``call(fn, *args)`` runs ``fn`` compiled by ``torch.compile`` (inductor:
fused Triton kernels on CUDA; one graph, static shapes) instead. It is the same torch code, so the
values are the same up to float rounding, and ``fn`` run eagerly is the oracle
(tests/test_compiled.py).

The first call of a function with a new input signature compiles it (seconds; again for each new
image size, up to torch's recompile limit, after which torch runs it eagerly) and checks the result
once: forward and backward on detached copies of the inputs, against the eager function. Where
compiling fails (no Triton, no C compiler, an unsupported operation) or the check disagrees, one
warning names the function and why, and that function runs eagerly for the rest of the process.

Off unless asked for: ``splat train --compile`` (``TrainConfig.compile``) calls ``enable(True)`` for
its run, and then ``applies(*tensors)`` is true for CUDA tensors; the callers (splat/rasterize.py for
the "cuda" backend; splat/losses.py under ``LossConfig.kernels = "fused"`` only where the CUDA loss
kernels of splat/losses_cuda.py, which it tries first, did not build) keep their eager code for
everything else. Measured on an H100 (docs/rasterizer.md): one training step at 640x480 with
300k Gaussians and priors 15 -> 10 ms; in a prior-free 30k-iteration run on ICL living room 1 the
steady step 16.4 -> 14.8 ms, after about 90 s of compiling on a machine with no inductor cache yet
(torch keeps compiled kernels on disk, so later runs on the same machine start in seconds).
"""

from __future__ import annotations

import logging
from typing import Any, Callable

import torch
from torch import Tensor

log = logging.getLogger(__name__)

_COMPILED: dict[Callable, Callable] = {}
_CHECKED: set[tuple] = set()
_FAILED: dict[Callable, str] = {}
_ENABLED = [False]


def enable(on: bool) -> None:
    """Switch compiling on or off for this process (``splat train --compile`` switches it on)."""
    _ENABLED[0] = bool(on)


def enabled() -> bool:
    """Whether compiling is switched on (see :func:`enable`)."""
    return _ENABLED[0]


def applies(*tensors: Tensor) -> bool:
    """Whether :func:`call` is meant for these tensors: all on a CUDA device, compiling switched on."""
    return enabled() and all(isinstance(t, Tensor) and t.device.type == "cuda" for t in tensors)


def _signature(fn: Callable, args: tuple) -> tuple:
    return (fn,) + tuple((tuple(a.shape), a.dtype, a.device, a.requires_grad) if isinstance(a, Tensor) else a
                         for a in args)


def _copies(args: tuple) -> tuple:
    return tuple(a.detach().clone().requires_grad_(a.requires_grad) if isinstance(a, Tensor) else a
                 for a in args)


def _close(a: Tensor, b: Tensor, rel: float) -> bool:
    """|a − b| within rel × (max |b| + tiny) everywhere, the non-finite entries in the same places."""
    if a.shape != b.shape:
        return False
    fa, fb = torch.isfinite(a), torch.isfinite(b)
    if not torch.equal(fa, fb):
        return False
    scale = float(b[fb].abs().max()) if bool(fb.any()) else 0.0
    return bool(((a - b)[fa].abs() <= rel * scale + 1e-12).all())


def _check(fn: Callable, compiled: Callable, args: tuple, rel: float) -> str:
    """'' when the compiled function gives fn's output and gradients on copies of ``args``, else why not."""
    outs = []
    for f in (fn, compiled):
        xs = _copies(args)
        y = f(*xs)
        ys = y if isinstance(y, tuple) else (y,)
        grads: list = []
        leaves = [x for x in xs if isinstance(x, Tensor) and x.requires_grad]
        diff = [t for t in ys if isinstance(t, Tensor) and t.requires_grad]
        if leaves and diff:
            seed = [torch.ones_like(t) for t in diff]
            grads = list(torch.autograd.grad(diff, leaves, seed, allow_unused=True))
        outs.append(([t.detach() for t in ys if isinstance(t, Tensor)], grads))
    (y0, g0), (y1, g1) = outs
    for k, (a, b) in enumerate(zip(y1, y0)):
        if not _close(a, b, rel):
            return f"output {k} differs from the eager code"
    for k, (a, b) in enumerate(zip(g1, g0)):
        if (a is None) != (b is None) or (a is not None and not _close(a, b, rel)):
            return f"gradient of input {k} differs from the eager code"
    return ""


def call(fn: Callable, *args: Any, rel: float = 1e-3) -> Any:
    """``fn(*args)`` by its compiled version (see the module); positional arguments only, tensors and
    hashable constants (a new constant value compiles again). ``rel``: tolerance of the one-time
    check against the eager code, relative to each output's and gradient's largest magnitude."""
    if fn in _FAILED:
        return fn(*args)
    compiled = _COMPILED.get(fn)
    if compiled is None:
        compiled = _COMPILED[fn] = torch.compile(fn, fullgraph=True, dynamic=False)
    key = _signature(fn, args)
    if key not in _CHECKED:
        try:
            why = _check(fn, compiled, args, rel)
        except Exception as exc:  # noqa: BLE001 — compiler errors have many types; the eager code still runs
            why = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
        if why:
            _FAILED[fn] = why
            log.warning("torch.compile of %s not used (%s): it runs eagerly", fn.__qualname__, why)
            return fn(*args)
        _CHECKED.add(key)
        log.debug("compiled %s for %s", fn.__qualname__, key[1:])
    return compiled(*args)


def reset() -> None:
    """Forget every compiled function, check and failure, and switch compiling off (tests)."""
    _ENABLED[0] = False
    _COMPILED.clear()
    _CHECKED.clear()
    _FAILED.clear()
    torch._dynamo.reset()
