"""The estimator's two outputs, geometry_msgs/PoseStamped and PoseWithCovarianceStamped, serialized
directly (little-endian CDR) for publishing.

Publishing the two as rclpy messages cost ~70 us a profile on 2026-12-02, ~45 us of it rclpy converting
the Python objects (the 36-value covariance above all); handed bytes, rclpy only writes them (~15 us).
The bytes are rclpy's but for the alignment padding, zero here where rclpy leaves whatever was in memory
(a test compares them field by field and byte by byte after zeroing the padding).
"""
from __future__ import annotations

import struct

import numpy as np

from .rotation import quaternion_xyzw

_ENCAPSULATION = b"\x00\x01\x00\x00"  # plain CDR, little-endian; alignment counts from after it
_STAMP = struct.Struct("<iI")
_POSE = struct.Struct("<7d")  # position x y z, orientation x y z w


def _frame_and_padding(frame_id: str) -> bytes:
    """header.frame_id as a CDR string, then the padding that aligns the doubles after it to 8."""
    raw = frame_id.encode("utf-8") + b"\x00"
    size = _STAMP.size + 4 + len(raw)
    return struct.pack("<I", len(raw)) + raw + bytes(-size % 8)


class SerializedPosePair:
    """What nodes.messages.PoseMessagePair is for the replay, as bytes for a publisher: fill(), then
    `pose` and `with_covariance`."""

    def __init__(self) -> None:
        self.pose = b""
        self.with_covariance = b""
        self._frame_id: str | None = None
        self._frame = b""

    def fill(self, rotation: np.ndarray, translation: np.ndarray, covariance: np.ndarray, stamp_sec: int,
             stamp_nanosec: int, frame_id: str) -> None:
        if frame_id != self._frame_id:
            self._frame_id, self._frame = frame_id, _frame_and_padding(frame_id)
        head = _ENCAPSULATION + _STAMP.pack(stamp_sec, stamp_nanosec) + self._frame
        pose = _POSE.pack(*np.asarray(translation, dtype=float).tolist(), *quaternion_xyzw(rotation).tolist())
        self.pose = head + pose
        self.with_covariance = head + pose + np.ascontiguousarray(covariance, dtype="<f8").reshape(36).tobytes()
