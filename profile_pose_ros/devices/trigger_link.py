"""The host side of the trigger MCU's serial link (pyserial URL: a device path, socket://, loop://).

One thread reads lines, maps the MCU clock to host time (clock_sync.ClockMap fed by T and PONG lines),
pings to detect silence, and reopens the port on any error. It never raises into the driver.
"""
from __future__ import annotations

import select
import socket
import struct
import sys
import threading
import time
from collections import deque
from typing import Callable

import serial

from ..core.timing.clock_sync import ClockMap
from ..core.wire.trigger_protocol import (MAX_LINE, MICROS_WRAP, Ack, McuError, MicrosUnwrapper, Pong, Ready, Trigger,
                                          TriggerLineError, parse_line)

DISCONNECTED, CONNECTING, OK, SILENT = "disconnected", "connecting", "ok", "silent"
AUTO_LATENCY = -1.0  # trigger_latency: estimate the one-way link latency as half the fastest PING round trip
RTT_WINDOW = 200  # round trips kept for that estimate
KERNEL_STAMP = struct.Struct("qq")  # struct timespec (64-bit Linux)
# Linux's value (asm-generic/socket.h) where Python's socket module does not export the name
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform.startswith("linux") else None)
READY_WINDOW_S = 1.0  # a READY this soon after our RESET or our opening the port is the expected one
CONVERGING_PING_PERIOD = 0.02  # s: ping faster until the clock map has a few seconds of samples
PONG_TIMEOUT_S = 0.5  # an unanswered PING this old is lost (the MCU answers within milliseconds)


