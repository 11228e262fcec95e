#!/usr/bin/env bash
# Set up everything on a fresh Debian/Ubuntu machine: system library for Open3D, a virtualenv,
# and the package with its dev extras. VENV chooses the virtualenv folder (default .venv).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${VENV:-.venv}"
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1
fi
python3 -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[dev]"
echo "installed into $VENV"
