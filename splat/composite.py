"""Front-to-back alpha compositing of projected Gaussians: the one function backends implement.

``composite`` takes Gaussians already projected to the image (2D means, conics, opacities, any
per-Gaussian channels) and blends them per pixel. It is the only part of the rasterizer with more
than one implementation ("backend"):

- ``"torch"``: :mod:`splat.composite_torch`, the reference and oracle; pure torch, CPU or CUDA.
- ``"cpu"``: :mod:`splat.composite_cpu`, a C++ kernel (CPU tensors only), built on first use.
- ``"cuda"``: :mod:`splat.composite_cuda`, CUDA kernels (float32 CUDA tensors only), built on first
  use; never imported where ``torch.cuda.is_available()`` is false.
- ``"auto"``: ``"cpu"`` for CPU tensors and ``"cuda"`` for float32 CUDA tensors when it imports and
  builds, else ``"torch"``.

Exact per-pixel rule (3DGS ``forward.cu`` semantics; every backend follows it)
-----------------------------------------------------------------------------
Pixel (row i, col j) has centre ``(px, py) = (j + 0.5, i + 0.5)`` (COLMAP convention). Gaussian g
*touches* the pixel iff ``radii[g] > 0`` and ``|px - means2d[g, 0]| <= radii[g]`` and
``|py - means2d[g, 1]| <= radii[g]`` (its radius box, inclusive). Touching Gaussians are visited in
ascending ``depths`` (ties: ascending index). With ``T = 1``, for each::

    dx, dy = means2d[g] - (px, py)
    power  = -0.5 * (a * dx**2 + c * dy**2) - b * dx * dy        # (a, b, c) = conics[g]
    if power > 0: skip
    alpha  = min(0.99, opacities[g] * exp(power))
    if alpha < 1/255: skip
    test_T = T * (1 - alpha)
    if test_T < 1e-4: stop                                      # this Gaussian is not included
    out   += features[g] * alpha * T
    if T > 0.5 and test_T <= 0.5: median = median_features[g]   # median stays 0 if never crossed
    T      = test_T
    n_contrib += 1

then ``out += T * background`` and ``alpha_out = 1 - T``. ``n_contrib`` counts the Gaussians that
were blended (not those skipped). Gradients are the exact derivatives of this rule w.r.t. means2d,
conics, opacities, features, background and median_features (``min(0.99, .)`` has zero gradient
where it clamps; the skip/stop decisions and the median choice are piecewise constant). ``depths``
and ``radii`` get no gradient.

A backend may cap the number of blended Gaussians per pixel (the torch backend's ``max_per_pixel``,
default 256): after the cap the pixel stops as if ``test_T`` had dropped below 1e-4.

A backend module (``splat.composite_cpu``, ``splat.composite_cuda``) exposes ``composite(means2d,
conics, opacities, features, depths, radii, width, height, *, background=None,
median_features=None) -> CompositeOut`` taking tensors already checked by
:func:`check_composite_inputs`.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from geocues.logs import warn_once
from splat.contracts import CompositeOut, check_composite_inputs  # noqa: F401  (re-exported)

log = logging.getLogger(__name__)

BACKENDS = ("torch", "cpu", "cuda", "auto")

# name -> the imported backend module (None: not tried yet or failed), and why it failed
_modules: dict[str, object | None] = {"cpu": None, "cuda": None}
_errors: dict[str, str | None] = {"cpu": None, "cuda": None}


def _load_backend(name: str):
    """Import (and thereby build) the "cpu" or "cuda" backend module once; the module or None,
    logging why. The CUDA one is never imported (nor built) on a machine without a CUDA device."""
    if _modules[name] is None and _errors[name] is None:
        if name == "cuda" and not torch.cuda.is_available():
            _errors[name] = "no CUDA device"
            return None
        try:  # lazy: building takes about a minute the first time
            import importlib

            _modules[name] = importlib.import_module(f"splat.composite_{name}")
        except Exception as exc:  # noqa: BLE001 - any build/import failure means "fall back"
            from splat.ext_build import compiler_error

            log.debug("%s backend import failed: %s", name, exc)  # the whole compiler output, with -v
            _errors[name] = f"{type(exc).__name__}: {compiler_error(exc)}"
            log.warning("%s compositing backend unavailable, using torch: %s",
                        {"cpu": "C++", "cuda": "CUDA"}[name], _errors[name])
    return _modules[name]


def cpu_backend_available() -> bool:
    """True when :mod:`splat.composite_cpu` imports (building it if needed)."""
    return _load_backend("cpu") is not None


def cuda_backend_available() -> bool:
    """True when there is a CUDA device and :mod:`splat.composite_cuda` imports (building it if needed)."""
    return _load_backend("cuda") is not None


def available_backends() -> list[str]:
    """The concrete backends that work here ("torch" always, "cpu" and "cuda" if they build)."""
    return (["torch"] + (["cpu"] if cpu_backend_available() else [])
            + (["cuda"] if cuda_backend_available() else []))


def resolve_backend(backend: str, device: torch.device, dtype: torch.dtype | None = None) -> str:
    """Map "auto" and unavailable choices to a concrete backend name ("torch", "cpu" or "cuda").

    ``dtype`` (of the features, when known): the "cuda" backend takes float32 only. A fallback is said
    once per process, not at every render (109 lines in 60 steps).
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "torch":
        return "torch"
    if device.type == "cuda" and backend in ("cuda", "auto"):
        if dtype is not None and dtype != torch.float32:
            if backend == "cuda":
                warn_once(log, f"backend 'cuda' takes float32 only, got {dtype}; using torch")
            return "torch"
        if _load_backend("cuda") is None:
            if backend == "cuda":
                warn_once(log, f"backend 'cuda' requested but unavailable ({_errors['cuda']}); using torch")
            return "torch"
        return "cuda"
    if backend == "cuda":
        warn_once(log, f"backend 'cuda' needs CUDA tensors, got {device}; using torch")
        return "torch"
    if device.type != "cpu":
        if backend == "cpu":
            warn_once(log, f"backend 'cpu' needs CPU tensors, got {device}; using torch")
        return "torch"
    if _load_backend("cpu") is None:
        if backend == "cpu":
            warn_once(log, f"backend 'cpu' requested but unavailable ({_errors['cpu']}); using torch")
        return "torch"
    return "cpu"


