#!/usr/bin/env bash
# The main job: set up (idempotent), then `slam run` on the built-in synthetic demo.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${VENV:-.venv}"
VENV="$VENV" bash scripts/setup.sh
# --overwrite: runs/demo is this script's own folder, replaced on every call
"$VENV/bin/slam" run --out runs/demo --overwrite "$@"
