"""sim_cell's robot controller enforces the MotoPlus protocol's rules (a raw client on loopback)."""
from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from profile_pose_ros.core.wire import motoplus_protocol as mp
from profile_pose_ros.sim.arm import Arm
from profile_pose_ros.sim.robot_controller import RobotController

HELLO = mp.Hello(12000, (100,) * 6, (3000,) * 6, 300)


class Client:
    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
        self.reader = mp.FrameReader()
        self.seq = 0
        self.frames: list[mp.Frame] = []

    def send(self, body, seq: int | None = None) -> None:
        self.seq = self.seq + 1 if seq is None else seq
        self.sock.sendall(mp.encode(mp.Frame(self.seq, 0, body)))

    def next(self, kind=mp.State, timeout: float = 2.0) -> mp.Frame:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            while self.frames:
                frame = self.frames.pop(0)
                if isinstance(frame.body, kind):
                    return frame
            data = self.sock.recv(4096)
            if not data:
                raise ConnectionError("closed")
            self.frames += self.reader.feed(data)
        raise TimeoutError(kind)


@pytest.fixture
def controller():
    c = RobotController(Arm(), port=0).start()
    yield c
    c.close()


def armed(controller) -> Client:
    client = Client(controller.port)
    client.send(HELLO)
    assert client.next().body.status & mp.ARMED
    return client


def test_state_paces_the_loop_and_increments_are_clamped(controller) -> None:
    client = armed(controller)
    times = []
    for _ in range(10):
        state = client.next()
        times.append(time.monotonic())
        client.send(mp.Correction((1000, -1000, 0, 0, 0, 0)))  # 10x the per-cycle limit
    state = client.next()
    assert 0.008 < np.median(np.diff(times)) < 0.016  # one STATE per 12 ms period
    assert state.body.offset[:2] == (1000, -1000)  # 10 periods x 100 um, not 10 x 1000
    assert state.body.status & mp.CLAMPED and controller.clamped >= 9


def test_three_missed_periods_hold_still(controller) -> None:
    client = armed(controller)
    for _ in range(5):
        state = client.next()
    assert state.body.status & mp.HOLDING and state.body.offset == (0,) * 6


def test_sequence_gap_faults_and_disarms(controller) -> None:
    client = armed(controller)
    client.next()
    client.send(mp.Correction((10,) + (0,) * 5), seq=client.seq + 5)
    fault = client.next(mp.Fault)
    assert fault.body.code == mp.FAULT_SEQUENCE_GAP and controller.session is None


def test_correction_before_hello_faults(controller) -> None:
    client = Client(controller.port)
    client.send(mp.Correction((10,) + (0,) * 5))
    assert client.next(mp.Fault).body.code == mp.FAULT_NOT_ARMED


def test_watchdog_ends_a_silent_session(controller) -> None:
    client = armed(controller)
    fault = client.next(mp.Fault, timeout=3.0)
    assert fault.body.code == mp.FAULT_WATCHDOG and controller.session is None


def test_total_offset_bound_faults(controller) -> None:
    client = armed(controller)
    with pytest.raises(ConnectionError):
        for _ in range(40):  # 100 um per period runs into the 3 mm bound
            client.next()
            client.send(mp.Correction((100,) + (0,) * 5))
    assert controller.last_fault[0] == mp.FAULT_LIMIT
    assert controller.correction[0] <= 3000


def test_a_second_peer_is_refused(controller) -> None:
    first = armed(controller)
    second = socket.create_connection(("127.0.0.1", controller.port), timeout=2.0)
    assert second.recv(16) == b""  # closed at once
    assert first.next().body.status & mp.ARMED and controller.refused == 1


def test_hello_with_the_wrong_period_is_refused(controller) -> None:
    client = Client(controller.port)
    client.send(mp.Hello(4000, (100,) * 6, (3000,) * 6, 300))
    assert client.next(mp.Fault).body.code == mp.FAULT_PROTOCOL and controller.session is None


def test_arm_model_reproduces_table_iv_open_loop() -> None:
    for size, expected in ((1e-3, (5.39, 65.88, 13.98)), (2e-3, (4.86, 39.48, 8.06))):
        arm = Arm()
        arm.command[:] = size
        peak = np.zeros(6)
        for _ in range(300):
            arm.advance(0.004)
            peak = np.maximum(peak, arm.position)
        overshoot = 100 * (peak[:3] - size) / size
        np.testing.assert_allclose(overshoot, expected, rtol=0.02)


def hello_with(**changes) -> mp.Hello:
    fields = dict(period_us=12000, max_step=(100,) * 6, max_offset=(3000,) * 6, watchdog_ms=300)
    fields.update(changes)
    return mp.Hello(**fields)


@pytest.mark.parametrize("hello, said", [
    (hello_with(max_step=(2 ** 31 - 1,) * 6), "max_step[0]"),
    (hello_with(max_offset=(100, 100, 100, 100, 100, 2 ** 31 - 1)), "max_offset[5]"),
    (hello_with(max_step=(0,) * 6), "max_step[0] = 0"),  # zero is refused, not read as "no limit"
    (hello_with(watchdog_ms=2 ** 32 - 1), "watchdog_ms"),
    (hello_with(watchdog_ms=1), "watchdog_ms"),
    (hello_with(period_us=4000), "period"),
])
def test_a_hello_beyond_the_controllers_own_limits_is_refused_and_moves_nothing(controller, hello, said) -> None:
    client = Client(controller.port)
    client.send(hello)
    fault = client.next(mp.Fault)
    assert fault.body.code in (mp.FAULT_LIMIT, mp.FAULT_PROTOCOL) and said in fault.body.text, fault.body.text
    assert controller.session is None and not np.any(controller.correction)


def test_a_second_hello_cannot_widen_the_clamp_mid_session(controller) -> None:
    client = armed(controller)
    client.send(hello_with(max_step=(200,) * 6))
    assert "second HELLO" in client.next(mp.Fault).body.text
    assert controller.session is None


def test_the_session_runs_on_the_narrower_of_the_hello_and_the_controller(controller) -> None:
    """The HELLO asks for 100 units; the controller allows 200 um and 573 (1e-3 rad): 100 it is."""
    client = armed(controller)
    client.next()
    client.send(mp.Correction((10_000,) * 6))
    state = client.next()
    for _ in range(3):
        if any(state.body.offset):
            break
        state = client.next()
    assert state.body.offset == (100,) * 6 and state.body.status & mp.CLAMPED


def test_an_idle_connection_is_closed_within_a_second_and_frees_the_slot(controller) -> None:
    idle = Client(controller.port)
    opened = time.monotonic()
    with pytest.raises(ConnectionError):
        idle.next(timeout=3.0)
    assert time.monotonic() - opened < 1.5 and controller.idle_closed == 1
    armed(controller)  # the one slot is free again


def test_the_controller_counts_the_triggers_that_did_not_come_one_period_after_the_last() -> None:
    """The trigger stamps' witness (test_trigger_stamps): a period whose trigger came a tick late, as when the
    task missed one, is one step; the periods after it, a period apart again, are not."""
    c = RobotController(Arm(), port=0)
    try:
        status = c.app.status()
        period_ns = round(c.period_s * 1e9)
        for tick_ns in (0, period_ns, 2 * period_ns, 3 * period_ns + 4_000_000, 4 * period_ns + 4_000_000):
            c._period(tick_ns, status)
        assert c.trigger_steps == 1 and c.report()["robot_trigger_steps"] == 1
    finally:
        c.close()
