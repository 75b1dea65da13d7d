"""Shared fixtures: the shipped gauge, seeded RNGs, and a fresh rclpy Context per test."""
from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from profile_pose_ros.core import Gauge
from profile_pose_ros.nodes.process_tuning import LOOP_SWITCH_INTERVAL_S, shorten_switch_interval
from profile_pose_ros.tools.processes import domain_range, fresh_domain_id

# Side by side (pytest-xdist, scripts/test.sh), each worker takes a share of fresh_domain_id's usual domains:
# 1-100 and 101-200 for two workers
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
if _WORKER.startswith("gw"):
    _ALL_FIRST, _ALL_LAST = domain_range("")
    _SHARE = (_ALL_LAST - _ALL_FIRST + 1) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    _FIRST = _ALL_FIRST + int(_WORKER[2:]) * _SHARE
    os.environ["PROFILE_POSE_DOMAIN_IDS"] = f"{_FIRST}-{_FIRST + _SHARE - 1}"


class _Turns:
    """Across the workers of one run: a test marked `alone` waits until no other test runs, and no test starts
    while it runs, so a test that judges the live loop's timing has the machine to itself as in a serial run.
    A readers-writer lock on flock(2) with a gate in front, so that a waiting `alone` test is not starved by
    the other workers' tests starting one after another."""

    def __init__(self, directory: Path) -> None:
        self.gate = open(directory / "turns.gate", "a")
        self.lock = open(directory / "turns.lock", "a")

    @contextlib.contextmanager
    def turn(self, alone: bool):
        fcntl.flock(self.gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(self.lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            fcntl.flock(self.gate, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(self.lock, fcntl.LOCK_UN)


_turns: _Turns | None = None
_TURNS_DIR = "PROFILE_POSE_TEST_TURNS"  # made by the run's controller, inherited by its workers


def pytest_configure(config) -> None:
    global _turns
    if hasattr(config, "workerinput"):
        if os.environ.get(_TURNS_DIR):
            _turns = _Turns(Path(os.environ[_TURNS_DIR]))
    elif config.pluginmanager.hasplugin("xdist") and config.getoption("numprocesses", None):
        os.environ[_TURNS_DIR] = tempfile.mkdtemp(prefix="profile_pose_turns_")


def pytest_unconfigure(config) -> None:
    if not hasattr(config, "workerinput") and os.environ.get(_TURNS_DIR):
        shutil.rmtree(os.environ.pop(_TURNS_DIR), ignore_errors=True)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Setup, call and teardown of each test (a module's fixtures with its first test) inside its turn."""
    if _turns is None:
        return (yield)
    with _turns.turn(item.get_closest_marker("alone") is not None):
        return (yield)


_rerun_reasons: list[tuple[str, str]] = []


def pytest_runtest_logreport(report) -> None:
    """A test's failed attempt that pytest-rerunfailures ran again (outcome "rerun"): kept for the summary. The
    plugin's summary names the test only, and a flaky first attempt on a fresh runner is what to look at."""
    if report.outcome == "rerun" and report.longrepr is not None:
        _rerun_reasons.append((report.nodeid, report.longreprtext))


def pytest_terminal_summary(terminalreporter) -> None:
    for nodeid, text in _rerun_reasons:
        terminalreporter.write_sep("-", f"why {nodeid} was run again")
        terminalreporter.write_line("\n".join(text.splitlines()[-40:]))


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


def on_a_table(gauge: Gauge, rotation: np.ndarray, t: np.ndarray, points: np.ndarray, below: float) -> np.ndarray:
    """The profile with what the gauge stands on: a plane `below` m under its base, met by every ray (along +z in
    F) that misses the gauge, as a cell's table or fixture plate is (shadows not modelled: the plane reaches
    the side walls)."""
    out = points.copy()
    miss = np.isnan(out[:, 1])
    depth = (gauge.base_z - below - t[2] - rotation[2, 0] * out[miss, 0]) / rotation[2, 2]
    out[miss, 1] = depth + 5e-6 * np.random.default_rng(0).standard_normal(depth.size)
    return out


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
