"""The loop's small messages serialized and read directly (little-endian CDR), without rclpy's Python
message objects: the estimator's PoseStamped and PoseWithCovarianceStamped out, the compensator's pose in
and TwistStamped correction out, the bridge's correction in and its robot_state and increments out.

Publishing the estimator's two poses as rclpy messages spends most of its time in rclpy converting the
Python objects (the 36-value covariance above all); handed bytes, rclpy only writes them
(docs/design_notes.md). Taking a message builds a tree of Python objects the same way. The bytes written are
rclpy's but for the alignment padding, zero here where rclpy leaves whatever was in memory (tests compare
them). What is read is outside input: anything that is not the message raises CdrFormatError.
"""
from __future__ import annotations

import struct
from functools import lru_cache

import numpy as np

from .cdr import CdrReader, CdrWriter, stamped
from ..model.rotation import HALF_TURN_X, quaternion_near

_POSE = struct.Struct("<7d")  # position x y z, orientation x y z w
_TWIST = struct.Struct("<6d")  # linear x y z, angular x y z
_COVARIANCE = 36 * 8
_MAX_FRAME_ID = 1024  # a longer header.frame_id is a corrupt length, not a frame name


class CdrFormatError(ValueError):
    """A serialized message that is not the message its topic's type says."""


def _read_header(data: bytes) -> tuple[int, str, int]:
    """(stamp ns, frame_id, where the 8-aligned body starts) of a serialized message that starts with a
    std_msgs/Header."""
    reader = CdrReader(data, CdrFormatError, "serialized message")
    stamp_ns, frame_id = reader.header(_MAX_FRAME_ID)
    reader.align(8)
    return stamp_ns, frame_id, reader.at


def decode_stamp(data: bytes) -> int:
    """The header stamp (ns) of a serialized message that starts with a std_msgs/Header."""
    return _read_header(data)[0]


@lru_cache(maxsize=16)
def _header(frame_id: str) -> bytes:
    """The header stamped zero and the padding that aligns the doubles after it to 8."""
    writer = CdrWriter()
    writer.header(frame_id)
    writer.align(8)
    return bytes(writer.out)


def _body(data: bytes, at: int, size: int, what: str) -> None:
    """The fixed-size body must fill the rest (up to 3 bytes of end padding)."""
    if not 0 <= len(data) - at - size <= 3:
        raise CdrFormatError(f"{len(data)} bytes is not a {what} (its body needs {size} from byte {at})")


def decode_pose_with_covariance_cdr(data: bytes) -> tuple[int, str, tuple[float, ...], np.ndarray]:
    """A serialized PoseWithCovarianceStamped -> (stamp ns, frame_id, (px py pz qx qy qz qw), 6x6)."""
    stamp_ns, frame_id, at = _read_header(data)
    _body(data, at, _POSE.size + _COVARIANCE, "PoseWithCovarianceStamped")
    pose = _POSE.unpack_from(data, at)
    covariance = np.frombuffer(data, dtype="<f8", count=36, offset=at + _POSE.size).reshape(6, 6)
    return stamp_ns, frame_id, pose, covariance


def encode_pose_with_covariance_cdr(pose, covariance, stamp_ns: int, frame_id: str) -> bytes:
    """(px py pz qx qy qz qw), 6x6 -> a serialized PoseWithCovarianceStamped, any values (the fuzzer's
    absurd ones too): the inverse of decode_pose_with_covariance_cdr."""
    return (stamped(_header(frame_id), *divmod(stamp_ns, 1_000_000_000)) + _POSE.pack(*(float(v) for v in pose))
            + np.ascontiguousarray(covariance, dtype="<f8").reshape(36).tobytes())


def encode_twist_cdr(values, stamp_ns: int, frame_id: str) -> bytes:
    """[vx vy vz wx wy wz] as a serialized TwistStamped (what nodes.messages.twist_stamped builds)."""
    return stamped(_header(frame_id), *divmod(stamp_ns, 1_000_000_000)) + _TWIST.pack(*(float(v) for v in values[:6]))


def _pose_body(rotation: np.ndarray, translation: np.ndarray, hint=HALF_TURN_X) -> bytes:
    return _POSE.pack(*np.asarray(translation, dtype=float).tolist(), *quaternion_near(rotation, hint).tolist())


def encode_pose_cdr(rotation: np.ndarray, translation: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """A serialized PoseStamped (the bytes SerializedPosePair.pose holds): the bridge's robot_state."""
    return stamped(_header(frame_id), *divmod(stamp_ns, 1_000_000_000)) + _pose_body(rotation, translation)


def decode_twist_cdr(data: bytes) -> tuple[int, str, np.ndarray]:
    """A serialized TwistStamped -> (stamp ns, frame_id, [vx vy vz wx wy wz])."""
    stamp_ns, frame_id, at = _read_header(data)
    _body(data, at, _TWIST.size, "TwistStamped")
    return stamp_ns, frame_id, np.array(_TWIST.unpack_from(data, at))


class SerializedPosePair:
    """The estimator's two poses as the bytes a publisher sends, refilled for every estimate: fill(), then
    `pose` and `with_covariance` (the node publishes them, the replay compares them with a bag's)."""

    def __init__(self) -> None:
        self.pose = b""
        self.with_covariance = b""

    def fill(self, rotation: np.ndarray, translation: np.ndarray, covariance: np.ndarray, stamp_sec: int,
             stamp_nanosec: int, frame_id: str, hint=HALF_TURN_X) -> None:
        """hint: the quaternion's hemisphere (rotation.quaternion_near)."""
        head = stamped(_header(frame_id), stamp_sec, stamp_nanosec)
        pose = _pose_body(rotation, translation, hint)
        self.pose = head + pose
        self.with_covariance = head + pose + np.ascontiguousarray(covariance, dtype="<f8").reshape(36).tobytes()
