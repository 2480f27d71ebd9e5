#!/usr/bin/env bash
# Set up .venv (scripts/setup.sh) and run the test suite: `bash scripts/test.sh [pytest args]`.
# Slow tests are left out by default (pyproject.toml); run them with `bash scripts/test.sh -m slow`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
exec .venv/bin/python -m pytest "$@"
