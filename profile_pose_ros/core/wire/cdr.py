"""Little-endian CDR, the bytes ROS 2 middlewares send, read and written field by field: the pieces the
profile (profile_cdr.py) and the loop's small messages (pose_cdr.py) share. Alignment counts from after
the 4-byte encapsulation header; padding is written as zeros."""
from __future__ import annotations

import struct

ENCAPSULATION = b"\x00\x01\x00\x00"  # kind: plain CDR, little-endian; then two option bytes
HEADER = len(ENCAPSULATION)
STAMP = struct.Struct("<iI")  # std_msgs/Header's stamp: sec, nanosec
U32 = struct.Struct("<I")


class CdrReader:
    """Reads fields in order; anything short or malformed raises `error` (the caller's documented type)."""

    def __init__(self, data: bytes, error: type[ValueError], kind: str) -> None:
        if data[:2] != ENCAPSULATION[:2]:
            raise error(f"not a little-endian CDR message (encapsulation {data[:2].hex() or 'missing'})")
        self.data = data
        self.view = memoryview(data)
        self.at = HEADER
        self.error = error
        self.kind = kind  # for messages: "serialized cloud ends at byte ..."

    def align(self, size: int) -> None:
        self.at += -(self.at - HEADER) % size

    def unpack(self, layout: struct.Struct, what: str) -> tuple:
        try:
            values = layout.unpack_from(self.data, self.at)
        except struct.error:
            raise self.error(f"{self.kind} ends at byte {len(self.data)}, inside {what}") from None
        self.at += layout.size
        return values

    def u32(self, what: str) -> int:
        self.align(4)
        return self.unpack(U32, what)[0]

    def byte(self, what: str) -> int:
        if self.at >= len(self.data):
            raise self.error(f"{self.kind} ends at byte {len(self.data)}, inside {what}")
        self.at += 1
        return self.data[self.at - 1]

    def block(self, size: int, what: str) -> memoryview:
        if size > len(self.data) - self.at:
            raise self.error(f"{what} says {size} bytes but only {len(self.data) - self.at} follow")
        self.at += size
        return self.view[self.at - size:self.at]

    def string(self, what: str, max_size: int | None = None) -> str:
        """A CDR string (length with its NUL, the bytes, the NUL); max_size bounds the length field."""
        size = self.u32(what)
        if max_size is not None and size > max_size:
            raise self.error(f"{what} says {size} bytes: a corrupt length, not a name")
        raw = self.block(size, what)
        if size == 0 or raw[-1] != 0:
            raise self.error(f"{what} is not a NUL-terminated CDR string")
        try:
            return bytes(raw[:-1]).decode("utf-8")
        except UnicodeDecodeError:
            raise self.error(f"{what} is not UTF-8") from None

    def header(self, max_frame_id: int | None = None) -> tuple[int, str]:
        """std_msgs/Header: (stamp in ns, frame_id)."""
        sec, nanosec = self.unpack(STAMP, "header.stamp")
        return sec * 1_000_000_000 + nanosec, self.string("header.frame_id", max_frame_id)


class CdrWriter:
    def __init__(self) -> None:
        self.out = bytearray(ENCAPSULATION)

    def align(self, size: int) -> None:
        self.out += bytes(-(len(self.out) - HEADER) % size)

    def pack(self, layout: struct.Struct, *values) -> None:
        self.out += layout.pack(*values)

    def u32(self, value: int) -> None:
        self.align(4)
        self.pack(U32, value)

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\x00"
        self.u32(len(raw))
        self.out += raw

    def header(self, frame_id: str) -> None:
        """std_msgs/Header stamped zero: a prefix built once per frame, stamped per message by `stamped`."""
        self.pack(STAMP, 0, 0)
        self.string(frame_id)


def stamped(prefix: bytes, sec: int, nanosec: int) -> bytes:
    """A prefix CdrWriter.header() began, with its stamp set."""
    return prefix[:HEADER] + STAMP.pack(sec, nanosec) + prefix[HEADER + STAMP.size:]
