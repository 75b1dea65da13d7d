"""Profile sources: what the driver's connection loop reads from. `sim` speaks sim_cell's TCP protocol."""
from __future__ import annotations

import socket
import time
from typing import Protocol

from ..core.wire.profiler_protocol import TYPE_HEARTBEAT, FrameDecoder, ProfileFrame, ProfilerProtocolError

SourceItem = ProfileFrame | ProfilerProtocolError


class ProfileSource(Protocol):
    name: str

    def open(self) -> None:
        """Connect and start streaming; raises OSError (or a subclass) on failure."""

    def read(self, timeout: float) -> list[SourceItem]:
        """Frames and protocol errors received within `timeout` s; raises OSError when the link is lost."""

    def seconds_since_data(self) -> float:
        """Time since the device last sent anything (frames or keep-alives): the stale-input watchdog."""

    def close(self) -> None:
        ...


class SimProfileSource:
    """sim_cell's profiler port: framed binary over TCP (docs/profiler_protocol.md)."""

    def __init__(self, host: str, port: int, connect_timeout: float = 1.0) -> None:
        self.name = f"tcp://{host}:{port}"
        self.host, self.port = host, port
        self.connect_timeout = connect_timeout
        self._sock: socket.socket | None = None
        self._decoder = FrameDecoder()
        self._last_data = time.monotonic()

    def open(self) -> None:
        self.close()
        sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self._sock = sock
        self._decoder.reset()
        self._last_data = time.monotonic()

    def read(self, timeout: float) -> list[SourceItem]:
        if self._sock is None:
            raise ConnectionError("not connected")
        self._sock.settimeout(timeout)
        try:
            data = self._sock.recv(1 << 16)
        except (TimeoutError, socket.timeout):
            return []
        if not data:
            raise ConnectionError("the profiler closed the connection")
        self._last_data = time.monotonic()
        return [item for item in self._decoder.feed(data)
                if not (isinstance(item, ProfileFrame) and item.frame_type == TYPE_HEARTBEAT)]

    def seconds_since_data(self) -> float:
        return time.monotonic() - self._last_data

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None
