"""The safety invariants: core.safety.SafetyMonitor on its own, the bridge's client against sim_cell's robot
controller (with bugs planted in the client to show the monitor stops them), and STOP on every shutdown
path of the bridge process."""
from __future__ import annotations

import dataclasses
import signal
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from profile_pose_ros.core.wire import motoplus_protocol as mp
from profile_pose_ros.core.control.safety import INVARIANTS, SafetyMonitor
from profile_pose_ros.devices.motoplus_client import ARMED, MotoPlusClient, SessionLimits
from profile_pose_ros.sim.arm import Arm
from profile_pose_ros.sim.robot_controller import DEFAULT_LIMITS, RobotController
from profile_pose_ros.tools import processes
from profile_pose_ros.tools.graph import MODULES, ros_params

from conftest import unique_domain_id, wait_for

STEP, BOUND = (200,) * 3 + (100,) * 3, (5000,) * 3 + (2000,) * 3


def monitor() -> SafetyMonitor:
    m = SafetyMonitor(STEP, BOUND, lambda: 0.05)
    m.rearmed()
    return m


def test_each_invariant_is_flagged_on_its_own() -> None:
    now, fresh, offset = 100.0, 99.99, (0,) * 6
    ok = (100, 0, 0, 0, 0, 0)
    assert monitor().check(ok, True, fresh, now, offset) == []
    assert monitor().check((201, 0, 0, 0, 0, 0), True, fresh, now, offset) == ["clamp"]
    assert monitor().check(ok, False, fresh, now, offset) == ["not_armed"]
    assert monitor().check(ok, True, now - 0.051, now, offset) == ["stale"]
    assert monitor().check(ok, True, None, now, offset) == ["stale"]
    assert monitor().check(ok, True, now + 0.0021, now, offset) == ["stale"]  # from the future: no fresher
    assert monitor().check(ok, True, now + 3600.0, now, offset) == ["stale"]
    assert monitor().check(ok, True, float("nan"), now, offset) == ["stale"]
    assert monitor().check(ok, True, fresh, now, (4950, 0, 0, 0, 0, 0)) == ["offset"]
    assert monitor().check((-100, 0, 0, 0, 0, 0), True, fresh, now, (-4950, 0, 0, 0, 0, 0)) == ["offset"]
    latched = monitor()
    latched.fault()
    assert latched.check(ok, True, fresh, now, offset) == ["after_fault"]
    latched.rearmed()
    assert latched.check(ok, True, fresh, now, offset) == []
    assert SafetyMonitor(STEP, BOUND, lambda: 0.05).check(ok, True, fresh, now, offset) == ["after_fault"]


@settings(max_examples=300, deadline=None)
@given(units=st.lists(st.integers(-10 ** 6, 10 ** 6), min_size=6, max_size=6),
       armed=st.booleans(), age=st.one_of(st.none(), st.floats(-1.0, 1.0)),
       offset=st.lists(st.integers(-6000, 6000), min_size=6, max_size=6))
def test_a_zero_increment_always_passes_and_a_passed_one_keeps_every_rule(units, armed, age, offset) -> None:
    m = monitor()
    now = 1000.0
    stamp = None if age is None else now - age
    assert m.check((0,) * 6, armed, stamp, now, offset) == []
    if not m.check(units, armed, stamp, now, offset) and any(units):
        assert armed and age is not None and -0.002 <= age <= 0.05
        assert all(abs(u) <= s for u, s in zip(units, STEP))
        assert all(abs(o + u) <= b for o, u, b in zip(offset, units, BOUND))
    assert m.total_violations == sum(m.violations.values()) and set(m.violations) == set(INVARIANTS)


