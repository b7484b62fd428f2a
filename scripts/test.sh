#!/usr/bin/env bash
# Set up a virtual environment (CPU torch first, so nothing pulls CUDA builds), install the test extras and the
# tools the viewer/glTF tests use (headless Chromium, the Khronos glTF validator), then run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMP_WAIT_POLICY=PASSIVE
[ -x .venv/bin/python ] || python3 -m venv .venv
. .venv/bin/activate
pip install -q torch==2.13.0
pip install -q -e ".[test,gpu,cluster]"  # gpu: numba-cuda (no torch, no CUDA libraries), so CI runs the CUDA kernels
# in its CUDA simulator and type-checks them for a GPU; cluster: Ray (no torch, no CUDA), so CI runs the
# partitioned-training tests (tests/blocks)
bash scripts/ci_extras.sh
python -m pytest -q "$@"
