"""The C++ compositing kernels of an earlier commit, built beside today's, for side-by-side timings.

    from bench.old_kernels import composite_kernels_at
    ext = composite_kernels_at("2a93836")   # a module with forward() and backward()

Writes that commit's ``splat/csrc/composite_cpu.{cpp,h}`` and ``kernels.h`` (``git show``) next to
a bindings file for the two compositing entry points in ``$INDOORGS_CACHE/torch_extensions/old_kernels/<sha>/``
and builds them with the baseline flags of :mod:`splat.cpu_ext` (cached like the project's own builds). The entry points'
signatures must match today's (true since the commit that added ``kernels.h``; the forward's later
``store_weights`` flag is bridged). Swapping
``splat.composite_cpu._ext`` for the result makes render() use the old kernels.
"""

from __future__ import annotations

import subprocess
from pathlib import Path
from types import ModuleType

import torch

from splat import cpu_ext
from splat.ext_build import build_or_load, cache_dir

REPO = Path(__file__).resolve().parents[1]
OLD_FILES = ("splat/csrc/composite_cpu.cpp", "splat/csrc/composite_cpu.h", "splat/csrc/kernels.h")
BINDINGS = """// The compositing entry points of splat/csrc/composite_cpu.cpp (bench/old_kernels.py).
#include "kernels.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &composite_forward, "composite forward");
  m.def("backward", &composite_backward, "composite backward");
}
"""


def composite_kernels_at(rev: str) -> ModuleType:
    """Build (or load from the cache) the compositing kernels of commit ``rev``."""
    sha = subprocess.run(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=REPO, check=True,
                         capture_output=True, text=True).stdout.strip()
    name = f"indoorgs_cpu_{sha[:10]}"
    src = cache_dir("old_kernels", (), [sha]).parent / sha
    src.mkdir(parents=True, exist_ok=True)
    for rel in OLD_FILES:
        text = subprocess.run(["git", "show", f"{sha}:{rel}"], cwd=REPO, check=True, capture_output=True,
                              text=True).stdout
        (src / Path(rel).name).write_text(text)
    bindings = src / "bindings_composite.cpp"
    bindings.write_text(BINDINGS)
    sources = (src / "composite_cpu.cpp", bindings)
    out = cache_dir(name, (*sources, src / "composite_cpu.h", src / "kernels.h"),
                    cpu_ext.CFLAGS + [torch.__version__])
    ext = build_or_load(name, sources, out, f"compositing kernels of {sha[:10]}", cflags=cpu_ext.CFLAGS,
                        ldflags=["-fopenmp"])
    return ext if "store_weights" in (src / "kernels.h").read_text() else _WithoutWeightStore(ext)


class _WithoutWeightStore:
    """Today's forward signature over kernels from before the weight store (splat/composite_cpu.py):
    the trailing ``store_weights`` flag (always False for a training step) dropped, its generation
    output -1."""

    def __init__(self, ext) -> None:
        self.ext = ext

    def forward(self, *args):
        *args, stored = args
        if stored:
            raise ValueError("the compositing kernels of this commit keep no blend weights")
        return [*self.ext.forward(*args), torch.full((1,), -1, dtype=torch.int64)]

    def backward(self, *args):
        return self.ext.backward(*args)
