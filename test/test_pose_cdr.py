"""The estimator publishes its poses serialized (core/pose_cdr.py): the same messages rclpy would send."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped

from profile_pose_ros.bags.reader import typestore
from profile_pose_ros.core.pose_cdr import SerializedPosePair
from profile_pose_ros.core.rotation import so3_exp
from profile_pose_ros.nodes.messages import PoseMessagePair

TYPES = {"pose": "geometry_msgs/msg/PoseStamped", "with_covariance": "geometry_msgs/msg/PoseWithCovarianceStamped"}


def padding_zeroed(data: bytes, msgtype: str) -> bytes:
    """rclpy leaves alignment padding as whatever was in memory; rosbags writes it as zeros."""
    store = typestore()
    return bytes(store.serialize_cdr(store.deserialize_cdr(data, msgtype), msgtype))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=9, max_size=9),
       st.text(st.characters(blacklist_characters="\x00"), max_size=12),  # a CDR string ends at its NUL
       st.integers(0, 2 ** 31 - 1), st.integers(0, 999_999_999))
def test_serialized_poses_are_what_rclpy_would_send(values, frame_id, sec, nanosec) -> None:
    rotation, translation = so3_exp(np.array(values[:3])), np.array(values[3:6])
    a = np.diag(values[6:9] + [1.0, 2.0, 3.0]) + 0.1
    covariance = a @ a.T
    messages, serialized = PoseMessagePair(), SerializedPosePair()
    messages.fill(rotation, translation, covariance, sec, nanosec, frame_id)
    serialized.fill(rotation, translation, covariance, sec, nanosec, frame_id)
    for name, msgtype in TYPES.items():
        ours, theirs = getattr(serialized, name), serialize_message(getattr(messages, name))
        assert len(ours) == len(theirs)
        assert ours == padding_zeroed(theirs, msgtype) == padding_zeroed(ours, msgtype)


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
