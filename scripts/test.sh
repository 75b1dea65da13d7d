#!/usr/bin/env bash
# The whole test suite. Extra arguments go to pytest.
source "$(dirname "$0")/venv.sh"
cd "$ROOT"
# The trigger firmware's toolchain (Debian's packages), so the suite also compiles firmware/trigger_mcu.
if ! command -v avr-gcc >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing the AVR toolchain for the firmware build test (Debian: arduino-mk arduino-core-avr gcc-avr avr-libc)"
  { timeout 300 apt-get update -qq && DEBIAN_FRONTEND=noninteractive timeout 300 apt-get install -y -qq \
      arduino-mk arduino-core-avr gcc-avr avr-libc; } >/dev/null 2>&1 \
    || echo "could not install the AVR toolchain; the firmware build test will be skipped"
fi
exec "$VENV/bin/python" -m pytest -p no:cacheprovider "$@"
