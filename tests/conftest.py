"""Shared fixtures. Paths to the shared data live beside the repository (../shared)."""

from __future__ import annotations

import os

# Before torch is imported anywhere: spin-waiting OpenMP threads crawl on shared cores.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
ICL = SHARED / "data" / "icl_livingroom1"


@pytest.fixture(scope="session")
def icl_dir() -> Path:
    if not (ICL / "sparse" / "0").is_dir():
        pytest.skip(f"ICL-NUIM scene not found at {ICL}")
    return ICL


@pytest.fixture(autouse=True)
def _seed_global_rngs():
    """Every test draws the same global torch/numpy randoms on every run (no flaky tolerances)."""
    import numpy as np
    import torch

    torch.manual_seed(0)
    np.random.seed(0)
    yield
