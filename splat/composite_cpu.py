"""C++ CPU compositing backend: built on first import, wrapped in a torch.autograd.Function.

The kernel (``splat/csrc/composite_cpu.cpp``) implements the per-pixel rule of
:mod:`splat.composite` with 16x16 tiles, a global stable depth sort, early termination, OpenMP
over tiles and an analytic backward (back to front, transmittance recovered by division, as 3DGS
``backward.cu``). It has no per-pixel cap on contributors. float32 and float64 are supported (the
latter for ``gradcheck``); all tensors must be on the CPU.

Importing this module compiles the extension with ``torch.utils.cpp_extension.load`` into
``<repo>/.cache/torch_extensions/<name>/<hash>`` (or ``$INDOORGS_CACHE/torch_extensions/...``),
where the hash covers the sources (``.cpp`` and ``.h``), the compiler flags and the torch version;
later imports reuse that build (about 0.5 s). If the build fails, the import raises ImportError
carrying the compiler's message, and :mod:`splat.composite` falls back to torch with a warning.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import time
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from splat.composite import CompositeOut, check_composite_inputs

log = logging.getLogger(__name__)

EXT_NAME = "indoorgs_composite_cpu"
SOURCE = Path(__file__).resolve().parent / "csrc" / "composite_cpu.cpp"
HEADERS = (SOURCE.with_suffix(".h"),)
# -ffp-contract=off: forward and backward must evaluate alpha bit-identically (same skip decisions).
# SSE4.2 (every x86-64 CPU since ~2009) gives inline floor/ceil; not -march=native, so that a cached
# build stays valid when the repository moves to another x86-64 machine.
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off"]
if platform.machine().lower() in ("x86_64", "amd64"):
    CFLAGS.append("-msse4.2")


def build_dir() -> Path:
    """``$INDOORGS_CACHE`` (or ``<repo>/.cache``) / torch_extensions / <name> / <hash of sources+flags>."""
    root = os.environ.get("INDOORGS_CACHE")
    base = Path(root) if root else Path(__file__).resolve().parents[1] / ".cache"
    digest = hashlib.sha1(" ".join(CFLAGS + [torch.__version__]).encode())
    for path in (SOURCE, *HEADERS):  # torch's own check hashes the listed .cpp only, not headers
        digest.update(path.read_bytes() if path.is_file() else b"")
    return base / "torch_extensions" / EXT_NAME / digest.hexdigest()[:12]


def _build():
    """Compile (or load the cached build of) the extension; ImportError with the compiler output on failure."""
    if not SOURCE.is_file():
        raise ImportError(f"C++ source not found: {SOURCE}")
    from torch.utils.cpp_extension import load

    out_dir = build_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        module = load(name=EXT_NAME, sources=[str(SOURCE)], extra_cflags=CFLAGS,
                      extra_ldflags=["-fopenmp"], build_directory=str(out_dir), verbose=False)
    except Exception as exc:  # noqa: BLE001 - ninja/compiler errors come as RuntimeError/OSError/...
        raise ImportError(f"building {SOURCE.name} in {out_dir} failed: {exc}") from exc
    log.debug("C++ compositing backend ready in %.1f s (%s)", time.perf_counter() - t0, out_dir)
    return module


_ext = _build()


class _CompositeCPU(torch.autograd.Function):
    """Autograd wrapper: forward and analytic backward both in C++."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, background, median_features, depths, radii,
                width, height):
        (out, alpha, median, n_contrib, final_t, last, median_idx,
         *bins) = _ext.forward(means2d, conics, opacities, features, depths, radii, background,
                               median_features, width, height)
        ctx.save_for_backward(means2d, conics, opacities, features, radii, background, median_features,
                              final_t, last, median_idx, *bins)
        ctx.size = (width, height)
        ctx.mark_non_differentiable(n_contrib)
        return out, alpha, median, n_contrib

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out, grad_alpha, grad_median, _grad_n):
        saved = ctx.saved_tensors
        grads = _ext.backward(grad_out.contiguous(), grad_alpha.contiguous(), grad_median.contiguous(),
                              *saved, *ctx.size)
        d_means, d_conics, d_opac, d_feat, d_bg, d_medf = grads
        return d_means, d_conics, d_opac, d_feat, d_bg, d_medf, None, None, None, None


def composite(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    depths: Tensor,  # [N]
    radii: Tensor,  # [N] int
    width: int,
    height: int,
    *,
    background: Tensor | None = None,  # [C]
    median_features: Tensor | None = None,  # [N, M]
) -> CompositeOut:
    """Composite with the C++ kernel; same arguments and result as :func:`splat.composite.composite`."""
    check_composite_inputs(means2d, conics, opacities, features, depths, radii, width, height,
                           background, median_features)
    dtype = features.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"features must be float32 or float64, got {dtype}")
    named = {"means2d": means2d, "conics": conics, "opacities": opacities, "features": features}
    if background is not None:
        named["background"] = background
    if median_features is not None:
        named["median_features"] = median_features
    for name, tensor in named.items():
        if tensor.device.type != "cpu":
            raise ValueError(f"{name} must be a CPU tensor for the 'cpu' backend, got {tensor.device}")
        if tensor.dtype != dtype:
            raise ValueError(f"{name} must have dtype {dtype} (as features), got {tensor.dtype}")
    n, c = features.shape
    bg = background if background is not None else features.new_zeros(c)
    med = median_features if median_features is not None else features.new_zeros(n, 0)
    out, alpha, median, n_contrib = _CompositeCPU.apply(
        means2d.contiguous(), conics.contiguous(), opacities.contiguous(), features.contiguous(),
        bg.contiguous(), med.contiguous(), depths.detach().to(dtype).contiguous(),
        radii.detach().to(torch.int32).contiguous(), int(width), int(height))
    return CompositeOut(out, alpha, median if median_features is not None else None, n_contrib)
