#!/usr/bin/env bash
# The CUDA backend's prepared check on a GPU machine (issue 51), run as it is there, within 8 minutes:
# `trisplat bench gpu` (parity with the reference on the GPU, 100k and 1M faces at 800x800 forward and
# forward+backward, a 5-minute lego run scored as the CPU runs, tests/render/test_render_cuda.py with the time left)
# -> $OUT/gpu.json and $OUT/gpu.md (plus the lego bench's train/train_cuda.* and log.txt).
# Needs what scripts/gpu_prepare.sh stages in .gpu_carry (wheels installed into /tmp, lego); nothing is downloaded.
# Usage: bash scripts/gpu_check.sh [--dry-run]     OUT (default gpu_check_out) names the output folder.
#   --dry-run: no GPU needed; every phase tiny under numba's CUDA simulator, lego replaced by a generated scene.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
DEADLINE_S=${TRISPLAT_GPU_DEADLINE_S:-470}  # the whole check; the lego run gets what parity and timings leave
CARRY=.gpu_carry
OUT_DIR="${OUT:-gpu_check_out}"
PY="${PYTHON:-python3}"
mkdir -p "$OUT_DIR"
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
DRY=0; [ "${1:-}" = "--dry-run" ] && DRY=1
if [ "$DRY" = 0 ] && ls "$CARRY"/wheels/*.whl >/dev/null 2>&1; then  # (Python 3.12 wheels: the GPU image's Python)
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/trisplat_site \
    "$CARRY"/wheels/*.whl || { echo "gpu_check: installing the carried wheels failed" >&2; exit 1; }
  export PYTHONPATH="/tmp/trisplat_site:$PYTHONPATH"
fi
ARGS=(--out "$OUT_DIR" --deadline-s "$DEADLINE_S" --commit "$(cat "$CARRY/commit.txt" 2>/dev/null || true)")
if [ "$DRY" = 1 ]; then
  export NUMBA_ENABLE_CUDASIM=1
  ARGS+=(--dry-run --data-root "$OUT_DIR/dry_data" --runs "$OUT_DIR/dry_runs" --minutes 0.05)
else
  [ -f "$CARRY/data/lego/transforms_train.json" ] || echo "gpu_check: no $CARRY/data/lego (scripts/gpu_prepare.sh); the lego phase will fail" >&2
  ARGS+=(--data-root "$CARRY/data")
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
fi
"$PY" -c "import sys, torch, numba; print('python', sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.version.cuda, 'gpu', torch.cuda.is_available(), 'numba', numba.__version__)"
timeout --kill-after=10 $((DEADLINE_S + 20)) "$PY" -m trisplat bench gpu "${ARGS[@]}" 2>&1 | tee "$OUT_DIR/log.txt"
status=${PIPESTATUS[0]}
echo "gpu_check: exit $status; results in $OUT_DIR/gpu.json and $OUT_DIR/gpu.md"
exit "$status"
