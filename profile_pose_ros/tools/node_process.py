"""A package node in its own process on a private DDS domain, and a client node in this process."""
from __future__ import annotations

import time
from pathlib import Path

from . import processes


class NodeProcess:
    """Starts `executable` (falling back to `python -m module`; None: always the module) and a client node
    to talk to it."""

    def __init__(self, executable: str | None, module: str, ros_args: list[str], client_name: str, domain_id: int,
                 log_path: Path) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.domain_id = domain_id
        self.log_path = log_path
        command = processes.executable(executable, module) + ["--ros-args", *ros_args]
        self.process = processes.start(command, domain_id, log_path)
        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(client_name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.direct_inputs = []  # subscriptions served directly (nodes/direct_input.py)

    def subscribe_fast(self, msg_type, topic: str, callback, qos, with_info: bool = False) -> None:
        """A subscription taken without the executor's per-message overhead (for latency measurements);
        with_info: callback(message, info) with rmw's timestamps."""
        from ..nodes.direct_input import DirectInput, ServedDirectly

        subscription = self.node.create_subscription(msg_type, topic, callback, qos, callback_group=ServedDirectly())
        direct_input = DirectInput(None, self.context)
        direct_input.add(subscription, callback, with_info)
        self.direct_inputs.append(direct_input)

    def spin_until(self, condition, timeout: float) -> bool:
        """Spin the client until condition() or the deadline; a node process that died is an error."""
        deadline = time.monotonic() + timeout
        while not condition() and time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the node process exited; see {self.log_path}")
            for direct_input in self.direct_inputs:
                direct_input.pump(0.002)
            self.executor.spin_once(timeout_sec=0.0 if self.direct_inputs else 0.01)
        return bool(condition())

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)
        processes.stop(self.process)
