#!/usr/bin/env bash
# Stage what scripts/gpu_check.sh needs on a GPU machine of the device tool (issue 51), in .gpu_carry/ (git-ignored
# through .git/info/exclude; never committed): lego (../shared/data/lego, 38 MB: its licence keeps it out of the repo),
# wheels (Python 3.12, manylinux x86_64) of the packages the training path imports that the machines' image lacks, and
# the commit. Prints the size of what a `run` sends (it must stay under the tool's 64 MiB) and the exact call.
# Usage: PYTHON=.venv/bin/python bash scripts/gpu_prepare.sh   (from any folder; PYTHON must have pip)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
CARRY=.gpu_carry
LIMIT_MIB=62  # the tool takes 64 MiB per call: tracked + untracked-not-ignored files + the carried folder
# Imported by `trisplat bench train` on lego (a traced run of the fusion switch, exports and scoring) and missing from
# the image's package list (/work/.library/device/KINDS.md): tyro and its needs, the mesh tools. The versions this
# project's environment tests with. typing-extensions is there, perhaps older than typeguard needs: carried too.
WHEELS=(tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.1 typing-extensions==4.16.0 trimesh==5.2.0
        embreex==4.4.0.post1 rtree==1.4.1 edt==3.1.2 fast-simplification==0.2.0 xatlas==0.0.11 plyfile==1.1.5)
EXCLUDE="$(git rev-parse --git-path info/exclude)"
grep -qx "/$CARRY/" "$EXCLUDE" 2>/dev/null || echo "/$CARRY/" >> "$EXCLUDE"
mkdir -p "$CARRY/wheels" "$CARRY/data"
LEGO="${TRISPLAT_SHARED_DATA:-$ROOT/../shared/data}/lego"
[ -f "$LEGO/transforms_train.json" ] || { echo "gpu_prepare: no lego capture at $LEGO (set TRISPLAT_SHARED_DATA)" >&2; exit 1; }
rm -rf "$CARRY/data/lego" && cp -r "$LEGO" "$CARRY/data/lego"
for spec in "${WHEELS[@]}"; do
  name="${spec%%==*}"; file_glob="$(echo "$name" | tr - _)-${spec##*==}-*.whl"
  ls "$CARRY"/wheels/$file_glob >/dev/null 2>&1 && continue
  "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
    -d "$CARRY/wheels" "$spec"
done
echo "$(git rev-parse --short HEAD)$(git diff --quiet HEAD -- . ':!.gpu_carry' || echo ' (with uncommitted changes)')" > "$CARRY/commit.txt"
bytes=$( { git ls-files -z; git ls-files -z --others --exclude-standard; } | xargs -0 -r du -cb 2>/dev/null | awk '/total$/ {s += $1} END {print s}')
carry=$(du -sb "$CARRY" | cut -f1)
total=$(( bytes + carry ))
echo "gpu_prepare: working tree $((bytes / 1048576)) MiB + $CARRY $((carry / 1048576)) MiB = $((total / 1048576)) MiB (limit ${LIMIT_MIB} MiB)"
[ "$total" -le $(( LIMIT_MIB * 1048576 )) ] || { echo "gpu_prepare: too much to carry" >&2; exit 1; }
echo 'gpu_prepare: ready. The device tool call (docs/benchmarks_gpu.md):'
echo '  run(command="bash scripts/gpu_check.sh", carry=[".gpu_carry"], timeout_s=560)'
