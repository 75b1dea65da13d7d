"""A node that estimates nothing: the latency floor of a profile-in, pose-out node on this machine.

It takes each profile the way pose_estimator does (serialized, sensor-data QoS, through a DirectInput,
the same run loop) and publishes a pose carrying the profile's stamp, serialized as pose_estimator's are.
What profile_pose node-benchmark measures for it is what rclpy, DDS and the machine's scheduling cost a
node before it does any work, so the estimator's own share is the difference. Benchmark-only: no
launch script or cell file uses it.
"""
from __future__ import annotations

import sys

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from ..core.wire.pose_cdr import encode_pose_cdr
from ..nodes.direct_input import DirectInput, ServedDirectly, spin
from ..nodes.local_topics import profile_input_qos
from ..nodes.messages import cdr_stamp_ns
from ..nodes.run import run_node

QUEUE_DEPTH = 20  # pose_estimator's default queue_depth (a test holds them equal; importing that node here
# would load the estimator and its kernels into the process whose footprint is the floor)


class NullNode(Node):
    def __init__(self) -> None:
        super().__init__("null_node")
        self.pose_pub = self.create_publisher(PoseStamped, "pose", 10)
        self.rotation, self.translation = np.eye(3), np.zeros(3)
        subscription = self.create_subscription(PointCloud2, "profile", self._on_profile,
                                                profile_input_qos(QUEUE_DEPTH), callback_group=ServedDirectly(),
                                                raw=True)
        self.direct_input = DirectInput(subscription, self.context, self._on_profile)

    def _on_profile(self, serialized: bytes) -> None:
        self.pose_pub.publish(encode_pose_cdr(self.rotation, self.translation, cdr_stamp_ns(serialized), "gauge"))


def main(args=None) -> int:
    return run_node(NullNode, "null_node", args,
                    spin=lambda executor, node, stop: spin(executor, node.direct_input, stop))


if __name__ == "__main__":
    sys.exit(main())
