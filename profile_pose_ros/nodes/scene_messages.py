"""TF and marker messages for viewers (message types only, no node code): the estimated profiler pose
on /tf, the gauge's place on /tf_static, the gauge and the latest profile as a MarkerArray."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point, TransformStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import ColorRGBA
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from ..core.model.rotation import HALF_TURN_X, quaternion_near, so3_exp
from .messages import set_stamp

# tf2_ros's own QoS: /tf keeps 100 transforms for slow listeners; /tf_static is latched (transient local)
# so a listener started later still gets the fixed frames.
TF_QOS = QoSProfile(depth=100)
TF_STATIC_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                           reliability=ReliabilityPolicy.RELIABLE)
# Latched too: a viewer that connects between two updates still draws the gauge and the last profile.
MARKER_QOS = TF_STATIC_QOS

GAUGE_COLOR = ColorRGBA(r=0.6, g=0.6, b=0.65, a=0.7)
PROFILE_COLOR = ColorRGBA(r=1.0, g=0.1, b=0.1, a=1.0)
PROFILE_POINT_SIZE = 0.0005  # m


def transform_stamped(parent: str, child: str, stamp_ns: int, rotation: np.ndarray, translation,
                      hint=HALF_TURN_X) -> TransformStamped:
    """child's pose in parent (p_parent = R p_child + t) as a TransformStamped."""
    msg = TransformStamped()
    set_stamp(msg.header.stamp, stamp_ns)
    msg.header.frame_id, msg.child_frame_id = parent, child
    t = msg.transform.translation
    t.x, t.y, t.z = np.asarray(translation, dtype=float).tolist()
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = quaternion_near(np.asarray(rotation, dtype=float), hint).tolist()
    return msg


def static_transform(parent: str, child: str, stamp_ns: int, pose6) -> TFMessage:
    """/tf_static's message for a fixed pose given as x y z (m) and a rotation vector (rad)."""
    pose6 = np.asarray(pose6, dtype=float)
    rotation = so3_exp(pose6[3:])
    return TFMessage(transforms=[transform_stamped(parent, child, stamp_ns, rotation, pose6[:3], (0, 0, 0, 1))])


def _points(array: np.ndarray) -> list[Point]:
    return [Point(x=x, y=y, z=z) for x, y, z in np.asarray(array, dtype=float).tolist()]


class SceneMarkers:
    """The MarkerArray of the gauge (fixed, built once) and the latest profile, refilled per update."""

    def __init__(self, triangles: np.ndarray, frame_id: str) -> None:
        self.gauge = Marker(ns="gauge", id=0, type=Marker.TRIANGLE_LIST, action=Marker.ADD, color=GAUGE_COLOR)
        self.gauge.pose.orientation.w = 1.0
        self.gauge.scale.x = self.gauge.scale.y = self.gauge.scale.z = 1.0
        self.gauge.points = _points(triangles)
        self.profile = Marker(ns="profile", id=0, type=Marker.POINTS, action=Marker.ADD, color=PROFILE_COLOR)
        self.profile.pose.orientation.w = 1.0
        self.profile.scale.x = self.profile.scale.y = PROFILE_POINT_SIZE
        self.array = MarkerArray(markers=[self.gauge, self.profile])
        self.set_frame(frame_id)

    def set_frame(self, frame_id: str) -> None:
        self.gauge.header.frame_id = self.profile.header.frame_id = frame_id

    def update(self, profile_in_gauge: np.ndarray, stamp_ns: int) -> MarkerArray:
        for marker in self.array.markers:
            set_stamp(marker.header.stamp, stamp_ns)
        self.profile.points = _points(profile_in_gauge)
        return self.array
