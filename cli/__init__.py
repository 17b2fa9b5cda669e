"""Thin command-line front ends: they parse arguments (tyro) and call library functions."""

import os

# OpenMP threads that spin-wait are 5-10x slower than one thread when another process shares the
# cores (measured on 2 cores, docs/rasterizer.md). Must be set before torch starts its runtime.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
