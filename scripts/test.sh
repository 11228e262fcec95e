#!/usr/bin/env bash
# The test command: set up (idempotent), then run the whole suite, real-data tests included when
# ../shared/datasets exists (they skip with a reason otherwise).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${VENV:-.venv}"
VENV="$VENV" bash scripts/setup.sh
"$VENV/bin/python" -m pytest -q -ra "$@"
