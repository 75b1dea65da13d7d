"""The `main(args=None)` of every node: init, construct (a configuration error exits 1 with the reason,
not a traceback), spin until Ctrl-C or shutdown, and always destroy the node and shut rclpy down."""
from __future__ import annotations

import signal
import sys
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node


def run_node(factory: Callable[[], Node], name: str, args=None,
             startup_errors: tuple[type[BaseException], ...] = (ValueError,),
             spin: Callable[[SingleThreadedExecutor, Node], None] | None = None,
             sigterm_as_interrupt: bool = False) -> int:
    """sigterm_as_interrupt: a process manager's SIGTERM takes Ctrl-C's path, for nodes whose shutdown
    must run (the bridge's STOP, the recorder closing its bag)."""
    if sigterm_as_interrupt:
        signal.signal(signal.SIGTERM, _interrupt)
    rclpy.init(args=args)
    try:
        node = factory()
    except startup_errors as exc:
        print(f"[{name}] refusing to start: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        if spin is None:
            executor.spin()
        else:
            spin(executor, node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _interrupt(*_) -> None:
    raise KeyboardInterrupt
