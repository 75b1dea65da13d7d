#!/usr/bin/env bash
# The whole test suite. Extra arguments go to pytest.
source "$(dirname "$0")/venv.sh"
cd "$ROOT"
# The prebuilt estimator kernel (a minute or two, the first time on a machine) builds while the toolchain below
# installs; the suite's first estimate would otherwise build it, alone. If a new venv started it already
# (venv.sh), this waits for that build instead of making a second (the build's lock).
"$VENV/bin/python" -m profile_pose_ros.core.compiled.aot build >/dev/null 2>&1 &
KERNEL_BUILD=$!
# Beside it, on the other core: numba's JIT of the same kernels, cached on disk, for the tests that compare the
# prebuilt kernel with it or time its stages (about 70 s of compiling they would otherwise do inside the suite).
PROFILE_POSE_KERNEL=jit "$VENV/bin/python" - >/dev/null 2>&1 <<'PY' &
import numpy as np
from profile_pose_ros.core import EstimatorOptions, Gauge, render_profile, sample_pose
from profile_pose_ros.resources import config_path
from profile_pose_ros.tools.benchmark import time_ours
gauge = Gauge.from_yaml(config_path("gauge_paper_n5.yaml"))
rng = np.random.default_rng(0)
time_ours(gauge, [render_profile(gauge, *sample_pose(gauge, rng), noise_std=5e-6, rng=rng) for _ in range(3)],
          EstimatorOptions())
PY
JIT_WARM_UP=$!
# The trigger firmware's toolchain (Debian's packages), so the suite also compiles firmware/trigger_mcu.
if ! command -v avr-gcc >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing the AVR toolchain for the firmware build test (Debian: arduino-mk arduino-core-avr gcc-avr avr-libc)"
  { timeout 300 apt-get update -qq && DEBIAN_FRONTEND=noninteractive timeout 300 apt-get install -y -qq \
      arduino-mk arduino-core-avr gcc-avr avr-libc; } >/dev/null 2>&1 \
    || echo "could not install the AVR toolchain; the firmware build test will be skipped"
fi
wait "$KERNEL_BUILD" || echo "the prebuilt kernel could not be built here; the suite runs the JIT-compiled one"
wait "$JIT_WARM_UP" || echo "numba's JIT could not be warmed up; the tests that use it compile it themselves"
# On every core (up to four workers), a test file to a worker so that a module's fixtures are made once; the
# tests marked `alone` (they judge the live loop's timing, or load the machine) take turns with everything
# else (test/conftest.py). `-n 0` after this command runs the suite serially.
exec "$VENV/bin/python" -m pytest -p no:cacheprovider --numprocesses auto --maxprocesses 4 --dist loadfile "$@"
