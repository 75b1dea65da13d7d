"""sim_cell's robot controller: the MotoPlus application of firmware/motoplus, run on this host.

The rules of docs/motoplus_protocol.md live in the C application (mpcl_app.c, mpcl_session.c), the code a
user loads on the YRC1000. This module is only its surroundings: the 4 ms interpolation clock, the arm
that moves by what the application hands mpExRcsIncrementMove, the pose mpGetCartPos reports, the
controller's configuration (D variables) and network faults a test injects. Each control period (3 cycles
= 12 ms by default) the application sends STATE, which paces the bridge, and the cell raises its
per-cycle output (it triggers the profiler at the arm's pose of that instant).
"""
from __future__ import annotations

import ipaddress
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.wire import motoplus_protocol as mp
from ..core.control.controller_limits import ControllerLimits
from .arm import Arm
from .motoplus_app import HostApplication, Status

TICK_S = 0.004  # the YRC1000's interpolation clock


@dataclass
class ControllerFaults:
    state_delay_s: float = 0.0  # every frame the controller sends this much late
    state_drop_fraction: float = 0.0  # STATEs the controller skips
    disconnect_after_periods: int = 0  # break the link after this many STATEs (0: never); once


# The simulated controller's own limits (SI), unless sim_cell's controller_max_* parameters say otherwise
DEFAULT_LIMITS_SI = {"max_step": [2e-4] * 3 + [1e-3] * 3, "max_offset": [5e-3] * 3 + [4e-2] * 3,
                     "max_speed": [0.05] * 3 + [0.25] * 3, "max_watchdog_s": 2.0}
DEFAULT_LIMITS = ControllerLimits.from_si(**DEFAULT_LIMITS_SI)


def configuration(limits: ControllerLimits, period_ticks: int, bridge_address: str = "") -> dict[int, int]:
    """The application's D variables (offsets from MPCL_CONFIG_D_BASE, mpcl_app.h) for these limits;
    bridge_address: the one peer it accepts ("": any). The port is the host's (HostApplication)."""
    peer = int(ipaddress.IPv4Address(bridge_address)) if bridge_address else 0
    values = [*limits.max_step, *limits.max_offset, *limits.max_speed, limits.max_watchdog_ms, period_ticks, 0,
              int(round(TICK_S * 1e6)), peer - 2 ** 32 if peer >= 2 ** 31 else peer]  # D variables are signed
    return dict(enumerate(values))


