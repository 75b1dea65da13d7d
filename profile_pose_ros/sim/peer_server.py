"""A TCP listener that serves one peer at a time, as the cell's devices do.

`replace`: a new connection takes over from the old one (a profiler or serial adapter after the host
rebooted); `refuse`: a second peer is closed at once while the first is connected (a robot controller
must never take commands from two clients).
"""
from __future__ import annotations

import socket
import threading
import time
from typing import Callable


class PeerServer:
    def __init__(self, name: str, host: str = "127.0.0.1", port: int = 0, policy: str = "replace",
                 on_connect: Callable[[socket.socket], None] | None = None) -> None:
        if policy not in ("replace", "refuse"):
            raise ValueError(f"policy must be 'replace' or 'refuse', not {policy!r}")
        self.name = name
        self.policy = policy
        self.on_connect = on_connect
        self._listener = socket.create_server((host, port), reuse_port=False)
        self._listener.settimeout(0.2)
        self.host, self.port = self._listener.getsockname()[:2]
        self._peer: socket.socket | None = None
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self.connections = self.refused = 0
        # the device's own view of a reconnect: how long it went without a peer after dropping one (its
        # monotonic clock), whatever the host's stamps or the rate of the trigger clock say
        self.reconnect_delays: list[float] = []
        self._dropped_at: float | None = None
        self._thread = threading.Thread(target=self._accept_loop, name=f"{name}-accept", daemon=True)

    def start(self) -> "PeerServer":
        self._thread.start()
        return self

    @property
    def peer(self) -> socket.socket | None:
        return self._peer

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                if self._peer is not None and self.policy == "refuse":
                    self.refused += 1
                    conn.close()
                    continue
                old, self._peer = self._peer, conn
                self.connections += 1
                if self._dropped_at is not None:
                    self.reconnect_delays.append(time.monotonic() - self._dropped_at)
                    self._dropped_at = None
            if old is not None:
                _close(old)
            if self.on_connect is not None:
                self.on_connect(conn)

    def send(self, data: bytes) -> bool:
        """Send to the current peer; on any error drop the peer. False if nothing was sent."""
        peer = self._peer
        if peer is None:
            return False
        try:
            with self._send_lock:  # whole frames: two threads' sendall calls must not interleave
                peer.sendall(data)
            return True
        except OSError:
            self.drop(peer)
            return False

    def drop(self, peer: socket.socket | None = None) -> None:
        """Close the current peer (only if it is still `peer`, when given)."""
        with self._lock:
            if self._peer is None or (peer is not None and peer is not self._peer):
                return
            old, self._peer = self._peer, None
            self._dropped_at = time.monotonic()
        _close(old)

    def close(self) -> None:
        self._stop.set()
        self.drop()
        _close(self._listener)
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)


def _close(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()
