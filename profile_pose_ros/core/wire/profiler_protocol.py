"""The profiler device's framed binary stream (docs/profiler_protocol.md): pure encode and decode.

A TCP stream has no message boundaries and a damaged frame must not cost the frames after it, so the
decoder is a byte-fed state machine that looks for the magic, checks version, size and CRC, and on any
failure reports the reason and resynchronises one byte past the bad frame's start.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

MAGIC = b"PPRF"
VERSION = 1
TYPE_PROFILE = 1
TYPE_HEARTBEAT = 2
FRAME_TYPES = (TYPE_PROFILE, TYPE_HEARTBEAT)

HEADER = struct.Struct("<4sBBHIQIdd")  # magic, version, type, reserved, trigger, device_us, n, x0, pitch
CRC = struct.Struct("<I")
HEADER_SIZE = HEADER.size + CRC.size  # 44: the header has its own CRC, so a damaged length is caught at once
MAX_POINTS = 65535

Z_UNIT = 1e-8  # m per count (0.01 um, the LJ-X8000's height unit)
INVALID_Z = -(2 ** 31)  # the code the device sends for "no point"
INVALID_Z_LIMIT = -(2 ** 31) + 16  # every value below this is one of the device's invalid codes


class ProfilerProtocolError(ValueError):
    """A frame that breaks the protocol; the message says which rule."""


@dataclass(frozen=True)
class ProfileFrame:
    trigger_count: int
    device_time_us: int
    x_start: float  # m
    x_pitch: float  # m
    counts: np.ndarray  # (N,) int32 heights in Z_UNIT as the device sent them (< INVALID_Z_LIMIT: no point)
    frame_type: int = TYPE_PROFILE

    @property
    def z(self) -> np.ndarray:
        """(N,) float64 metres, NaN where invalid."""
        return z_metres(self.counts)

    @property
    def points(self) -> np.ndarray:
        """(N, 2) [x, z] in the profiler frame."""
        x = self.x_start + self.x_pitch * np.arange(len(self.counts))
        return np.column_stack([x, self.z])

    def xyz_table(self) -> bytes:
        """The profile as DESIGN.md's point table (x, y = 0, z as float32, 12 bytes a point; NaN x, y and z
        where there is no point), straight from the counts: the bytes profile_cloud.encode_profile(points)
        gives (a test holds them equal), without the float64 points in between, which cost a third more
        per frame."""
        valid = self.counts >= INVALID_Z_LIMIT
        table = np.empty((len(self.counts), 3), dtype="<f4")
        table[:, 0] = np.where(valid, _x_grid(self.x_start, self.x_pitch, len(self.counts)), np.float32(np.nan))
        table[:, 1] = np.where(valid, np.float32(0.0), np.float32(np.nan))
        table[:, 2] = self.z
        return table.tobytes()


@lru_cache(maxsize=8)
def _x_grid(x_start: float, x_pitch: float, n: int) -> np.ndarray:
    """A device's x grid as float32 (the same for every profile of a run)."""
    grid = (x_start + x_pitch * np.arange(n)).astype(np.float32)
    grid.flags.writeable = False
    return grid


def z_counts(z: np.ndarray) -> np.ndarray:
    """Metres -> the device's int32 counts, NaN (and anything out of range) -> INVALID_Z."""
    z = np.asarray(z, dtype=np.float64)
    counts = np.full(len(z), INVALID_Z, dtype=np.int64)
    ok = np.isfinite(z)
    counts[ok] = np.rint(z[ok] / Z_UNIT)
    counts[(counts < INVALID_Z_LIMIT) | (counts > 2 ** 31 - 1)] = INVALID_Z
    return counts.astype("<i4")


def z_metres(counts: np.ndarray) -> np.ndarray:
    counts = np.asarray(counts)
    z = counts.astype(np.float64) * Z_UNIT
    z[counts < INVALID_Z_LIMIT] = np.nan
    return z


