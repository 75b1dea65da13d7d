"""The composed nodes' in-process hand-over (nodes/local_topics.py), with real rclpy publishers."""
from __future__ import annotations

from std_msgs.msg import String

from profile_pose_ros.nodes.local_topics import LocalTopics, LoopOutput


def test_hand_over_reaches_takers_of_the_resolved_name_and_survives_a_failing_one(ros) -> None:
    import rclpy

    node = ros.add(rclpy.create_node("publisher", namespace="cell2", context=ros.context))
    local = LocalTopics()
    received: list[bytes] = []

    def failing(_: bytes) -> None:
        raise RuntimeError("a taker's bug")

    local.take("/cell2/loop", failing)
    local.take("/cell2/loop", received.append)
    local.take("/loop", lambda data: received.append(b"wrong namespace: " + data))
    out = LoopOutput(node.create_publisher(String, "loop", 10), local, node.get_logger())
    assert len(local.takers(out.publisher.topic_name)) == 2
    out.hand_over(b"\x00\x01")
    assert received == [b"\x00\x01"]  # the failing taker before it did not stop it; /loop got nothing


def test_composed_publish_goes_over_dds_only_to_a_subscriber_there(ros) -> None:
    from rclpy.serialization import serialize_message

    publisher_node, listener = ros.node("composed"), ros.node("listener")
    out = LoopOutput(publisher_node.create_publisher(String, "loop", 10), LocalTopics())
    heard: list[str] = []
    message = String(data="profile")
    out.publish(serialize_message(message))  # nobody over DDS: not sent (nothing to assert but no error)
    listener.create_subscription(String, "loop", lambda m: heard.append(m.data), 10)
    assert ros.spin_until(lambda: out.publisher.get_subscription_count() == 1, 10.0)
    assert ros.spin_until(lambda: bool(heard), 10.0, action=lambda: out.publish(serialize_message(message)))
    assert heard[0] == "profile"
