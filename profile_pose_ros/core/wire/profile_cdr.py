"""A profile as it travels on the wire, a serialized sensor_msgs/PointCloud2 (little-endian CDR), decoded
and encoded without building the ROS message.

rclpy's conversion of a 3200-point cloud into Python objects is a fifth of the estimator node's time per
profile at 1 kHz (docs/design_notes.md); this reads the few metadata fields with struct (and only when they
differ from the previous profile's) and hands the point table, in place, to decode_profile. A bag's
recorded bytes take the very same path in replay. Anything malformed raises ProfileFormatError, like
every other profile check. The driver publishes the bytes encode_profile_cdr writes: rclpy's
serialization but for the alignment padding, which rclpy leaves as whatever was in memory and this
writes as zeros (a test compares them), without building the message and converting it back (a third
of the driver's time per profile).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .cdr import ENCAPSULATION, HEADER, STAMP, CdrReader, CdrWriter, stamped
from .profile_cloud import XYZ_FIELDS, Field, ProfileFormatError, decode_profile, encode_profile

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


def encode_profile_cdr(points: np.ndarray, stamp_sec: int, stamp_nanosec: int, frame_id: str,
                       intensity: np.ndarray | None = None) -> bytes:
    """An (N, 2) [x, z] profile as a serialized PointCloud2 (DESIGN.md's layout, encode_profile's fields)."""
    fields, step, table = encode_profile(points, intensity)
    return _cloud_cdr(tuple(fields), step, len(points), table, stamp_sec, stamp_nanosec, frame_id)


def encode_xyz_table_cdr(table: bytes, stamp_sec: int, stamp_nanosec: int, frame_id: str) -> bytes:
    """A point table already in encode_profile's x, y, z layout (ProfileFrame.xyz_table) as a serialized
    PointCloud2: encode_profile_cdr's bytes for the same profile."""
    return _cloud_cdr(XYZ_FIELDS, 12, len(table) // 12, table, stamp_sec, stamp_nanosec, frame_id)


def _cloud_cdr(fields: tuple[Field, ...], step: int, width: int, table: bytes, stamp_sec: int, stamp_nanosec: int,
               frame_id: str) -> bytes:
    prefix = _cloud_prefix(frame_id, fields, step, width)
    return b"".join((stamped(prefix, stamp_sec, stamp_nanosec), table, b"\x00"))  # is_dense: invalid points: NaN


@lru_cache(maxsize=16)
def _cloud_prefix(frame_id: str, fields: tuple[Field, ...], step: int, width: int) -> bytes:
    """Everything before the point table, stamped zero: the same for every profile of a driver (building it
    field by field took longer than the table)."""
    writer = CdrWriter()
    writer.header(frame_id)
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


@dataclass(frozen=True)
class _Layout:
    """Everything of a serialized cloud but its stamp, its point table and what follows the table: the
    same in every profile of one publisher, but for the alignment padding, which rclpy leaves as
    whatever was in memory. So a layout is recognised by its bytes between the paddings."""
    pieces: tuple[tuple[int, bytes], ...]  # (offset, the bytes there), padding and stamp left out
    table_start: int
    frame_id: str
    height: int
    width: int
    fields: tuple[Field, ...]
    is_bigendian: bool
    point_step: int
    row_step: int
    table_size: int

    def matches(self, data: bytes) -> bool:
        return (data[:2] == ENCAPSULATION[:2] and 1 <= len(data) - self.table_start - self.table_size <= 4
                and all(data[at:at + len(piece)] == piece for at, piece in self.pieces))


class _PaddingReader(CdrReader):
    """A CdrReader that notes where it skipped alignment padding."""

    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.padding: list[tuple[int, int]] = []

    def align(self, size: int) -> None:
        start = self.at
        super().align(size)
        if self.at > start:
            self.padding.append((start, self.at))


_LAYOUT_START = HEADER + STAMP.size
_last_layout: _Layout | None = None  # the previous profile's, to recognise the next one's by its bytes


def decode_profile_cdr(data: bytes | bytearray | memoryview) -> ProfileMessage:
    """A serialized PointCloud2 profile -> stamp, frame_id and [x, z] points. Raises ProfileFormatError.

    The layout is read field by field only when it differs from the previous profile's: reading it is a
    noticeable share of the node's time per profile (docs/design_notes.md), and a publisher sends the same
    layout every time. The same bytes read the same, so nothing else changes."""
    global _last_layout
    data = bytes(data) if not isinstance(data, bytes) else data
    layout = _last_layout
    if layout is None or not layout.matches(data):
        layout = _last_layout = _read_layout(data)
    sec, nanosec = STAMP.unpack_from(data, HEADER)
    table = memoryview(data)[layout.table_start:layout.table_start + layout.table_size]
    points = decode_profile(width=layout.width, height=layout.height, fields=layout.fields,
                            is_bigendian=layout.is_bigendian, point_step=layout.point_step,
                            row_step=layout.row_step, data=table)
    return ProfileMessage(sec, nanosec, layout.frame_id, points)


def _read_layout(data: bytes) -> _Layout:
    reader = _PaddingReader(data, ProfileFormatError, "serialized cloud")
    reader.unpack(STAMP, "header.stamp")
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
    table_size = reader.u32("the data length")
    table_start = reader.at
    reader.block(table_size, "the data length")
    reader.byte("is_dense")
    if len(data) - reader.at > 3:  # at most alignment padding after the last field
        raise ProfileFormatError(f"{len(data) - reader.at} bytes after the end of the cloud")
    bounds = [_LAYOUT_START, *(edge for span in reader.padding if span[1] <= table_start for edge in span),
              table_start]
    pieces = tuple((start, data[start:end]) for start, end in zip(bounds[::2], bounds[1::2]) if end > start)
    return _Layout(pieces, table_start, frame_id, height, width, tuple(fields), bool(is_bigendian), point_step,
                   row_step, table_size)