class TriggerLink:
    def __init__(self, url: str, baudrate: int, on_trigger: Callable[[int, float, float], None],
                 on_resync_needed: Callable[[str], None], trigger_latency: float = AUTO_LATENCY,
                 ping_period: float = 0.05, silent_after: float = 1.0, training_pings: int = 20,
                 reopen_delay: float = 0.5) -> None:
        self.url, self.baudrate = url, baudrate
        self.on_trigger, self.on_resync_needed = on_trigger, on_resync_needed
        self.trigger_latency = trigger_latency
        self.ping_period, self.silent_after = ping_period, silent_after
        self.training_pings, self.reopen_delay = training_pings, reopen_delay
        self.clock = ClockMap()  # MCU seconds -> host time the line would arrive with zero latency
        self._pings: deque[float] = deque(maxlen=64)  # host send times of unanswered PINGs
        self._round_trips: deque[float] = deque(maxlen=RTT_WINDOW)
        self._unwrap = MicrosUnwrapper()
        self.state = DISCONNECTED
        self.last_error = ""
        self.lines = self.triggers = self.bad_lines = self.triggers_lost = self.reopens = self.mcu_errors = 0
        self._last_seq: int | None = None
        self._last_micros: int | None = None
        self._port: serial.SerialBase | None = None
        self._socket: socket.socket | None = None
        self._write_lock = threading.Lock()
        self._acks: dict[str, threading.Event] = {}
        self.ready_expected_until = 0.0  # monotonic: a READY before this answers our RESET or connection
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="trigger-link", daemon=True)

    def start(self) -> "TriggerLink":
        self._thread.start()
        return self

    @property
    def kernel_timestamps(self) -> bool:
        return self._socket is not None

    @property
    def ok(self) -> bool:
        return self.state == OK

    # ---------------------------------------------------------------- commands
    def command(self, command: str, timeout: float = 0.3) -> bool:
        """Send a command and wait for its OK; False if the MCU did not acknowledge in time."""
        event = self._acks.setdefault(command, threading.Event())
        event.clear()
        if command == "RESET":
            self.ready_expected_until = time.monotonic() + READY_WINDOW_S
        if not self._write(command):
            return False
        return event.wait(timeout)

    def _write(self, command: str) -> bool:
        with self._write_lock:
            port = self._port
            if port is None:
                return False
            try:
                if command == "PING":  # before writing: after it, this thread may wait for the GIL
                    self._pings.append(time.time())
                port.write(command.encode() + b"\n")
                return True
            except (serial.SerialException, OSError) as exc:
                self.last_error = f"write {command}: {exc}"
                return False

    # ---------------------------------------------------------------- reading
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.02)
            except (serial.SerialException, OSError, ValueError) as exc:
                self.last_error = f"open {self.url}: {exc}"
                self._stop.wait(self.reopen_delay)
                continue
            self.state = CONNECTING
            self._pings.clear()
            self._forget_device()
            self.ready_expected_until = time.monotonic() + READY_WINDOW_S
            # Opening a USB serial port resets the board (DTR); a network serial server may have lost lines
            # while away. Either way the counters and clock start over. Do not wait for the board's READY:
            # pyserial's open() flushes input, so a READY that is quick enough is never seen.
            self.on_resync_needed("trigger MCU (re)connected")
            self._socket = self._kernel_stamped_socket(self._port)
            self._session()
            with self._write_lock:
                port, self._port = self._port, None
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass
            self.state = DISCONNECTED
            self.reopens += 1
            self._stop.wait(self.reopen_delay)

    @staticmethod
    def _kernel_stamped_socket(port) -> socket.socket | None:
        """pyserial's socket:// port's socket, with kernel receive timestamps on (Linux); else None."""
        sock = getattr(port, "_socket", None)
        if not isinstance(sock, socket.socket) or SO_TIMESTAMPNS is None:
            return None
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError:
            return None
        return sock

    def _session(self) -> None:
        buffer = b""
        last_line = last_ping = time.monotonic()
        pings = 0
        while not self._stop.is_set():
            now = time.monotonic()
            if self._may_ping():
                if self.state == CONNECTING and pings < self.training_pings and now - last_ping > 0.005:
                    self._write("PING")  # train the clock map before the first trigger needs it
                    pings, last_ping = pings + 1, now
                elif now - last_ping > (self.ping_period if self.clock.converged else CONVERGING_PING_PERIOD):
                    self._write("PING")
                    last_ping = now
            if now - last_line > self.silent_after and self.state in (OK, CONNECTING):
                self.state = SILENT
                self.last_error = f"MCU silent for {now - last_line:.1f} s"
            try:
                data, arrival = self._read()
            except (serial.SerialException, OSError) as exc:
                self.last_error = f"read: {exc}"
                return
            if not data:
                continue
            buffer += data
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                last_line = time.monotonic()
                self._handle(line, arrival)
            if len(buffer) > MAX_LINE:  # noise without a newline
                self.bad_lines += 1
                buffer = b""
            if self.state == SILENT or (self.state == CONNECTING and pings >= self.training_pings):
                if self.clock.ready:
                    self.state = OK

    def _read(self) -> tuple[bytes, float]:
        """Bytes and their arrival time. A network serial server (socket://) gets the kernel's receive
        timestamp, so the time this thread takes to wake up and get the GIL is not in it."""
        sock = self._socket
        if sock is None:
            data = self._port.read(max(1, self._port.in_waiting))
            return data, time.time()
        ready, _, _ = select.select([sock], [], [], 0.02)
        if not ready:
            return b"", 0.0
        data, ancillary, _, _ = sock.recvmsg(4096, socket.CMSG_SPACE(KERNEL_STAMP.size))
        if not data:
            raise ConnectionError("the MCU's serial server closed the connection")
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                seconds, nanoseconds = KERNEL_STAMP.unpack(payload[:KERNEL_STAMP.size])
                return data, seconds + nanoseconds * 1e-9
        return data, time.time()

    def _handle(self, line: bytes, arrival: float) -> None:
        self.lines += 1
        try:
            message = parse_line(line)
        except TriggerLineError as exc:
            self.bad_lines += 1
            self.last_error = f"bad line: {exc}"
            return
        sent_at = arrival - self._transmission(len(line) + 1)
        delay_bound = float("inf")
        if isinstance(message, Pong):
            if self._pings:
                ping_sent = self._pings.popleft()
                delay_bound = sent_at - ping_sent - self._transmission(len("PING\n"))
                self._round_trips.append(delay_bound)
        if isinstance(message, (Trigger, Pong)):
            device_s = self._clock_sample(message.micros, sent_at, delay_bound)
        if isinstance(message, Trigger):
            self.triggers += 1
            if self._last_seq is not None and message.seq > self._last_seq + 1:
                self.triggers_lost += message.seq - self._last_seq - 1
            self._last_seq = message.seq
            self.on_trigger(message.seq, self.clock.to_host(device_s) - self.latency, self.clock.error_bound)
        elif isinstance(message, Ack):
            self._acks.setdefault(message.command, threading.Event()).set()
        elif isinstance(message, Ready):
            self._last_seq = None
            if time.monotonic() > self.ready_expected_until:  # the MCU rebooted by itself (power,
                self._forget_device()  #                           watchdog): its clock and counter restarted
                self.on_resync_needed("trigger MCU restarted")
        elif isinstance(message, McuError):
            self.mcu_errors += 1
            self.last_error = f"MCU: {message.text}"

    def _may_ping(self) -> bool:
        """One PING at a time: a PONG carries no number, so with several outstanding a lost PONG (an MCU
        gone silent) would pair every later PONG with an earlier PING, for good. One unanswered for
        PONG_TIMEOUT_S is taken as lost."""
        if self._pings and time.time() - self._pings[-1] < PONG_TIMEOUT_S:
            return False
        self._pings.clear()
        return True

    def _forget_device(self) -> None:
        self._unwrap.reset()
        self._last_micros = None
        self._last_seq = None
        self.clock.reset("the MCU (re)started")

    def _transmission(self, n_bytes: int) -> float:
        return 10.0 * n_bytes / self.baudrate  # 8N1: ten bits per byte

    @property
    def latency(self) -> float:
        """One-way delay from the MCU writing a line to this thread reading it, beyond transmission (s)."""
        if self.trigger_latency >= 0:
            return self.trigger_latency
        return max(0.0, self.fastest_round_trip / 2) if self._round_trips else 0.0

    @property
    def fastest_round_trip(self) -> float:
        """Shortest recent PING -> PONG time net of transmission (s): an upper bound on each way's latency."""
        return min(self._round_trips) if self._round_trips else float("nan")

    def _clock_sample(self, micros: int, sent_at: float, delay_bound: float) -> float:
        """Feed the clock map; returns the line's MCU time in seconds (unwrapped)."""
        last = self._last_micros
        if last is not None and 1_000_000 < last - micros < MICROS_WRAP // 2:
            # back by over a second without wrapping: the MCU restarted (lines can be a few us out of
            # order when a PONG and a trigger race for the UART, so small steps back are normal)
            self._unwrap.reset()
            self.clock.reset("the MCU's clock went back over a second")
        self._last_micros = micros
        device_s = self._unwrap(micros) * 1e-6
        self.clock.add(device_s, sent_at, delay_bound)
        return device_s

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