def encode_frame(trigger_count: int, device_time_us: int, x_start: float, x_pitch: float,
                 z: np.ndarray | None, frame_type: int = TYPE_PROFILE, version: int = VERSION) -> bytes:
    """One frame; z in metres (NaN = invalid). A heartbeat carries no points."""
    counts = z_counts(z) if z is not None else np.zeros(0, dtype="<i4")
    header = HEADER.pack(MAGIC, version, frame_type, 0, trigger_count & 0xFFFFFFFF,
                         device_time_us & 0xFFFFFFFFFFFFFFFF, len(counts), x_start, x_pitch)
    body = header + CRC.pack(zlib.crc32(header)) + counts.tobytes()
    return body + CRC.pack(zlib.crc32(body))


def decode_frame(data: bytes) -> ProfileFrame:
    """Exactly one complete frame; raises ProfilerProtocolError."""
    decoder = FrameDecoder()
    results = decoder.feed(data)
    for result in results:
        if isinstance(result, ProfilerProtocolError):
            raise result
    left = decoder.buffered + decoder.skipped_bytes
    if left:
        raise ProfilerProtocolError(f"{left} bytes left over (truncated or trailing data)")
    if len(results) != 1:
        raise ProfilerProtocolError(f"expected one frame, decoded {len(results)}")
    return results[0]


class FrameDecoder:
    """Feed bytes in any chunking; get frames and errors (ProfilerProtocolError instances) in stream order."""

    def __init__(self, max_points: int = MAX_POINTS) -> None:
        self.max_points = max_points
        self._buffer = bytearray()
        self.skipped_bytes = 0  # bytes discarded while looking for a frame start

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def reset(self) -> None:
        self._buffer.clear()

    def feed(self, data: bytes) -> list[ProfileFrame | ProfilerProtocolError]:
        self._buffer += data
        out: list[ProfileFrame | ProfilerProtocolError] = []
        while True:
            item = self._next()
            if item is None:
                return out
            out.append(item)

    def _discard(self, count: int) -> None:
        del self._buffer[:count]
        self.skipped_bytes += count

    def _next(self) -> ProfileFrame | ProfilerProtocolError | None:
        buf = self._buffer
        start = buf.find(MAGIC)
        if start < 0:  # keep a possible partial magic at the end
            keep = next((k for k in range(len(MAGIC) - 1, 0, -1) if buf.endswith(MAGIC[:k])), 0)
            if len(buf) - keep:
                self._discard(len(buf) - keep)
            return None
        if start:
            self._discard(start)
            return ProfilerProtocolError(f"garbage before frame: {start} bytes skipped")
        if len(buf) < HEADER_SIZE:
            return None
        _, version, frame_type, _, trigger, device_us, n, x0, pitch = HEADER.unpack_from(buf)
        (header_crc,) = CRC.unpack_from(buf, HEADER.size)
        problem = None
        if zlib.crc32(memoryview(buf)[:HEADER.size]) != header_crc:
            problem = "header checksum mismatch"
        elif version != VERSION:
            problem = f"unsupported protocol version {version} (this driver speaks {VERSION})"
        elif frame_type not in FRAME_TYPES:
            problem = f"unknown frame type {frame_type}"
        elif n > self.max_points:
            problem = f"point count {n} exceeds {self.max_points}"
        elif frame_type == TYPE_PROFILE and not (np.isfinite(x0) and np.isfinite(pitch) and pitch > 0):
            problem = f"bad x grid: start {x0!r}, pitch {pitch!r}"
        if problem:
            self._discard(1)
            return ProfilerProtocolError(problem)
        size = HEADER_SIZE + 4 * n + CRC.size
        if len(buf) < size:
            return None
        (crc,) = CRC.unpack_from(buf, size - CRC.size)
        if zlib.crc32(memoryview(buf)[: size - CRC.size]) != crc:
            self._discard(1)
            return ProfilerProtocolError(f"checksum mismatch in frame for trigger {trigger}")
        counts = np.frombuffer(bytes(buf[HEADER_SIZE: HEADER_SIZE + 4 * n]), dtype="<i4")
        del buf[:size]
        return ProfileFrame(trigger, device_us, x0, pitch, counts, frame_type)
