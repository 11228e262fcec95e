#!/usr/bin/env bash
# Set up everything on a fresh Debian/Ubuntu machine: system library for Open3D, a virtualenv,
# and the package with its dev extras. VENV chooses the virtualenv folder (default .venv).
# Idempotent: when the virtualenv already holds this checkout's install made from the same
# pyproject.toml, nothing is installed again (the package is installed editable, so code changes
# need no reinstall); a changed pyproject.toml reinstalls.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${VENV:-.venv}"
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1
fi
STAMP="$VENV/.rgbd-slam-setup"
WANT="$(pwd) $(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ -x "$VENV/bin/slam" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ]; then
  echo "already set up in $VENV (delete $STAMP to reinstall)"
  exit 0
fi
echo "setting up: a virtualenv in $VENV with the package and its dependencies (Open3D, GTSAM,"
echo "numba, Ray, rerun: about 2 minutes and ~3 GB the first time) ..."
python3 -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
# PYTHONWARNINGS: setuptools' advice on editable installs in general (a UserWarning printed by
# the build backend) says nothing about this project
PYTHONWARNINGS="ignore::UserWarning" "$VENV/bin/python" -m pip install -q -e ".[dev]"
echo "$WANT" > "$STAMP"
echo "installed into $VENV"
