#!/usr/bin/env bash
# Regenerates the checked-in gRPC/protobuf stubs in bgkmap_client/_pb/ from ../../proto.
#
# The code generator is pinned (GRPCIO_TOOLS_VERSION below) because the generated code checks
# the runtime it is loaded with: bgkmap_pb2.py needs a protobuf runtime of the same major version
# and at least the generator's protobuf version, and bgkmap_pb2_grpc.py needs grpcio at least the
# generator's version. pyproject.toml pins `protobuf` and `grpcio` to match; bump all three
# together. grpcio-tools 1.80.x is the newest line that still supports Python 3.9.
#
# Usage: clients/python/regen.sh   (uses ${BGKMAP_REGEN_VENV:-$HOME/.cache/bgkmap/regen-venv})
set -euo pipefail
cd "$(dirname "$0")"

GRPCIO_TOOLS_VERSION=1.80.1
venv="${BGKMAP_REGEN_VENV:-${HOME:-/tmp}/.cache/bgkmap/regen-venv}"
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
fi
if ! "$venv/bin/python" -c "import importlib.metadata as m, sys; sys.exit(m.version('grpcio-tools') != '$GRPCIO_TOOLS_VERSION')" 2>/dev/null; then
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "grpcio-tools==$GRPCIO_TOOLS_VERSION"
fi

out=bgkmap_client/_pb
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$venv/bin/python" -m grpc_tools.protoc \
  -I ../../proto \
  --python_out="$tmp" --pyi_out="$tmp" --grpc_python_out="$tmp" \
  bgkmap/v1/bgkmap.proto

mkdir -p "$out"
cp "$tmp/bgkmap/v1/bgkmap_pb2.py" "$tmp/bgkmap/v1/bgkmap_pb2.pyi" "$out/"
# protoc writes `from bgkmap.v1 import bgkmap_pb2 as …`; inside the package it must be relative.
sed -e 's/^from bgkmap\.v1 import bgkmap_pb2 as /from . import bgkmap_pb2 as /' \
  "$tmp/bgkmap/v1/bgkmap_pb2_grpc.py" >"$out/bgkmap_pb2_grpc.py"
if ! grep -q '^from \. import bgkmap_pb2 as ' "$out/bgkmap_pb2_grpc.py"; then
  echo "regen.sh: could not make the import in bgkmap_pb2_grpc.py package-relative" >&2
  exit 1
fi
[ -f "$out/__init__.py" ] || printf '"""Generated from proto/bgkmap/v1/bgkmap.proto by regen.sh; do not edit."""\n' >"$out/__init__.py"
echo "regenerated $out with grpcio-tools $GRPCIO_TOOLS_VERSION ($("$venv/bin/python" -m grpc_tools.protoc --version))"
