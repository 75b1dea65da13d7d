"""A profile as it travels on the wire, a serialized sensor_msgs/PointCloud2 (little-endian CDR), decoded
and encoded without building the ROS message.

rclpy's conversion of a 3200-point cloud into Python objects cost 30-60 us, a fifth of the estimator
node's time per profile at 1 kHz; this reads the few metadata fields with struct (~7 us) and hands the
point table, in place, to decode_profile. A bag's recorded bytes take the very same path in replay.
Anything malformed raises ProfileFormatError, like every other profile check. The driver publishes the
bytes encode_profile_cdr writes: rclpy's serialization but for the alignment padding, which rclpy leaves
as whatever was in memory and this writes as zeros (a test compares them), without building the message
and converting it back (a third of the driver's time per profile).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .profile_cloud import Field, ProfileFormatError, decode_profile, encode_profile

CDR_LE = b"\x00\x01"  # encapsulation kind: plain CDR, little-endian (what ROS 2 middlewares send)
_HEADER = 4  # encapsulation kind and options; CDR alignment counts from after it
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_U32X2 = struct.Struct("<II")
_FIELD_TAIL = struct.Struct("<IB")
_MAX_FIELDS = 64  # a profile has 3 or 4; a huge count is a corrupt length, not a cloud


@dataclass(frozen=True)
class ProfileMessage:
    stamp_sec: int
    stamp_nanosec: int
    frame_id: str
    points: np.ndarray  # (N, 2) [x, z], as decode_profile returns them

    @property
    def stamp_ns(self) -> int:
        return self.stamp_sec * 1_000_000_000 + self.stamp_nanosec


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.view = memoryview(data)
        self.at = _HEADER

    def align(self, size: int) -> None:
        self.at += -(self.at - _HEADER) % size

    def unpack(self, layout: struct.Struct, what: str) -> tuple:
        try:
            values = layout.unpack_from(self.data, self.at)
        except struct.error:
            raise ProfileFormatError(f"serialized cloud ends at byte {len(self.data)}, inside {what}") from None
        self.at += layout.size
        return values

    def u32(self, what: str) -> int:
        self.align(4)
        return self.unpack(_U32, what)[0]

    def byte(self, what: str) -> int:
        if self.at >= len(self.data):
            raise ProfileFormatError(f"serialized cloud ends at byte {len(self.data)}, inside {what}")
        self.at += 1
        return self.data[self.at - 1]

    def block(self, size: int, what: str) -> memoryview:
        if size > len(self.data) - self.at:
            raise ProfileFormatError(f"{what} says {size} bytes but only {len(self.data) - self.at} follow")
        self.at += size
        return self.view[self.at - size:self.at]

    def string(self, what: str) -> str:
        size = self.u32(what)
        raw = self.block(size, what)
        if size == 0 or raw[-1] != 0:
            raise ProfileFormatError(f"{what} is not a NUL-terminated CDR string")
        try:
            return bytes(raw[:-1]).decode("utf-8")
        except UnicodeDecodeError:
            raise ProfileFormatError(f"{what} is not UTF-8") from None


class _Writer:
    def __init__(self) -> None:
        self.out = bytearray(CDR_LE + b"\x00\x00")

    def align(self, size: int) -> None:
        self.out += bytes(-(len(self.out) - _HEADER) % size)

    def pack(self, layout: struct.Struct, *values) -> None:
        self.out += layout.pack(*values)

    def u32(self, value: int) -> None:
        self.align(4)
        self.pack(_U32, value)

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\x00"
        self.u32(len(raw))
        self.out += raw


def encode_profile_cdr(points: np.ndarray, stamp_sec: int, stamp_nanosec: int, frame_id: str,
                       intensity: np.ndarray | None = None) -> bytes:
    """An (N, 2) [x, z] profile as a serialized PointCloud2 (DESIGN.md's layout, encode_profile's fields)."""
    fields, step, table = encode_profile(points, intensity)
    prefix = _cloud_prefix(frame_id, tuple(fields), step, len(points))
    return b"".join((prefix[:_HEADER], _STAMP.pack(stamp_sec, stamp_nanosec), prefix[_HEADER + _STAMP.size:],
                     table, b"\x00"))  # is_dense: invalid points are NaN


@lru_cache(maxsize=16)
def _cloud_prefix(frame_id: str, fields: tuple[Field, ...], step: int, width: int) -> bytes:
    """Everything before the point table, stamped zero: the same for every profile of a driver (building it
    field by field took longer than the table)."""
    writer = _Writer()
    writer.pack(_STAMP, 0, 0)
    writer.string(frame_id)
    writer.align(4)
    writer.pack(_U32X2, 1, width)
    writer.u32(len(fields))
    for field in fields:
        writer.string(field.name)
        writer.align(4)
        writer.pack(_FIELD_TAIL, field.offset, field.datatype)
        writer.u32(field.count)
    writer.out.append(0)  # is_bigendian
    writer.align(4)
    writer.pack(_U32X2, step, step * width)
    writer.u32(step * width)  # the table's length
    return bytes(writer.out)


def decode_profile_cdr(data: bytes | bytearray | memoryview) -> ProfileMessage:
    """A serialized PointCloud2 profile -> stamp, frame_id and [x, z] points. Raises ProfileFormatError."""
    data = bytes(data) if not isinstance(data, bytes) else data
    if data[:2] != CDR_LE:
        raise ProfileFormatError(f"not a little-endian CDR message (encapsulation {data[:2].hex() or 'missing'})")
    reader = _Reader(data)
    sec, nanosec = reader.unpack(_STAMP, "header.stamp")
    frame_id = reader.string("header.frame_id")
    reader.align(4)
    height, width = reader.unpack(_U32X2, "height/width")
    count = reader.u32("the field count")
    if count > _MAX_FIELDS:
        raise ProfileFormatError(f"{count} point fields; a profile has at most a few")
    fields = []
    for k in range(count):
        name = reader.string(f"field {k}'s name")
        reader.align(4)
        offset, datatype = reader.unpack(_FIELD_TAIL, f"field {k}")
        fields.append(Field(name, offset, datatype, reader.u32(f"field {k}'s count")))
    is_bigendian = reader.byte("is_bigendian")
    reader.align(4)
    point_step, row_step = reader.unpack(_U32X2, "point_step/row_step")
    table = reader.block(reader.u32("the data length"), "the data length")
    reader.byte("is_dense")
    if len(data) - reader.at > 3:  # at most alignment padding after the last field
        raise ProfileFormatError(f"{len(data) - reader.at} bytes after the end of the cloud")
    points = decode_profile(width=width, height=height, fields=fields, is_bigendian=bool(is_bigendian),
                            point_step=point_step, row_step=row_step, data=table)
    return ProfileMessage(sec, nanosec, frame_id, points)
