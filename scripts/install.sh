#!/usr/bin/env bash
# Idempotent installer: system packages, a virtual environment in .venv, the project and its pins.
# Safe to run again: each step checks what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${INDOORGS_VENV:-.venv}

# Open3D's wheels need Debian's libusb-1.0-0 to import.
if command -v dpkg >/dev/null 2>&1 && ! dpkg -s libusb-1.0-0 >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
    python3 -m venv "$VENV"
fi
PY="$VENV/bin/python"
stamp="$VENV/.indoorgs-installed"
# Re-install only when pyproject.toml changed since the last successful install.
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    "$PY" -m pip install -q --upgrade pip setuptools wheel
    # Pin torch first: an unpinned torch would pull a multi-GB CUDA build.
    "$PY" -m pip install -q "torch==2.13.0"
    "$PY" -m pip install -q -e ".[test]"
    touch "$stamp"
fi
"$PY" - <<'PY'
import open3d, pycolmap, cv2, torch  # noqa: F401  (fail here, not mid-run, if an import is broken)
PY
