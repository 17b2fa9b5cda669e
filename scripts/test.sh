#!/usr/bin/env bash
# README command 2: install what is missing (idempotent), then run the default test suite.
# Slow benchmarks are excluded (pytest marker `slow`); run them with: .venv/bin/pytest -m slow
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# The `splat view` browser test draws the page in headless Chromium (software WebGL); without it
# that test is skipped.
if command -v dpkg >/dev/null 2>&1 && ! dpkg -s chromium >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null; } \
        || echo "could not install chromium: tests/test_view.py's browser test will be skipped" >&2
fi
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}"
exec .venv/bin/python -m pytest -q "$@"
