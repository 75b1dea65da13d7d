"""The `main(args=None)` of every node: init, construct (a configuration error exits 1 with the reason,
not a traceback), spin until Ctrl-C or shutdown, and always destroy the node and shut rclpy down."""
from __future__ import annotations

import faulthandler
import gc
import signal
import sys
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from .realtime import realtime_from_parameters


SHUTDOWN_GRACE_S = 10.0  # from the stop request to the process gone, whatever hangs


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
             spin: Callable[[SingleThreadedExecutor, Node, StopRequest], None] | None = None) -> int:
    """Ctrl-C and SIGTERM (a process manager's stop) only ask the spin loop to end (`spin` gets that
    event too), so no callback is cut short and destroy_node() runs whole with a live context: the
    bridge's STOP, the recorder draining its queues and closing its bag."""
    return run_nodes([factory], name, args, startup_errors,
                     None if spin is None else lambda executor, nodes, stop: spin(executor, nodes[0], stop))


def run_nodes(factories: list[Callable[[], Node]], name: str, args=None,
              startup_errors: tuple[type[BaseException], ...] = (ValueError,),
              spin: Callable[[SingleThreadedExecutor, list[Node], StopRequest], None] | None = None,
              destroy_order: Callable[[list[Node]], list[Node]] = lambda nodes: nodes) -> int:
    """run_node for several nodes in one process (cell_container): built in the given order (a node that
    fails to start takes down those built before it), one executor, destroyed in `destroy_order`."""
    stop = StopRequest().install()
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
    # What start-up built (modules, compiled kernels, rclpy's types: ~10^5 objects) lives as long as the
    # process; frozen, the collector never walks it again. A full collection over it took 37 ms here,
    # tens of profiles at 1 kHz; what the node allocates from now on is collected as usual.
    gc.collect()
    gc.freeze()
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
        # Seen once (2026-12-02, all five nodes stopping at once when their bringup was SIGKILLed): rcl's
        # node teardown spun for minutes at 100 % CPU holding the GIL. faulthandler's watchdog is a C thread:
        # past the grace it prints where the process hung (to the log) and exits, so no node outlives its
        # cell. destroy_node() has done what matters by then (the bridge's STOP, the bag closed).
        faulthandler.dump_traceback_later(SHUTDOWN_GRACE_S, exit=True)
        executor.shutdown()
        for node in destroy_order(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
        faulthandler.cancel_dump_traceback_later()
    return 0
