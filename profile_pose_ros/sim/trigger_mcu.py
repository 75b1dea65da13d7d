"""The simulated trigger microcontroller, reachable as pyserial's `socket://127.0.0.1:<port>`.

It behaves like firmware/trigger_mcu: on each robot signal, if armed, it fires the profiler and writes
`T <seq> <micros>`; it answers PING, RESET, ARM and DISARM. Its clock runs at its own rate (a ceramic
resonator's drift) and wraps at 32 bits like Arduino's micros(); each line reaches the host after its
serial transmission time at the configured baud rate, and a command takes effect after its own.
"""
from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..core.wire.trigger_protocol import COMMANDS, MICROS_WRAP, format_trigger
from .peer_server import PeerServer
from .precise_wait import wait_until

FIRMWARE_NAME, FIRMWARE_VERSION = "trigger_mcu", "1"


@dataclass
class McuFaults:
    silent: bool = False  # fires triggers but writes and answers nothing (a dead USB-serial link)
    garbage_fraction: float = 0.0  # per trigger: a line of line noise before the T line
    close_after_triggers: int = 0  # drop the serial connection after every this many triggers (0: never)
    reboot_after_triggers: int = 0  # the board restarts by itself after every this many triggers (0: never)


class TriggerMcu:
    def __init__(self, host: str = "127.0.0.1", port: int = 0, baudrate: int = 1_000_000,
                 drift_ppm: float = 300.0, micros_start: int = 0, faults: McuFaults | None = None,
                 seed: int = 1) -> None:
        self.baudrate = baudrate
        self.drift = drift_ppm * 1e-6
        self.micros_start = micros_start
        self.faults = faults or McuFaults()
        self.rng = np.random.default_rng(seed)
        self.boot_ns = time.monotonic_ns()
        self.armed = True  # the firmware boots armed, so a cell without this driver still triggers
        self.seq = 0
        self.lines_sent = self.commands = self.closes = self.reboots = 0
        self._fired = 0  # triggers fired, which the scheduled faults count
        self._lock = threading.Lock()
        self._uart = threading.Lock()
        self._line_free_at = 0.0
        self._stop = False
        self.server = PeerServer("trigger_mcu", host, port, policy="replace", on_connect=self._on_connect)

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return f"socket://{self.server.host}:{self.port}"

    def start(self) -> "TriggerMcu":
        self.server.start()
        return self

    def micros(self, monotonic_ns: int | None = None) -> int:
        now = time.monotonic_ns() if monotonic_ns is None else monotonic_ns
        return int(self.micros_start + (now - self.boot_ns) * (1.0 + self.drift) / 1000.0) % MICROS_WRAP

    def robot_signal(self, monotonic_ns: int) -> int | None:
        """The robot controller's per-cycle output edge: the sequence number fired, or None if disarmed."""
        with self._lock:
            if not self.armed:
                return None
            self.seq = (self.seq + 1) % MICROS_WRAP
            seq = self.seq
        if self.faults.garbage_fraction > 0 and self.rng.random() < self.faults.garbage_fraction:
            self._write(self.rng.integers(32, 127, int(self.rng.integers(1, 40)), dtype=np.uint8).tobytes() + b"\n")
        self._write(format_trigger(seq, self.micros(monotonic_ns)))
        self._scheduled_faults()
        return seq

    def _scheduled_faults(self) -> None:
        self._fired += 1
        close_every, reboot_every = self.faults.close_after_triggers, self.faults.reboot_after_triggers
        if close_every and self._fired % close_every == 0:
            self.closes += 1
            self.server.drop()  # the host sees the serial server go away and opens the port again
        if reboot_every and self._fired % reboot_every == 0:
            self.reboots += 1
            self.reboot()

    # ---------------------------------------------------------------- serial side
    def _write(self, line: bytes) -> None:
        """Put a line on the simulated wire: it reaches the host when its last bit would, one line after
        another like a UART. The calling thread waits out the transmission itself (precise_wait: sleeping,
        then spinning for the last part): a writer thread would add its own wake-up delay, which a UART
        does not have."""
        if self.faults.silent:
            return
        with self._uart:
            due = max(time.monotonic(), self._line_free_at) + 10.0 * len(line) / self.baudrate  # 8N1
            self._line_free_at = due
            wait_until(due)
            if self.server.send(line):
                self.lines_sent += 1

    def _on_connect(self, conn: socket.socket) -> None:
        # Opening a Nano's USB serial port resets the board (DTR).
        self.reboot(wait=False)
        threading.Thread(target=self._read_loop, args=(conn,), name="mcu-read", daemon=True).start()

    def reboot(self, wait: bool = True) -> None:
        """Power cycle or watchdog: the board boots armed, its clock restarts (from micros_start, to exercise
        the 32-bit wrap), and it says READY."""
        with self._lock:
            self.seq, self.armed = 0, True
        self.boot_ns = time.monotonic_ns()
        ready = f"READY {FIRMWARE_NAME} {FIRMWARE_VERSION}\n".encode()
        if wait:
            self._write(ready)
        else:
            threading.Thread(target=self._write, args=(ready,), daemon=True).start()

    def _read_loop(self, conn: socket.socket) -> None:
        buffer = b""
        while not self._stop:
            try:
                data = conn.recv(256)
            except OSError:
                return
            if not data:
                return
            received = time.monotonic()
            buffer += data
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                wait_until(received + 10.0 * (len(line) + 1) / self.baudrate)  # the command's last bit arrives
                self._command(line.strip().decode("ascii", "replace"))
            buffer = buffer[-64:]  # the firmware's line buffer is small too

    def _command(self, command: str) -> None:
        self.commands += 1
        if command not in COMMANDS:
            self._write(f"E unknown command {command[:20]}\n".encode())
            return
        with self._lock:
            if command == "RESET":
                self.seq = 0
            elif command in ("ARM", "DISARM"):
                self.armed = command == "ARM"
        if command == "PING":
            self._write(f"PONG {self.micros()}\n".encode())
            return
        self._write(f"OK {command}\n".encode())
        if command == "RESET":
            self._write(f"READY {FIRMWARE_NAME} {FIRMWARE_VERSION}\n".encode())

    def close(self) -> None:
        self._stop = True
        self.server.close()