class Cell:
    """sim_cell's robot controller in this process, recording every increment it applied."""

    def __init__(self) -> None:
        self.applied: list[tuple[int, ...]] = []
        # the controller's own watchdog limit raised: the shutdown tests below need a 5 s session watchdog
        limits = dataclasses.replace(DEFAULT_LIMITS, max_watchdog_ms=10_000)
        self.controller = RobotController(Arm(), port=0, on_applied=lambda _t, units: self.applied.append(units),
                                          limits=limits)
        self.controller.start()

    def client(self, increment, client_class=MotoPlusClient) -> MotoPlusClient:
        limits = SessionLimits(max_step=mp.units_to_metres(STEP), max_offset=mp.units_to_metres(BOUND),
                               watchdog_s=2.0)
        return client_class("127.0.0.1", self.controller.port, limits, increment, lambda *_: None,
                            max_age_s=lambda: 0.05, log=lambda _text: None).start()

    def close(self) -> None:
        self.controller.close()


@pytest.fixture
def cell():
    c = Cell()
    yield c
    c.close()


def test_a_steady_push_stops_at_the_offset_bound_without_a_controller_fault(cell) -> None:
    client = cell.client(lambda now: (np.array([1e-3, 0, 0, 0, 0, 0]), now))  # 1 mm per period, forever
    client.arm()
    try:
        assert wait_for(lambda: cell.controller.correction[0] == BOUND[0]), cell.controller.correction
        assert wait_for(lambda: client.counters.offset_limited >= 5)
        assert client.state == ARMED and cell.controller.faults_raised == 0, cell.controller.last_fault
        assert client.monitor.total_violations == 0 and client.counters.clamped > 0
        assert max(abs(u[0]) for u in cell.applied) == STEP[0]
    finally:
        client.stop()


class NoLimits(MotoPlusClient):
    """A planted bug: the client's own clamping is gone."""

    def _limit(self, units):
        return units


def test_the_monitor_stops_what_a_bug_lets_through_and_disarms(cell) -> None:
    client = cell.client(lambda now: (np.array([1e-3, 0, 0, 0, 0, 0]), now), NoLimits)
    client.arm()
    try:
        assert wait_for(lambda: client.monitor.violations["clamp"] > 0)
        assert wait_for(lambda: cell.controller.session_end == "STOP") and client.state != ARMED
        assert all(u == (0,) * 6 for u in cell.applied), "an increment above the clamp reached the controller"
        assert cell.controller.clamped == 0
    finally:
        client.stop()


class SlowStop(MotoPlusClient):
    """A planted delay: STOP leaves 0.2 s after it was asked for (a thread switch at the wrong moment, on a
    loaded machine), long enough for the socket thread to notice the disarmed state several times over."""

    def _send(self, body):
        if isinstance(body, mp.Stop):
            threading.Event().wait(0.2)
        return super()._send(body)


@pytest.mark.parametrize("ending", ["stop", "disarm"])
def test_stop_reaches_the_controller_however_late_it_leaves(cell, ending) -> None:
    """The socket thread must not close the connection between the state change and STOP: the STOP would
    find no socket and the controller, its STATEs unread, a reset ('a receive failed')."""
    client = cell.client(lambda now: (np.zeros(6), now), SlowStop)
    client.arm()
    try:
        assert wait_for(lambda: client.state == ARMED and len(cell.applied) > 5)
        client.stop() if ending == "stop" else client.disarm("test")
        assert wait_for(lambda: cell.controller.session is None)
        assert cell.controller.session_end == "STOP"
    finally:
        client.stop()


def test_the_monitor_refuses_a_stale_correction_the_client_passed_on(cell) -> None:
    client = cell.client(lambda now: (np.array([1e-4, 0, 0, 0, 0, 0]), now - 0.2))  # a bug: no age check
    client.arm()
    try:
        assert wait_for(lambda: client.monitor.violations["stale"] > 0)
        assert wait_for(lambda: cell.controller.session_end == "STOP")
        assert not any(any(u) for u in cell.applied)
    finally:
        client.stop()


# Once more on failure: in one clean-clone CI run (2026-12-04) the SIGINT case saw the controller end on a
# dropped connection instead of STOP (the safe end, not the asked one); 0 of 40 runs reproduced it on an idle
# machine. Still open: docs/safety.md.
@pytest.mark.flaky(reruns=1)
@pytest.mark.parametrize("signum,end,burst", [(signal.SIGTERM, "STOP", 1), (signal.SIGINT, "STOP", 1),
                                              (signal.SIGTERM, "STOP", 200),
                                              (signal.SIGKILL, "the bridge disconnected", 1)])
