"""The trigger microcontroller's serial line protocol (firmware/trigger_mcu/README.md): pure parsing.

MCU -> host, one ASCII line each, '\\n'-terminated:
    T <seq> <micros>      a trigger was fired (seq counts from 1 after boot or RESET; micros: 32-bit,
                          wraps every 71.6 min)
    PONG <micros>         answer to PING
    OK <command>          RESET, ARM or DISARM done
    READY <name> <version>   after boot and after RESET
    E <text>              the MCU did not understand a command
host -> MCU: PING, RESET, ARM, DISARM.
"""
from __future__ import annotations

from dataclasses import dataclass

MICROS_WRAP = 2 ** 32
MAX_LINE = 64  # longer lines are garbage, not a protocol message
COMMANDS = ("PING", "RESET", "ARM", "DISARM")


class TriggerLineError(ValueError):
    """A line that is not a protocol message (garbage on the serial line, a cut line)."""


@dataclass(frozen=True)
class Trigger:
    seq: int
    micros: int


@dataclass(frozen=True)
class Pong:
    micros: int


@dataclass(frozen=True)
class Ack:
    command: str


@dataclass(frozen=True)
class Ready:
    name: str
    version: str


@dataclass(frozen=True)
class McuError:
    text: str


McuMessage = Trigger | Pong | Ack | Ready | McuError


def _u32(text: str, what: str) -> int:
    if not text.isdigit():
        raise TriggerLineError(f"{what} '{text}' is not an unsigned integer")
    value = int(text)
    if value >= MICROS_WRAP:
        raise TriggerLineError(f"{what} {value} does not fit 32 bits")
    return value


def parse_line(line: bytes) -> McuMessage:
    """One line without its terminator; raises TriggerLineError."""
    if len(line) > MAX_LINE:
        raise TriggerLineError(f"line of {len(line)} bytes (max {MAX_LINE})")
    try:
        text = line.decode("ascii").strip()
    except UnicodeDecodeError:
        raise TriggerLineError(f"non-ASCII bytes: {line[:16]!r}") from None
    parts = text.split()
    if not parts:
        raise TriggerLineError("empty line")
    kind, args = parts[0], parts[1:]
    if kind == "T" and len(args) == 2:
        return Trigger(_u32(args[0], "sequence"), _u32(args[1], "micros"))
    if kind == "PONG" and len(args) == 1:
        return Pong(_u32(args[0], "micros"))
    if kind == "OK" and len(args) == 1 and args[0] in COMMANDS:
        return Ack(args[0])
    if kind == "READY" and len(args) == 2:
        return Ready(args[0], args[1])
    if kind == "E":
        return McuError(" ".join(args))
    raise TriggerLineError(f"not a trigger-MCU message: {text[:32]!r}")


def format_trigger(seq: int, micros: int) -> bytes:
    return f"T {seq} {micros % MICROS_WRAP}\n".encode()


class MicrosUnwrapper:
    """32-bit micros -> a monotonic 64-bit count (the MCU clock wraps every 71.6 minutes)."""

    def __init__(self) -> None:
        self._last: int | None = None
        self._epochs = 0

    def reset(self) -> None:
        self._last, self._epochs = None, 0

    def __call__(self, micros: int) -> int:
        if self._last is not None and micros < self._last and self._last - micros > MICROS_WRAP // 2:
            self._epochs += 1
        self._last = micros
        return self._epochs * MICROS_WRAP + micros
