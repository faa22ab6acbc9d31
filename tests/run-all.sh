#!/usr/bin/env bash
# Runs every check and test of bgkmap from a fresh checkout: formatting, lints, docs, the pure
# core without optional features, the Rust suite (unit, property and integration tests that
# start the real binary; the zenoh test also drives a Python peer), then the Python client's
# tests with grpcurl, curl, eclipse-zenoh and rosbags, then the web viewer in a browser. Needs the
# Rust toolchain (clippy, rustfmt; cargo-nextest when present), python3 and node (>= 20);
# tests/python.sh sets up its own virtualenv (and installs curl with apt when missing and
# running as root); tests/browser/run.sh installs Debian's chromium (apt) and playwright-core
# (npm) when missing.
set -euo pipefail
cd "$(dirname "$0")/.."

# Reuse one build directory outside the clone, so a fresh clone on the same machine starts warm.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${HOME:-/tmp}/.cache/bgkmap/target}"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
mkdir -p "$CARGO_TARGET_DIR"

step() { printf '\n== %s\n' "$*"; }

step "format"
cargo fmt --all --check

step "lints (clippy -D warnings)"
cargo clippy --locked --all-targets -- -D warnings

step "docs (warnings are errors)"
RUSTDOCFLAGS="-D warnings" cargo doc --locked --no-deps --quiet

step "pure core: library tests without optional features"
cargo test --locked --lib --no-default-features --quiet

step "Python test environment (the zenoh test's third robot is a Python peer)"
export BGKMAP_VENV="${BGKMAP_VENV:-${HOME:-/tmp}/.cache/bgkmap/venv}"
bash tests/python.sh --setup
export BGKMAP_REQUIRE_TOOLS=1

step "all Rust tests (unit, property, integration against the real binary)"
if cargo nextest --version >/dev/null 2>&1; then
  cargo nextest run --locked --no-fail-fast
else
  cargo test --locked --no-fail-fast
fi

step "Python client, grpcurl and curl against the real server"
cargo build --locked --quiet
bash tests/python.sh

step "the web viewer in a real browser (chromium + playwright-core, node --test)"
bash tests/browser/run.sh
