"""Shared fixtures: the shipped gauge, seeded RNGs, and a fresh rclpy Context per test."""
from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from profile_pose_ros.core import Gauge
from profile_pose_ros.nodes.process_tuning import LOOP_SWITCH_INTERVAL_S, shorten_switch_interval
from profile_pose_ros.tools.processes import fresh_domain_id

# Nodes under test run in this process: tuned as their own processes are (run_node's switch_interval)
shorten_switch_interval(LOOP_SWITCH_INTERVAL_S)

ROOT = Path(__file__).resolve().parent.parent
PAPER_GAUGE = ROOT / "config" / "gauge_paper_n5.yaml"


@pytest.fixture(scope="session")
def gauge() -> Gauge:
    return Gauge.from_yaml(PAPER_GAUGE)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20260122)


unique_domain_id = fresh_domain_id  # distinct per test, and from every Graph of this pytest process


def wait_for(condition, timeout: float = 10.0) -> bool:
    """Poll a condition set by other threads (a client's and a controller's, no ROS executor), on the local
    clock, until it holds or `timeout` passes."""
    done = threading.Event()
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        done.wait(0.005)
    return bool(condition())


def paced(action, period: float = 0.005):
    """action() at most once per period: publishing on every spin turn floods a subscription's queue, and on a
    slow machine the message a node handles is then as old as depth x turn time (stale for a node that checks
    stamps); a real sender runs at the profile rate."""
    last = [-float("inf")]

    def run(*args, **kwargs) -> None:
        if time.monotonic() - last[0] >= period:
            last[0] = time.monotonic()
            action(*args, **kwargs)

    return run


class RosHarness:
    """A fresh Context on its own domain, an executor, and helpers to spin until a condition."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.rclpy = rclpy
        self.context = Context()
        self.domain_id = unique_domain_id()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []

    def add(self, node):
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str):
        return self.add(self.rclpy.create_node(name, context=self.context))

    def spin_until(self, condition, timeout: float = 10.0, action=None) -> bool:
        """Spin until condition() is true or the deadline passes; action() runs each turn (e.g. publish)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            if action is not None:
                action()
            for node in self.nodes:  # nodes that take their input directly (nodes/direct_input.py)
                if hasattr(node, "pump"):
                    node.pump(0.0)
            self.executor.spin_once(timeout_sec=0.02)
        return bool(condition())

    def close(self) -> None:
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        self.rclpy.shutdown(context=self.context)


@pytest.fixture
def ros():
    harness = RosHarness()
    yield harness
    harness.close()
