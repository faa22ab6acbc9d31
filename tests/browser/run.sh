#!/usr/bin/env bash
# The viewer's browser tests: playwright-core (npm, pinned in package.json) driving Debian's
# chromium, under `node --test`, against the debug binary that cargo already built (this
# script does not build it). Installs chromium with apt (when root) and playwright-core with
# npm when missing; idempotent; needs no stdin (works with CI=true). Never downloads a browser
# of Playwright's own.
#
#   CARGO_TARGET_DIR  where cargo built into (default: target); the binary is $CARGO_TARGET_DIR/debug/bgkmap
#   BGKMAP_BIN        the binary (default: the one above)
#   CHROMIUM          the browser (default: /usr/bin/chromium)
#   Screenshots land in tests/browser/artifacts/ (git ignores it).
set -euo pipefail
cd "$(dirname "$0")"
repo="$(cd ../.. && pwd)"
target="${CARGO_TARGET_DIR:-target}"
case "$target" in /*) ;; *) target="$repo/$target" ;; esac
export BGKMAP_BIN="${BGKMAP_BIN:-$target/debug/bgkmap}"
export CHROMIUM="${CHROMIUM:-/usr/bin/chromium}"

if [ ! -x "$BGKMAP_BIN" ]; then
  echo "tests/browser/run.sh: $BGKMAP_BIN not found; build it first (cargo build)" >&2
  exit 1
fi

apt_install() {
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "== installing $* (apt)"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
  else
    echo "tests/browser/run.sh: $* missing and cannot be installed here (not root with apt)" >&2
    exit 1
  fi
}

if [ ! -x "$CHROMIUM" ]; then
  apt_install chromium
fi
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
  apt_install nodejs npm
fi
node_major="$(node -p 'process.versions.node.split(".")[0]')"
if [ "$node_major" -lt 20 ]; then
  echo "tests/browser/run.sh: node $(node --version) is too old; playwright-core needs node >= 20" >&2
  exit 1
fi

# playwright-core from the lock file, reinstalled only when the lock file changed.
stamp=node_modules/.bgkmap-lock
if [ ! -f "$stamp" ] || ! cmp -s package-lock.json "$stamp" || [ ! -d node_modules/playwright-core ]; then
  echo "== installing playwright-core (npm)"
  npm ci --no-audit --no-fund --ignore-scripts --loglevel=error </dev/null
  cp package-lock.json "$stamp"
fi

echo "== viewer in chromium ($("$CHROMIUM" --version 2>/dev/null | head -1)), server: $BGKMAP_BIN"
exec node --test --test-reporter=spec viewer.test.mjs </dev/null
