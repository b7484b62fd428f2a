#!/usr/bin/env bash
# Set up a virtual environment (CPU torch first, so nothing pulls CUDA builds) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMP_WAIT_POLICY=PASSIVE
python3 -m venv .venv
. .venv/bin/activate
pip install -q torch==2.13.0
pip install -q -e ".[test]"
python -m pytest -q "$@"