def describe_backend(backend: str, device: torch.device) -> str:
    """What ``backend`` resolves to on ``device``, in words for a log line or a report:
    "cpu (C++ avx2 build, OpenMP, 2 threads)", "cpu (C++ baseline build, one thread)", "cuda", "torch"."""
    name = resolve_backend(backend, device)
    if name != "cpu":
        return name
    from splat.cpu_ext import OPENMP, SIMD

    threads = f"OpenMP, {torch.get_num_threads()} threads" if OPENMP else "one thread"
    return f"cpu (C++ {SIMD} build, {threads})"


def composite(
    means2d: Tensor,  # [N, 2] pixel coordinates (COLMAP centres)
    conics: Tensor,  # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    opacities: Tensor,  # [N] in (0, 1)
    features: Tensor,  # [N, C] channels to blend
    depths: Tensor,  # [N] view-space z, sort key only
    radii: Tensor,  # [N] int32 pixel radius, 0 = culled
    width: int,
    height: int,
    *,
    background: Tensor | None = None,  # [C] or None (zeros)
    median_features: Tensor | None = None,  # [N, M] or None
    backend: str = "torch",
    max_per_pixel: int = 256,
) -> CompositeOut:
    """Blend Gaussians front to back per pixel (rule in the module docstring) with a backend.

    ``max_per_pixel`` caps the Gaussians blended per pixel in the torch backend (its cost grows
    with it); backends without a cap ignore it.
    """
    check_composite_inputs(means2d, conics, opacities, features, depths, radii, width, height,
                           background, median_features)
    name = resolve_backend(backend, means2d.device, features.dtype)
    if name == "cpu":
        return _load_backend("cpu").composite(
            means2d, conics, opacities, features, depths, radii, int(width), int(height),
            background=background, median_features=median_features)
    if name == "cuda":
        return _load_backend("cuda").composite(
            means2d, conics, opacities, features, depths, radii, int(width), int(height),
            background=background, median_features=median_features)
    from splat.composite_torch import composite_torch

    return composite_torch(means2d, conics, opacities, features, depths, radii, int(width), int(height),
                           background=background, median_features=median_features,
                           max_per_pixel=max_per_pixel)
