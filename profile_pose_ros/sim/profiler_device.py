"""The simulated profiler controller: one frame per trigger on its TCP data port, with injectable faults."""
from __future__ import annotations

import heapq
import itertools
import threading
import time
import zlib
from dataclasses import dataclass

import numpy as np

from ..core.wire.profiler_protocol import CRC, HEADER, HEADER_SIZE, TYPE_HEARTBEAT, encode_frame
from .peer_server import PeerServer

CORRUPT_MODES = ("flip", "truncate", "version", "garbage")


@dataclass
class ProfilerFaults:
    """Changed at run time by sim_cell's parameters; read once per frame."""

    drop_fraction: float = 0.0  # frames rendered and counted but never sent
    delay_s: float = 0.0  # extra delay before a frame is sent
    corrupt_fraction: float = 0.0
    corrupt_mode: str = "mixed"  # one of CORRUPT_MODES, or "mixed" (cycle through them)
    close_after_frames: int = 0  # close the connection after every this many frames sent (0: never)


def corrupt(frame: bytes, mode: str, rng: np.random.Generator) -> bytes:
    """A damaged copy of a frame, as a bad cable, a firmware mismatch or a half-written buffer gives."""
    if mode == "flip":  # one bit in the payload: only the checksum can tell
        data = bytearray(frame)
        i = int(rng.integers(HEADER_SIZE, len(data) - 4)) if len(data) > HEADER_SIZE + 4 else 5
        data[i] ^= 1 << int(rng.integers(0, 8))
        return bytes(data)
    if mode == "truncate":
        return frame[: int(rng.integers(1, len(frame)))]
    if mode == "version":  # a well-formed frame of a protocol version the driver does not speak
        fields = list(HEADER.unpack_from(frame))
        fields[1] += 1
        header = HEADER.pack(*fields)
        body = header + CRC.pack(zlib.crc32(header)) + frame[HEADER_SIZE:-CRC.size]
        return body + CRC.pack(zlib.crc32(body))
    if mode == "garbage":
        return rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes() + frame
    raise ValueError(f"corrupt_mode must be one of {', '.join(CORRUPT_MODES)} or 'mixed', not {mode!r}")


class ProfilerDevice:
    """Counts triggers, sends frames (delayed, dropped or damaged as configured), and heartbeats when idle."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, heartbeat_s: float = 0.2,
                 faults: ProfilerFaults | None = None, seed: int = 0) -> None:
        self.faults = faults or ProfilerFaults()
        self.heartbeat_s = heartbeat_s
        self.rng = np.random.default_rng(seed)
        self.server = PeerServer("profiler", host, port, policy="replace")
        self.boot_ns = time.monotonic_ns()
        self.trigger_count = 0
        self.frames_sent = self.frames_dropped = self.frames_corrupted = self.closes = 0
        self.frames_unsent = 0  # no client connected
        self._frames_since_close = 0
        self._close_setting = 0
        self._modes = itertools.cycle(CORRUPT_MODES)
        self._queue: list[tuple[float, int, bytes]] = []
        self._order = itertools.count()
        self._wake = threading.Condition()
        self._stop = False
        self._last_sent = time.monotonic()
        self._sender = threading.Thread(target=self._send_loop, name="profiler-send", daemon=True)

    @property
    def port(self) -> int:
        return self.server.port

    def start(self) -> "ProfilerDevice":
        self.server.start()
        self._sender.start()
        return self

    def device_time_us(self) -> int:
        return (time.monotonic_ns() - self.boot_ns) // 1000

    def trigger(self, device_time_us: int, x_start: float, x_pitch: float, z: np.ndarray,
                final: bool = False) -> str:
        """One trigger pulse: count it and queue its frame. Returns what happened to the frame.

        `final` marks the last trigger of a finite run; it is never dropped, so every drop is observable
        as a gap before a later frame.
        """
        self.trigger_count = (self.trigger_count + 1) & 0xFFFFFFFF
        f = self.faults
        if not final and f.drop_fraction > 0 and self.rng.random() < f.drop_fraction:
            self.frames_dropped += 1
            return "dropped"
        frame = encode_frame(self.trigger_count, device_time_us, x_start, x_pitch, z)
        status = "sent"
        if f.corrupt_fraction > 0 and self.rng.random() < f.corrupt_fraction:
            mode = next(self._modes) if f.corrupt_mode == "mixed" else f.corrupt_mode
            frame = corrupt(frame, mode, self.rng)
            self.frames_corrupted += 1
            status = f"corrupted ({mode})"
        if f.delay_s <= 0 and not self._queue:
            self._send_frame(frame)  # straight out from the trigger's thread: no hand-over per frame
            self._last_sent = time.monotonic()
            return status
        with self._wake:
            heapq.heappush(self._queue, (time.monotonic() + f.delay_s, next(self._order), frame))
            self._wake.notify()
        return status

    def _send_loop(self) -> None:
        while True:
            with self._wake:
                while not self._stop:
                    now = time.monotonic()
                    if self._queue and self._queue[0][0] <= now:
                        break
                    due = self._queue[0][0] if self._queue else self._last_sent + self.heartbeat_s
                    if not self._queue and due <= now:
                        break
                    self._wake.wait(timeout=max(due - now, 0.0))
                if self._stop:
                    return
                item = heapq.heappop(self._queue) if self._queue and self._queue[0][0] <= time.monotonic() else None
            if item is None:
                self.server.send(encode_frame(self.trigger_count, self.device_time_us(), 0.0, 1.0, None,
                                              frame_type=TYPE_HEARTBEAT))
            else:
                self._send_frame(item[2])
            self._last_sent = time.monotonic()

    def _send_frame(self, frame: bytes) -> None:
        if not self.server.send(frame):
            self.frames_unsent += 1
            return
        self.frames_sent += 1
        self._frames_since_close += 1
        limit = self.faults.close_after_frames
        if limit != self._close_setting:  # a new setting counts from now
            self._close_setting, self._frames_since_close = limit, 1
        if limit and self._frames_since_close >= limit:
            self._frames_since_close = 0
            self.closes += 1
            self.server.drop()

    def close(self) -> None:
        with self._wake:
            self._stop = True
            self._wake.notify()
        if self._sender.is_alive():
            self._sender.join(timeout=2.0)
        self.server.close()
