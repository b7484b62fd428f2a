#!/usr/bin/env bash
# Rebuilds static/three.bundle.min.js from the npm registry (needs node + npm; not needed to use the viewer).
# three.js is MIT licensed; its licence is copied beside the bundle.
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
THREE_VERSION="0.187.0"
ESBUILD_VERSION="0.28.2"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
cd "$WORK"
echo '{"private": true}' > package.json
npm install --no-audit --no-fund --loglevel=error "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION" >/dev/null
cp "$HERE/three_entry.js" entry.js
./node_modules/.bin/esbuild entry.js --bundle --minify --format=esm --legal-comments=none \
  --banner:js="/* three.js ${THREE_VERSION} (MIT, see LICENSE-three.txt), tree-shaken by esbuild: trisplat/viewer/vendor */" \
  --outfile="$HERE/../static/three.bundle.min.js"
cp node_modules/three/LICENSE "$HERE/../static/LICENSE-three.txt"
echo "wrote $HERE/../static/three.bundle.min.js"
