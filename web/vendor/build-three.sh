#!/usr/bin/env bash
# Rebuilds web/vendor/three.min.js and web/vendor/three.LICENSE from npm (three.js ships ES
# modules only since r160; a page opened from file:// cannot import modules from other files,
# so the library is bundled into one classic script, an IIFE defining `window.THREE`).
# Needs node and npm; installs into a scratch folder, never into the repository.
set -euo pipefail
THREE_VERSION=0.187.0
ESBUILD_VERSION=0.28.2
here="$(cd "$(dirname "$0")" && pwd)"
scratch="$(mktemp -d)"
trap 'rm -rf "$scratch"' EXIT
cd "$scratch"
npm init -y >/dev/null
npm install --no-audit --no-fund --silent "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION"
cp "$here/three-entry.mjs" entry.mjs
./node_modules/.bin/esbuild entry.mjs --bundle --minify --format=iife --global-name=THREE \
  --target=es2020 --legal-comments=inline \
  --banner:js="/* three.js r$(echo "$THREE_VERSION" | cut -d. -f2) (npm three@$THREE_VERSION, MIT: three.LICENSE) with OrbitControls, bundled by esbuild $ESBUILD_VERSION into an IIFE that defines window.THREE (web/vendor/build-three.sh) */" \
  --outfile="$here/three.min.js"
cp node_modules/three/LICENSE "$here/three.LICENSE"
echo "wrote $here/three.min.js ($(wc -c <"$here/three.min.js") bytes) and three.LICENSE"
