"""The loop's small messages travel serialized (core/wire/pose_cdr.py): the estimator's poses and the
compensator's corrections are the bytes rclpy would send, and what the compensator and the bridge read back
is the message, or CdrFormatError (fuzzed in test_fuzz.py)."""
import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from hypothesis import given, settings, strategies as st
from rclpy.serialization import deserialize_message, serialize_message

from profile_pose_ros.bags.reader import typestore
from profile_pose_ros.core.wire.pose_cdr import (CdrFormatError, SerializedPosePair, decode_pose_with_covariance_cdr,
                                                 decode_twist_cdr, encode_pose_cdr, encode_twist_cdr)
from profile_pose_ros.core.model.rotation import so3_exp
from profile_pose_ros.nodes.messages import fill_pose, pose_with_covariance, twist_stamped

TYPES = {"pose": "geometry_msgs/msg/PoseStamped", "with_covariance": "geometry_msgs/msg/PoseWithCovarianceStamped"}


# frame names as ROS carries them: UTF-8 (no lone surrogate, which no ROS string can hold) without a NUL
# (a CDR string ends at its NUL)
FRAME_IDS = st.text(st.characters(exclude_characters="\x00", exclude_categories=("Cs",)), max_size=12)


def padding_zeroed(data: bytes, msgtype: str) -> bytes:
    """rclpy leaves alignment padding as whatever was in memory; rosbags writes it as zeros."""
    store = typestore()
    return bytes(store.serialize_cdr(store.deserialize_cdr(data, msgtype), msgtype))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=9, max_size=9),
       FRAME_IDS,
       st.integers(0, 2 ** 31 - 1), st.integers(0, 999_999_999))
def test_serialized_poses_are_what_rclpy_would_send(values, frame_id, sec, nanosec) -> None:
    rotation, translation = so3_exp(np.array(values[:3])), np.array(values[3:6])
    a = np.diag(values[6:9] + [1.0, 2.0, 3.0]) + 0.1
    covariance = a @ a.T
    serialized = SerializedPosePair()
    serialized.fill(rotation, translation, covariance, sec, nanosec, frame_id)
    pose = PoseStamped()  # the same poses as rclpy's messages, the reference
    pose.header.stamp.sec, pose.header.stamp.nanosec, pose.header.frame_id = sec, nanosec, frame_id
    fill_pose(pose.pose, rotation, translation)
    messages = {"pose": pose, "with_covariance": pose_with_covariance(pose, covariance)}
    for name, msgtype in TYPES.items():
        ours, theirs = getattr(serialized, name), serialize_message(messages[name])
        assert len(ours) == len(theirs)
        assert ours == padding_zeroed(theirs, msgtype) == padding_zeroed(ours, msgtype)
    # the bridge's robot_state: a PoseStamped on its own
    assert encode_pose_cdr(rotation, translation, sec * 1_000_000_000 + nanosec, frame_id) == serialized.pose


def test_a_serialized_pose_reads_back_as_the_message() -> None:
    serialized = SerializedPosePair()
    covariance = np.arange(36.0).reshape(6, 6)
    serialized.fill(so3_exp(np.array([0.0, 0.0, np.pi / 2])), np.array([0.1, -0.2, 0.3]), covariance, 5, 6, "gauge")
    pose = deserialize_message(serialized.with_covariance, PoseWithCovarianceStamped)
    assert (pose.header.stamp.sec, pose.header.stamp.nanosec, pose.header.frame_id) == (5, 6, "gauge")
    assert [pose.pose.pose.position.x, pose.pose.pose.position.y, pose.pose.pose.position.z] == [0.1, -0.2, 0.3]
    assert pose.pose.pose.orientation.z == pytest.approx(np.sqrt(0.5)) and pose.pose.pose.orientation.w > 0
    assert list(pose.pose.covariance) == list(range(36))
    assert deserialize_message(serialized.pose, PoseStamped).pose == pose.pose.pose


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=6, max_size=6),
       FRAME_IDS, st.integers(0, 2 ** 62))
def test_corrections_travel_as_rclpy_would_send_them(values, frame_id, stamp_ns) -> None:
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    if sec >= 2 ** 31:
        return
    theirs = serialize_message(twist_stamped(values, Time(sec=sec, nanosec=nanosec), frame_id))
    ours = encode_twist_cdr(values, stamp_ns, frame_id)
    assert ours == padding_zeroed(theirs, "geometry_msgs/msg/TwistStamped")
    stamp, frame, decoded = decode_twist_cdr(theirs)
    assert (stamp, frame, decoded.tolist()) == (stamp_ns, frame_id, values)


def test_a_pose_the_estimator_sent_reads_back_in_the_compensator() -> None:
    serialized = SerializedPosePair()
    serialized.fill(np.eye(3), np.array([0.1, 0.2, 0.3]), np.arange(36.0).reshape(6, 6), 5, 6, "gauge")
    stamp, frame, pose, covariance = decode_pose_with_covariance_cdr(serialized.with_covariance)
    assert (stamp, frame, pose) == (5_000_000_006, "gauge", (0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0))
    assert covariance.tolist() == np.arange(36.0).reshape(6, 6).tolist()
    for bad in (serialized.pose, serialized.with_covariance[:-8], serialized.with_covariance + bytes(8), b"",
                b"\x01\x00" + serialized.with_covariance[2:]):
        with pytest.raises(CdrFormatError):
            decode_pose_with_covariance_cdr(bad)


def test_consecutive_poses_near_a_half_turn_keep_one_hemisphere() -> None:
    """A profiler looking down on the gauge sits near a half turn, where w crosses zero: signed by w >= 0 the
    quaternion flipped between consecutive poses; signed against the orientation hint it never does, and the
    bytes still decode to the same rotation."""
    from profile_pose_ros.core.wire.pose_cdr import SerializedPosePair, decode_pose_with_covariance_cdr
    from profile_pose_ros.core.model.rotation import quaternion_xyzw, rotation_from_quaternion_xyzw, so3_exp

    rng = np.random.default_rng(3)
    rotations = [so3_exp(np.array([np.pi, 0.0, 0.0]) + rng.normal(0.0, 2e-3, 3)) for _ in range(200)]
    plain = np.array([quaternion_xyzw(r) for r in rotations])
    assert np.any(np.sum(plain[1:] * plain[:-1], axis=1) < 0)  # the old sign convention flips
    pair, quaternions = SerializedPosePair(), []
    for rotation in rotations:
        pair.fill(rotation, np.zeros(3), np.eye(6), 1, 2, "gauge")
        q = np.array(decode_pose_with_covariance_cdr(pair.with_covariance)[2][3:])
        np.testing.assert_allclose(rotation_from_quaternion_xyzw(q), rotation, atol=1e-12)
        quaternions.append(q)
    quaternions = np.array(quaternions)
    assert np.all(np.sum(quaternions[1:] * quaternions[:-1], axis=1) >= 0)