def test_the_bridge_process_sends_stop_on_every_shutdown_path(cell, tmp_path, signum, end, burst) -> None:
    """SIGTERM (a process manager) and SIGINT (Ctrl-C) take the node's clean path, which sends STOP;
    SIGKILL cannot, and the controller, having lost its peer, holds still. A burst of signals (a parent's
    death signal on top of a process manager's) is one clean stop. (A node once deadlocked in its signal
    handler that way; this burst does not reproduce that race, nodes/run.py's StopRequest removes it.)"""
    # watchdog 5 s: the controller must see the lost peer before its watchdog would end the session; with
    # 2 s, one full-suite run on this loaded VM saw the watchdog first (the read thread woke too late).
    command = processes.executable("motoplus_bridge", MODULES["motoplus_bridge"]) + ["--ros-args", *ros_params(
        {"port": cell.controller.port, "arm_on_start": True, "watchdog": 5.0, "input_timeout": 5.0})]
    process = processes.start(command, unique_domain_id(), tmp_path / "bridge.log")
    try:
        assert wait_for(lambda: len(cell.applied) > 10, 30.0), (tmp_path / "bridge.log").read_text()
        for _ in range(burst):
            process.send_signal(signum)
        process.wait(10.0)
        assert wait_for(lambda: cell.controller.session is None)
        # SIGKILL: the controller learns of it by reading the end of the stream, or by a STATE it cannot send
        assert cell.controller.session_end.startswith(end), (tmp_path / "bridge.log").read_text()
    finally:
        processes.stop(process)


def test_the_composed_loop_sends_stop_when_its_process_is_terminated(cell, tmp_path) -> None:
    """cell_container holds the bridge among three other nodes: SIGTERM still takes the clean path, and the
    bridge is torn down first, so the controller hears STOP, not a dropped connection."""
    import yaml

    from profile_pose_ros.tools.graph import free_port

    params = tmp_path / "container.yaml"  # per node: `-p port:=` would give the driver the controller's port
    params.write_text(yaml.safe_dump({
        "/**/motoplus_bridge": {"ros__parameters": {"port": cell.controller.port, "arm_on_start": True,
                                                    "watchdog": 5.0, "input_timeout": 5.0}},
        "/**/profiler_driver": {"ros__parameters": {"port": free_port()}}}))  # no profiler: it retries
    command = processes.executable("cell_container", MODULES["cell_container"]) + [
        "--ros-args", "--params-file", str(params)]
    process = processes.start(command, unique_domain_id(), tmp_path / "container.log")
    try:
        assert wait_for(lambda: len(cell.applied) > 10, 60.0), (tmp_path / "container.log").read_text()
        process.send_signal(signal.SIGTERM)
        assert process.wait(15.0) == 0
        assert wait_for(lambda: cell.controller.session is None)
        assert cell.controller.session_end == "STOP", (tmp_path / "container.log").read_text()
    finally:
        processes.stop(process)


def test_a_correction_stream_that_stops_ends_the_session_and_its_return_moves_nothing(cell) -> None:
    """A killed and restarted estimator: the corrections stop, the bridge sends STOP after input_timeout,
    and when they come back the arm stays still (the controller's own record) until the operator re-arms."""
    streaming = threading.Event()
    streaming.set()
    client = cell.client(lambda now: (np.array([1e-5, 0, 0, 0, 0, 0]), now) if streaming.is_set() else None)
    client.input_timeout_s = 0.2
    client.arm()
    try:
        assert wait_for(lambda: sum(any(u) for u in cell.applied) >= 5)
        streaming.clear()
        assert wait_for(lambda: cell.controller.session_end == "STOP", 5.0), cell.controller.session_end
        assert client.counters.input_lost == 1 and client.state != ARMED
        streaming.set()
        moved_before = len(cell.applied)
        wait_for(lambda: False, 0.5)
        assert len(cell.applied) == moved_before, "the controller applied periods without a session"
        client.arm()
        assert wait_for(lambda: any(any(u) for u in cell.applied[moved_before:]))
    finally:
        client.stop()
