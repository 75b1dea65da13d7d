"""The trigger-MCU link against sim_cell's MCU on loopback (no ROS): when it asks the driver to pair again."""
from __future__ import annotations

import threading
import time

import pytest

from profile_pose_ros.devices.trigger_link import TriggerLink
from profile_pose_ros.sim.trigger_mcu import TriggerMcu


class Resyncs:
    """The reasons the link gave for re-pairing, and a way to wait for the next one."""

    def __init__(self) -> None:
        self.reasons: list[str] = []
        self._cond = threading.Condition()

    def __call__(self, reason: str) -> None:
        with self._cond:
            self.reasons.append(reason)
            self._cond.notify_all()

    def wait_for(self, count: int, timeout: float = 5.0) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: len(self.reasons) >= count, timeout)


def wait_until(condition, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)  # polling a thread's state, not synchronising on time
    return True


@pytest.fixture
def rig():
    mcus: list[TriggerMcu] = []
    resyncs = Resyncs()
    mcus.append(TriggerMcu().start())
    link = TriggerLink(mcus[0].url, 1_000_000, on_trigger=lambda seq, t: None, on_resync_needed=resyncs,
                       reopen_delay=0.05)
    yield mcus, link.start(), resyncs
    link.stop()
    for mcu in mcus:
        mcu.close()


def test_every_connection_asks_for_a_new_pairing_even_when_its_ready_is_flushed(rig) -> None:
    mcus, link, resyncs = rig
    assert resyncs.wait_for(1) and "connected" in resyncs.reasons[0]
    assert wait_until(lambda: link.ok)
    port = mcus[0].port
    mcus[0].close()  # a new MCU process on the same port: its READY may come before pyserial flushes input
    mcus.append(TriggerMcu(port=port).start())
    assert resyncs.wait_for(2) and "connected" in resyncs.reasons[1]
    assert wait_until(lambda: link.ok)


def test_a_reset_we_asked_for_is_not_a_restart_but_a_reboot_is(rig) -> None:
    mcus, link, resyncs = rig
    assert resyncs.wait_for(1) and wait_until(lambda: link.ok)
    assert link.command("RESET")  # its READY follows the OK at once
    assert wait_until(lambda: time.monotonic() > link.ready_expected_until)
    assert resyncs.reasons == [resyncs.reasons[0]]
    mcus[0].reboot()  # later: a reboot (power, watchdog)
    assert resyncs.wait_for(2) and "restarted" in resyncs.reasons[1]


def test_the_simulated_uart_waits_out_a_line_without_returning_early() -> None:
    """precise_wait: never before the moment, and on Linux the waiting thread's timer slack is fine
    (so the sleep, not a spin, covers all but the last tens of microseconds)."""
    import ctypes
    import sys

    from profile_pose_ros.sim.precise_wait import FINE_SLACK_NS, wait_until

    results: list[tuple[float, int]] = []

    def waiter() -> None:
        for delay in (0.0, 5e-5, 3e-4, 2e-3):
            due = time.monotonic() + delay
            wait_until(due)
            results.append((time.monotonic() - due, ctypes.CDLL(None).prctl(30, 0, 0, 0, 0)))  # PR_GET_TIMERSLACK

    thread = threading.Thread(target=waiter)
    thread.start()
    thread.join()
    assert len(results) == 4 and all(late >= 0.0 for late, _ in results)
    if sys.platform == "linux":
        assert all(slack == FINE_SLACK_NS for _, slack in results)
