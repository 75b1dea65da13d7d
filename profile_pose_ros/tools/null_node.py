"""A node that estimates nothing: the latency floor of a profile-in, pose-out node on this machine.

It takes each profile the way pose_estimator does (serialized, sensor-data QoS, through a FastInput,
the same run loop) and publishes a pose carrying the profile's stamp, serialized as pose_estimator's are.
What profile_pose_node_benchmark measures for it is what rclpy, DDS and the machine's scheduling cost a
node before it does any work, so the estimator's own share is the difference. Benchmark-only: no
launch script or cell file uses it.
"""
from __future__ import annotations

import struct
import sys

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

from ..core.pose_cdr import encode_pose_cdr
from ..nodes.fast_input import FastInput, ServedDirectly, spin
from ..nodes.run import run_node

STAMP = struct.Struct("<iI")  # header.stamp after the 4-byte CDR encapsulation
QUEUE_DEPTH = 20  # pose_estimator's default queue_depth (a test holds them equal; importing that node here
# would load the estimator and its kernels into the process whose footprint is the floor)


class NullNode(Node):
    def __init__(self) -> None:
        super().__init__("null_node")
        self.pose_pub = self.create_publisher(PoseStamped, "pose", 10)
        self.rotation, self.translation = np.eye(3), np.zeros(3)
        qos = QoSProfile(depth=QUEUE_DEPTH, reliability=qos_profile_sensor_data.reliability,
                         durability=qos_profile_sensor_data.durability, history=qos_profile_sensor_data.history)
        subscription = self.create_subscription(PointCloud2, "profile", self._on_profile, qos,
                                                callback_group=ServedDirectly(), raw=True)
        self.fast_input = FastInput(subscription, self.context, self._on_profile)

    def _on_profile(self, serialized: bytes) -> None:
        sec, nanosec = STAMP.unpack_from(serialized, 4)
        self.pose_pub.publish(encode_pose_cdr(self.rotation, self.translation, sec * 1_000_000_000 + nanosec,
                                              "gauge"))


def main(args=None) -> int:
    return run_node(NullNode, "null_node", args,
                    spin=lambda executor, node, stop: spin(executor, node.fast_input, stop))


if __name__ == "__main__":
    sys.exit(main())
