"""The trigger MCU's firmware compiles for the Arduino Nano (Debian's arduino-mk toolchain)."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import ROOT

ARDUINO_MK = Path("/usr/share/arduino/Arduino.mk")


@pytest.mark.skipif(not (shutil.which("avr-gcc") and shutil.which("make") and ARDUINO_MK.exists()),
                    reason="AVR toolchain not installed (scripts/test.sh installs it on Debian as root)")
def test_trigger_firmware_builds_for_the_nano(tmp_path) -> None:
    work = tmp_path / "trigger_mcu"
    shutil.copytree(ROOT / "firmware" / "trigger_mcu", work, ignore=shutil.ignore_patterns("build-*"))
    result = subprocess.run(["make"], cwd=work, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    hex_file = work / "build-nano-atmega328" / "trigger_mcu.hex"
    assert hex_file.exists()
    program = next(line for line in result.stdout.splitlines() if line.strip().startswith("Program:"))
    assert int(program.split()[1]) < 30720  # fits the Nano's flash beside its bootloader
