#!/usr/bin/env bash
# Creates .venv and installs sdrl-bench with its test tools. Idempotent. SDRL_LOCKED=1: the exact
# versions of scripts/requirements-lock.txt (the reproduction environment).
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
# PYTHONWARNINGS=ignore: setuptools' editable build prints a banner (a Python warning, not an error)
# on every install of a flat-layout package; pip's own messages are not warnings and still show
export PYTHONWARNINGS=ignore
if [ "${SDRL_LOCKED:-0}" = "1" ]; then
  # the exact versions the reference report was rebuilt with (scripts/requirements-lock.txt), so
  # that a clean clone reproduces it seed by seed; by default the ranges of pyproject.toml
  .venv/bin/python -m pip install --quiet -e ".[dev]" -c scripts/requirements-lock.txt
else
  .venv/bin/python -m pip install --quiet -e ".[dev]"
fi
unset PYTHONWARNINGS
echo "sdrl-bench installed in $(pwd)/.venv"
