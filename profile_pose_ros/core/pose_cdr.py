"""The loop's small messages serialized and read directly (little-endian CDR), without rclpy's Python
message objects: the estimator's PoseStamped and PoseWithCovarianceStamped out, the compensator's pose in
and TwistStamped correction out, the bridge's correction in.

Publishing the estimator's two poses as rclpy messages cost ~70 us a profile on 2026-12-02, ~45 us of it
rclpy converting the Python objects (the 36-value covariance above all); handed bytes, rclpy only writes
them (~15 us). Taking a message builds a tree of Python objects the same way. The bytes written are
rclpy's but for the alignment padding, zero here where rclpy leaves whatever was in memory (tests compare
them). What is read is outside input: anything that is not the message raises CdrFormatError.
"""
from __future__ import annotations

import struct

import numpy as np

from .rotation import quaternion_xyzw

_ENCAPSULATION = b"\x00\x01\x00\x00"  # plain CDR, little-endian; alignment counts from after it
_HEADER = len(_ENCAPSULATION)
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_POSE = struct.Struct("<7d")  # position x y z, orientation x y z w
_TWIST = struct.Struct("<6d")  # linear x y z, angular x y z
_COVARIANCE = 36 * 8
_MAX_FRAME_ID = 1024  # a longer header.frame_id is a corrupt length, not a frame name


class CdrFormatError(ValueError):
    """A serialized message that is not the message its topic's type says."""


def read_header(data: bytes) -> tuple[int, str, int]:
    """(stamp ns, frame_id, where the 8-aligned body starts) of a serialized message that starts with a
    std_msgs/Header."""
    if data[:2] != _ENCAPSULATION[:2]:
        raise CdrFormatError(f"not a little-endian CDR message (encapsulation {data[:2].hex() or 'missing'})")
    if len(data) < _HEADER + _STAMP.size + 4:
        raise CdrFormatError(f"{len(data)} bytes: too short for a header")
    sec, nanosec = _STAMP.unpack_from(data, _HEADER)
    size = _U32.unpack_from(data, _HEADER + _STAMP.size)[0]
    start = _HEADER + _STAMP.size + 4
    if not 0 < size <= _MAX_FRAME_ID or start + size > len(data) or data[start + size - 1] != 0:
        raise CdrFormatError("header.frame_id is not a NUL-terminated CDR string inside the message")
    try:
        frame_id = data[start:start + size - 1].decode("utf-8")
    except UnicodeDecodeError:
        raise CdrFormatError("header.frame_id is not UTF-8") from None
    body = start + size
    return sec * 1_000_000_000 + nanosec, frame_id, body + (-(body - _HEADER) % 8)


def _body(data: bytes, at: int, size: int, what: str) -> None:
    """The fixed-size body must fill the rest (up to 3 bytes of end padding)."""
    if not 0 <= len(data) - at - size <= 3:
        raise CdrFormatError(f"{len(data)} bytes is not a {what} (its body needs {size} from byte {at})")


def decode_pose_with_covariance_cdr(data: bytes) -> tuple[int, str, tuple[float, ...], np.ndarray]:
    """A serialized PoseWithCovarianceStamped -> (stamp ns, frame_id, (px py pz qx qy qz qw), 6x6)."""
    stamp_ns, frame_id, at = read_header(data)
    _body(data, at, _POSE.size + _COVARIANCE, "PoseWithCovarianceStamped")
    pose = _POSE.unpack_from(data, at)
    covariance = np.frombuffer(data, dtype="<f8", count=36, offset=at + _POSE.size).reshape(6, 6)
    return stamp_ns, frame_id, pose, covariance


def encode_twist_cdr(values, stamp_ns: int, frame_id: str) -> bytes:
    """[vx vy vz wx wy wz] as a serialized TwistStamped (what nodes.messages.twist_stamped builds)."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return (_ENCAPSULATION + _STAMP.pack(sec, nanosec) + _frame_and_padding(frame_id)
            + _TWIST.pack(*(float(v) for v in values[:6])))


def decode_twist_cdr(data: bytes) -> tuple[int, str, np.ndarray]:
    """A serialized TwistStamped -> (stamp ns, frame_id, [vx vy vz wx wy wz])."""
    stamp_ns, frame_id, at = read_header(data)
    _body(data, at, _TWIST.size, "TwistStamped")
    return stamp_ns, frame_id, np.array(_TWIST.unpack_from(data, at))


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
