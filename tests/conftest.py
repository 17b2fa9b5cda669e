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


@pytest.fixture
def restore_log_handlers():
    """The CLI attaches a handler to the (captured) stderr of the test that calls it; drop it after."""
    import logging

    names = ("geocues", "splat", "evaluation")
    before = {n: list(logging.getLogger(n).handlers) for n in names}
    yield
    for n in names:
        logging.getLogger(n).handlers = before[n]


@pytest.fixture(autouse=True)
def _warnings_said_anew():
    """geocues.logs.warn_once says a sentence once per process: each test starts with none said, so
    what one test asserts does not depend on what ran before it."""
    from geocues import logs

    logs._SAID.clear()
    yield


@pytest.fixture(autouse=True)
def _seed_global_rngs():
    """Every test draws the same global torch/numpy randoms on every run (no flaky tolerances)."""
    import numpy as np
    import torch

    torch.manual_seed(0)
    np.random.seed(0)
    yield


# ---- hypothesis profiles of the property-based fuzz suite (tests/test_fuzz_*.py, docs/testing.md)
# "ci" (default): 100 examples per property, derandomized (the same examples on every run and
# machine), no example database. "fuzz" (--hypothesis-profile=fuzz): 1000 random examples per
# property; failures found are kept in .cache/hypothesis (ignored by git) and replayed first.
try:
    from hypothesis import HealthCheck, settings
    from hypothesis.database import DirectoryBasedExampleDatabase
except ImportError:  # the test extra is not installed: the fuzz files fail to import on their own
    pass
else:
    settings.register_profile("ci", max_examples=100, deadline=None, derandomize=True, database=None,
                              suppress_health_check=[HealthCheck.too_slow])
    settings.register_profile("fuzz", max_examples=1000, deadline=None, derandomize=False,
                              database=DirectoryBasedExampleDatabase(str(REPO / ".cache" / "hypothesis")),
                              suppress_health_check=[HealthCheck.too_slow])
    settings.load_profile("ci")
