"""The `main(args=None)` of every node: init, construct (a configuration error exits 1 with the reason,
not a traceback), spin until Ctrl-C or shutdown, and always destroy the node and shut rclpy down."""
from __future__ import annotations

import signal
import sys
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from .process_tuning import (exit_if_shutdown_hangs, freeze_startup_heap, realtime_from_parameters,
                             shorten_switch_interval)


class StopRequest:
    """Ctrl-C / SIGTERM, as a plain flag the spin loops poll. threading.Event.set() takes a lock: a second
    signal arriving while the handler of the first was inside set() deadlocked the process (seen: a
    sim_cell left running for ever after its bringup was killed, three handlers deep)."""

    def __init__(self) -> None:
        self.requested = False

    def set(self, *_signal_args) -> None:
        self.requested = True

    def is_set(self) -> bool:
        return self.requested

    def install(self) -> "StopRequest":
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self.set)
        return self


def run_node(factory: Callable[[], Node], name: str, args=None,
             startup_errors: tuple[type[BaseException], ...] = (ValueError,),
             spin: Callable[[SingleThreadedExecutor, Node, StopRequest], None] | None = None,
             switch_interval: float | None = None) -> int:
    """Ctrl-C and SIGTERM (a process manager's stop) only ask the spin loop to end (`spin` gets that
    event too), so no callback is cut short and destroy_node() runs whole with a live context: the
    bridge's STOP, the recorder draining its queues and closing its bag."""
    return run_nodes([factory], name, args, startup_errors,
                     None if spin is None else lambda executor, nodes, stop: spin(executor, nodes[0], stop),
                     switch_interval=switch_interval)


def run_nodes(factories: list[Callable[[], Node]], name: str, args=None,
              startup_errors: tuple[type[BaseException], ...] = (ValueError,),
              spin: Callable[[SingleThreadedExecutor, list[Node], StopRequest], None] | None = None,
              destroy_order: Callable[[list[Node]], list[Node]] = lambda nodes: nodes,
              switch_interval: float | None = None) -> int:
    """run_node for several nodes in one process (cell_container): built in the given order (a node that
    fails to start takes down those built before it), one executor, destroyed in `destroy_order`.
    switch_interval: the GIL's, for a process whose threads have deadlines (process_tuning.py)."""
    stop = StopRequest().install()
    if switch_interval is not None:
        shorten_switch_interval(switch_interval)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    nodes: list[Node] = []
    try:
        for factory in factories:
            nodes.append(factory())
    except startup_errors as exc:
        print(f"[{name}] refusing to start: {exc}", file=sys.stderr)
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
        return 1
    freeze_startup_heap()
    scheduling = realtime_from_parameters(nodes)  # last: the DDS and device threads exist by now
    if scheduling is not None:
        for node in nodes:
            node.scheduling = scheduling  # reported in the node's /diagnostics (diagnostics.py)
        log = nodes[0].get_logger().warning if "refused" in scheduling else nodes[0].get_logger().info
        log(f"scheduling: {scheduling}")
    executor = SingleThreadedExecutor()
    for node in nodes:
        executor.add_node(node)
    try:
        if spin is not None:
            spin(executor, nodes, stop)
        else:
            while not stop.is_set() and executor.context.ok():
                executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        with exit_if_shutdown_hangs():
            executor.shutdown()
            for node in destroy_order(nodes):
                node.destroy_node()
            rclpy.try_shutdown()
    return 0
