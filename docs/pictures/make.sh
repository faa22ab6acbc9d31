#!/usr/bin/env bash
# Makes the README's pictures: roc.png (two maps of 12 simulated scans against the analytic
# ground truth, `bgkmap eval --roc`) and viewer.png (the viewer on `bgkmap demo`, screenshot
# in Debian's chromium). Uses BGKMAP_BIN, else $CARGO_TARGET_DIR/release/bgkmap (build it with
# `cargo build --release`); needs node and chromium as tests/browser/run.sh installs them.
set -euo pipefail
cd "$(dirname "$0")/../.."
target="${CARGO_TARGET_DIR:-target}"
export BGKMAP_BIN="${BGKMAP_BIN:-$target/release/bgkmap}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

"$BGKMAP_BIN" simulate --out "$tmp/sim" --scans 12 --seed 3 >/dev/null
"$BGKMAP_BIN" build --out "$tmp/truncate.bgkmap" "$tmp"/sim/scan_*.pcd
"$BGKMAP_BIN" build --out "$tmp/drop.bgkmap" --range-mode drop "$tmp"/sim/scan_*.pcd
"$BGKMAP_BIN" eval "$tmp/truncate.bgkmap" "$tmp/drop.bgkmap" --truth "$tmp/sim/truth.bt" --roc docs/pictures/roc.png

(cd tests/browser && { [ -d node_modules/playwright-core ] || npm ci --no-audit --no-fund --ignore-scripts --loglevel=error; })
node tests/browser/screenshot.mjs docs/pictures/viewer.png
ls -l docs/pictures/*.png