class RobotController:
    def __init__(self, arm: Arm, on_period: Callable[[int], None] | None = None, host: str = "127.0.0.1",
                 port: int = 0, period_ticks: int = 3, faults: ControllerFaults | None = None,
                 seed: int = 3, on_applied: Callable[[float, tuple[int, ...]], None] | None = None,
                 limits: ControllerLimits = DEFAULT_LIMITS,
                 pose_of: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        """on_applied(wall time, increment in units): every armed period, the step the application committed
        (spread over the period's cycles; zeros when it held): the witness the safety checks judge by.
        pose_of(arm offset): the tool pose mpGetCartPos reports (x y z m, Rx Ry Rz rad); None: the offset."""
        self.arm = arm
        self.pose_of = pose_of or (lambda offset: offset)
        self.on_period = on_period
        self.on_applied = on_applied
        self.period_ticks = period_ticks
        self.faults = faults or ControllerFaults()
        self.seed = seed
        self.program = np.zeros(6)  # the robot program's target offset from the start pose (m, rad)
        self.moved = np.zeros(6, dtype=np.int64)  # what mpExRcsIncrementMove was handed, summed (units)
        self.app = HostApplication(configuration(limits, period_ticks), host, port)
        self._pushed: tuple[float, float] | None = None
        self._periods = 0
        # the controller's own record of its trigger's spacing (its clock, not the stamps a test judges): periods
        # whose trigger came other than one period after the last, as when its task missed ticks
        self.trigger_steps = 0
        self._last_trigger_ns: int | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.port = 0
        self.host = ""  # where it listens, once started
        self._clock = threading.Thread(target=self._run_clock, name="interpolation-clock", daemon=True)

    @property
    def period_s(self) -> float:
        return self.period_ticks * TICK_S

    def start(self) -> "RobotController":
        self.arm.advance(0.0)  # loads the compiled dynamics (~0.5 s in a fresh process) before the clock runs
        self.port = self.app.start()
        self.host = self.app.address()
        self._clock.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._clock.is_alive():
            self._clock.join(timeout=2.0)
        self.app.stop()

    # ---------------------------------------------------------------- what the application reports
    @property
    def session(self):
        """The application's status while a session is armed, else None."""
        status = self.app.status()
        return status if status.armed else None

    @property
    def correction(self) -> np.ndarray:
        """The total offset the application has committed (units)."""
        return np.array(self.app.status().offset, dtype=np.int64)

    def _stat(self, name: str) -> int:
        return getattr(self.app.status().stats, name)

    clamped = property(lambda self: self._stat("clamped"))
    faults_raised = property(lambda self: self._stat("faults"))
    idle_closed = property(lambda self: self._stat("idle_closed"))
    sessions_ended = property(lambda self: self._stat("sessions_ended"))
    replaced = property(lambda self: self._stat("replaced"))
    states_sent = property(lambda self: self._stat("states"))
    refused = property(lambda self: self._stat("refused_peers"))  # second peers closed at once

    @property
    def last_fault(self) -> tuple[int, str]:
        stats = self.app.status().stats
        return stats.last_fault_code, stats.last_fault.decode(errors="replace")

    @property
    def session_end(self) -> str:
        return self.app.status().stats.session_end.decode(errors="replace")

    def report(self) -> dict:
        """What sim_cell's /diagnostics show of the controller, from one read of the application's status."""
        status = self.app.status()
        s = status.stats
        return {"robot_port": self.port, "robot_armed": bool(status.armed), "robot_states": s.states,
                "robot_faults": s.faults, "robot_last_fault": s.last_fault.decode(errors="replace") or "none",
                "robot_clamped": s.clamped, "robot_idle_connections_closed": s.idle_closed,
                "robot_corrections_replaced": s.replaced,
                "robot_session_end": s.session_end.decode(errors="replace") or "none",
                "robot_sessions_ended": s.sessions_ended, "robot_clock_overruns": self.app.overruns(),
                "robot_trigger_steps": self.trigger_steps,
                "arm_offset_um": [round(x * 1e6, 1) for x in self.arm.position[:3]]}

    # ---------------------------------------------------------------- the clock
    def _push_faults(self) -> None:
        f = self.faults
        wanted = (f.state_drop_fraction, f.state_delay_s)
        if wanted != self._pushed or f.disconnect_after_periods:
            self.app.set_net_faults(f.state_drop_fraction, f.state_delay_s, f.disconnect_after_periods, self.seed)
            f.disconnect_after_periods = 0  # once
            self._pushed = wanted

    def _run_clock(self) -> None:
        deadline = time.monotonic()
        period = 0  # the application's periods so far (its cycles // period_ticks)
        while not self._stop.is_set():
            deadline += TICK_S
            delay = deadline - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            self._push_faults()
            with self._lock:
                self.arm.command = self.program + np.array(mp.units_to_metres(self.moved))
                self.arm.advance(TICK_S)
                pose = mp.metres_to_units(self.pose_of(self.arm.position))
            self.moved += self.app.tick(pose)
            # The period is the application's: its STATE went out in the cycle that made its count a multiple of
            # the period, and the trigger follows that STATE, as the real controller's task does both. This
            # clock's own tick count drifts from the application's whenever its task misses a tick, and a
            # trigger a tick after the STATE makes each correction miss the bridge's answer_wait
            # (docs/performance.md, "The simulated trigger's phase").
            status = self.app.status()
            if status.cycles // self.period_ticks != period:
                period = status.cycles // self.period_ticks
                self._period(int(deadline * 1e9), status)

    def _period(self, tick_ns: int, status: Status) -> None:
        if self._last_trigger_ns is not None and abs(tick_ns - self._last_trigger_ns - self.period_s * 1e9) > \
                TICK_S * 1e9 / 2:
            self.trigger_steps += 1
        self._last_trigger_ns = tick_ns
        if status.periods != self._periods and self.on_applied is not None:  # an armed period
            self.on_applied(time.time(), tuple(status.period_step))
        self._periods = status.periods
        if self.on_period is not None:
            # The per-cycle output, right after the STATE, as the real controller's task does both at once.
            # The arm has not moved since; the edge is at the tick's time, however late this thread runs.
            self.on_period(tick_ns)
