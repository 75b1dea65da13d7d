"""What nodes/direct_input.py takes from rclpy's private API, checked by name and in use: an rclpy upgrade
that moves or changes any of it fails here, saying what, before it fails a node in a cell."""
from __future__ import annotations

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import String

from conftest import unique_domain_id
from profile_pose_ros.nodes.direct_input import DirectInput, ServedDirectly, take_all


def test_the_private_names_direct_input_uses_exist() -> None:
    from rclpy.impl.implementation_singleton import rclpy_implementation as c_extension

    missing = [name for name in ("WaitSet", "RCLError") if not hasattr(c_extension, name)]
    assert not missing, f"rclpy's C extension no longer has {missing}: nodes/direct_input.py needs a new way in"
    for method in ("clear_entities", "add_subscription", "add_guard_condition", "wait", "is_ready"):
        assert hasattr(c_extension.WaitSet, method), f"rclpy's WaitSet lost {method}() (nodes/direct_input.py)"
    import rclpy._rclpy_pybind11 as pybind  # direct_input.py imports RCLError from here

    assert hasattr(pybind, "RCLError"), "rclpy._rclpy_pybind11 no longer has RCLError (nodes/direct_input.py)"


def test_a_served_directly_subscription_and_guard_work_end_to_end() -> None:
    """A message taken by DirectInput with its info, the executor never taking it, a guard condition run,
    and take_all draining a queue: every private call on the path, exercised."""
    context = Context()
    rclpy.init(context=context, domain_id=unique_domain_id())
    node = rclpy.create_node("private_api_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        got, guarded, by_executor = [], [], []
        group = ServedDirectly()
        subscription = node.create_subscription(String, "probe", lambda m: by_executor.append(m), 10,
                                                callback_group=group)
        guard = node.create_guard_condition(lambda: guarded.append(True), callback_group=group)
        direct = DirectInput(None, context, guard=guard)
        direct.add(subscription, lambda message, info: got.append((message.data, info)), with_info=True)
        publisher = node.create_publisher(String, "probe", 10)
        for k in range(3):
            publisher.publish(String(data=f"m{k}"))
        guard.trigger()
        deadline_pumps = 200
        while (len(got) < 3 or not guarded) and deadline_pumps:
            direct.pump(0.05)
            executor.spin_once(timeout_sec=0.0)
            deadline_pumps -= 1
        assert [data for data, _ in got] == ["m0", "m1", "m2"]
        assert {"source_timestamp", "received_timestamp"} <= set(got[0][1])
        assert guarded and not by_executor  # the executor never served the direct group
        publisher.publish(String(data="queued"))
        queued = []
        for _ in range(200):
            queued += [message.data for message, _ in take_all(subscription)]
            if queued:
                break
            executor.spin_once(timeout_sec=0.01)
        assert queued == ["queued"]
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
