#!/usr/bin/env bash
# Installs what the io/viewer/physics tests need beyond the Python package, idempotently (seconds when present):
#   - chromium (Debian package) for the headless viewer test,
#   - the Khronos glTF validator (npm gltf-validator) into .cache/node, outside the package,
#   - mujoco (PyPI, part of the `test` extra) into the active Python when it is missing,
#   - with --blender (or TRISPLAT_CI_BLENDER=1) only: Blender as a Python module (PyPI bpy, Python 3.11) in its own
#     environment .cache/bpy-venv, for tests/consumers/test_blender_import.py and `trisplat bench consumers`. Not by
#     default: about 400 MB to download (1 GB installed), and bpy 5.0 pins numpy < 2, so it cannot share trisplat's
#     environment; without it that test skips with a message.
# Usage: bash scripts/ci_extras.sh [--blender]   (from any folder; uses the python on PATH)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BPY_VERSION="5.0.1"
BPY_VENV="$ROOT/.cache/bpy-venv"
WITH_BLENDER="${TRISPLAT_CI_BLENDER:-0}"
for arg in "$@"; do
  case "$arg" in
    --blender) WITH_BLENDER=1 ;;
    *) echo "ci_extras: unknown option $arg (known: --blender)" >&2; exit 2 ;;
  esac
done
GLTF_VALIDATOR_VERSION="2.0.0-dev.3.10"
NODE_PREFIX="$ROOT/.cache/node"

if ! command -v chromium >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1; then
    echo "ci_extras: installing chromium (apt)"
    export DEBIAN_FRONTEND=noninteractive
    SUDO=""; [ "$(id -u)" != 0 ] && SUDO="sudo"
    if ! { $SUDO apt-get update -qq >/dev/null && $SUDO apt-get install -y -qq chromium >/dev/null; }; then
      echo "ci_extras: could not install chromium: the viewer test will skip" >&2
    fi
  else
    echo "ci_extras: no chromium and no apt-get: the viewer test will skip" >&2
  fi
fi

if command -v npm >/dev/null 2>&1; then
  if [ ! -f "$NODE_PREFIX/node_modules/gltf-validator/package.json" ] || \
     ! grep -q "\"version\": \"$GLTF_VALIDATOR_VERSION\"" "$NODE_PREFIX/node_modules/gltf-validator/package.json"; then
    echo "ci_extras: installing gltf-validator@$GLTF_VALIDATOR_VERSION into $NODE_PREFIX"
    mkdir -p "$NODE_PREFIX"
    [ -f "$NODE_PREFIX/package.json" ] || echo '{"private": true}' > "$NODE_PREFIX/package.json"
    npm install --prefix "$NODE_PREFIX" --no-audit --no-fund --loglevel=error \
      "gltf-validator@$GLTF_VALIDATOR_VERSION" >/dev/null \
      || echo "ci_extras: could not install gltf-validator: the glTF validation test will skip" >&2
  fi
else
  echo "ci_extras: no npm: the glTF validation test will skip" >&2
fi

if ! python -c "import mujoco" >/dev/null 2>&1; then
  echo "ci_extras: installing mujoco (pip)"
  python -m pip install -q "mujoco>=3.0"
fi
if [ "$WITH_BLENDER" = 1 ]; then
  if ! "$BPY_VENV/bin/python" -c "import importlib.metadata as m, sys; sys.exit(m.version('bpy') != '$BPY_VERSION')" \
       >/dev/null 2>&1; then
    if command -v python3.11 >/dev/null 2>&1; then
      echo "ci_extras: installing bpy==$BPY_VERSION into $BPY_VENV (about 400 MB)"
      python3.11 -m venv "$BPY_VENV"
      "$BPY_VENV/bin/python" -m pip install -q "bpy==$BPY_VERSION" \
        || echo "ci_extras: could not install bpy: the Blender test will skip" >&2
    else
      echo "ci_extras: bpy $BPY_VERSION needs python3.11 (not found): the Blender test will skip" >&2
    fi
  fi
fi
echo "ci_extras: ok (chromium: $(command -v chromium || echo none); gltf-validator: $([ -d "$NODE_PREFIX/node_modules/gltf-validator" ] && echo yes || echo no); bpy: $([ -x "$BPY_VENV/bin/python" ] && echo "$BPY_VENV" || echo no))"
