#!/usr/bin/env bash
# README command 2: install what is missing (idempotent), then run the default test suite.
# Slow benchmarks are excluded (pytest marker `slow`); run them with: .venv/bin/pytest -m slow
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}"
exec .venv/bin/python -m pytest -q "$@"
