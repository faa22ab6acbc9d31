#!/usr/bin/env bash
# Bundles the viewer's sources (src/*.js, ours) with three.js (npm, pinned in package.json)
# into dist/viewer.bundle.js, which is checked in so `cargo build` needs no Node. Run after
# changing src/:  bash src/api/http/viewer/build.sh   (needs node and npm; installs into
# node_modules/, which git ignores).
set -euo pipefail
cd "$(dirname "$0")"
if [ ! -x node_modules/.bin/esbuild ] || [ ! -d node_modules/three ]; then
  npm ci --no-audit --no-fund --ignore-scripts
fi
# esbuild's own binary comes as the npm package @esbuild/linux-x64 (no install script needed).
node_modules/.bin/esbuild src/main.js --bundle --format=esm --minify --target=es2020 \
  --legal-comments=eof --outfile=dist/viewer.bundle.js --log-level=warning
ls -l dist/viewer.bundle.js
