#!/usr/bin/env bash
# Creates .venv and installs sdrl-bench with its test tools. Idempotent.
# torch is installed first as the pinned CPU build, so the package's torch range is already
# satisfied and pip does not pull the CUDA wheels.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet "torch==2.13.0"
.venv/bin/python -m pip install --quiet -e ".[dev]"
echo "sdrl-bench installed in $(pwd)/.venv"
