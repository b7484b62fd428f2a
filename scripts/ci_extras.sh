#!/usr/bin/env bash
# Installs what the io/viewer/physics tests need beyond the Python package, idempotently (seconds when present):
#   - chromium (Debian package) for the headless viewer test,
#   - the Khronos glTF validator (npm gltf-validator) into .cache/node, outside the package,
#   - mujoco (PyPI, part of the `test` extra) into the active Python when it is missing.
# Usage: bash scripts/ci_extras.sh   (from any folder; uses the python on PATH)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
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
echo "ci_extras: ok (chromium: $(command -v chromium || echo none); gltf-validator: $([ -d "$NODE_PREFIX/node_modules/gltf-validator" ] && echo yes || echo no))"
