"""Conversions between ROS messages and the core's arrays (message types only, no rclpy node code)."""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TwistStamped
from sensor_msgs.msg import PointCloud2, PointField

from ..core.wire.cdr import HEADER, STAMP
from ..core.wire.profile_cloud import Field, decode_profile, encode_profile
from ..core.model.rotation import HALF_TURN_X, quaternion_near, rotation_angle, rotation_from_quaternion_xyzw



def stamp_ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def set_stamp(stamp: Time, nanoseconds: int) -> None:
    stamp.sec, stamp.nanosec = divmod(int(nanoseconds), 1_000_000_000)


def cdr_stamp_ns(cdr: bytes) -> int:
    """header.stamp of a serialized message that starts with a std_msgs/Header (little-endian CDR), without
    decoding the rest (a 3200-point profile, say)."""
    sec, nanosec = STAMP.unpack_from(cdr, HEADER)
    return sec * 1_000_000_000 + nanosec


def pose_difference(a, b) -> tuple[float, float]:
    """(position m, rotation rad) between two geometry_msgs Pose."""
    (ra, ta), (rb, tb) = rotation_translation(a), rotation_translation(b)
    return float(np.linalg.norm(ta - tb)), rotation_angle(ra, rb)


def cloud_from_points(points: np.ndarray, stamp: Time, frame_id: str,
                      intensity: np.ndarray | None = None) -> PointCloud2:
    fields, step, data = encode_profile(points, intensity)
    msg = PointCloud2()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height = 1
    msg.width = len(points)
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in fields]
    msg.is_bigendian = False
    msg.point_step = step
    msg.row_step = step * len(points)
    msg.data = data
    msg.is_dense = False
    return msg


def points_from_cloud(msg: PointCloud2) -> np.ndarray:
    """Raises ProfileFormatError for anything that is not a DESIGN.md profile."""
    fields = [Field(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    return decode_profile(width=msg.width, height=msg.height, fields=fields, is_bigendian=msg.is_bigendian,
                          point_step=msg.point_step, row_step=msg.row_step, data=msg.data)


def pose_stamped(rotation: np.ndarray, translation: np.ndarray, stamp: Time, frame_id: str) -> PoseStamped:
    msg = PoseStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    fill_pose(msg.pose, rotation, translation)
    return msg


def twist_stamped(values, stamp: Time, frame_id: str) -> TwistStamped:
    """[vx vy vz wx wy wz] (or an increment: m and rad) as a TwistStamped."""
    msg = TwistStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z = (float(x) for x in values[:3])
    msg.twist.angular.x, msg.twist.angular.y, msg.twist.angular.z = (float(x) for x in values[3:6])
    return msg


def twist_vector(twist) -> np.ndarray:
    """A Twist as [vx vy vz wx wy wz] (the inverse of twist_stamped)."""
    return np.array([twist.linear.x, twist.linear.y, twist.linear.z,
                     twist.angular.x, twist.angular.y, twist.angular.z])


def pose_with_covariance(pose: PoseStamped, covariance: np.ndarray) -> PoseWithCovarianceStamped:
    """The same pose (header and Pose shared, not recomputed) with its 6x6 covariance in ROS order."""
    msg = PoseWithCovarianceStamped()
    msg.header = pose.header
    msg.pose.pose = pose.pose
    msg.pose.covariance = _row_major(covariance)
    return msg


def _row_major(covariance: np.ndarray) -> np.ndarray:
    """A 6x6 covariance as the 36 float64 values geometry_msgs stores."""
    return np.ascontiguousarray(covariance, dtype=np.float64).reshape(36)


def fill_pose(pose, rotation: np.ndarray, translation: np.ndarray, hint=HALF_TURN_X) -> None:
    pose.position.x, pose.position.y, pose.position.z = np.asarray(translation, dtype=float).tolist()
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = \
        quaternion_near(rotation, hint).tolist()


def rotation_translation(pose) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a geometry_msgs/Pose."""
    o, p = pose.orientation, pose.position
    return rotation_from_quaternion_xyzw(np.array([o.x, o.y, o.z, o.w])), np.array([p.x, p.y, p.z])
