#!/usr/bin/env bash
# Build the tf2_msgs messages into a venv that holds the ros-jazzy-* wheels (requirements.txt), unless it
# has them already: tf2_msgs has no wheel on PyPI (interfaces/README.md). Usage: build_tf2_msgs.sh [venv];
# default: the active one ($VIRTUAL_ENV). Needs cmake and a C compiler, once.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
VENV="$(cd "${1:-${VIRTUAL_ENV:?give the venv, or activate it}}" && pwd)"

"$VENV/bin/python" -c 'import tf2_msgs.msg' 2>/dev/null && exit 0
command -v cmake >/dev/null || { echo "error: cmake is needed once, to build tf2_msgs into $VENV" >&2; exit 1; }
echo "[setup] building the tf2_msgs interface into $VENV (no wheel on PyPI; about 10 s)" >&2
BUILD="$(mktemp -d)"
if ! (cd "$BUILD" && export PATH="$VENV/bin:$PATH" &&
      cmake "$ROOT/interfaces/tf2_msgs" -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
        -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF && make -j2 install) >"$BUILD/log" 2>&1; then
  tail -30 "$BUILD/log" >&2
  echo "error: building tf2_msgs failed (whole log: $BUILD/log)" >&2
  exit 1
fi
rm -rf "$BUILD"
"$VENV/bin/python" -c 'import tf2_msgs.msg'
