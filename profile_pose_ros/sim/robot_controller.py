"""The simulated robot controller: the MotoPlus side of docs/motoplus_protocol.md, over the arm model.

A thread runs the 4 ms interpolation clock. Each tick the arm advances; each control period (3 ticks =
12 ms by default) the controller applies the newest CORRECTION it received (clamped per cycle, the total
offset bounded), sends STATE, which paces the bridge, and raises its per-cycle output (the cell triggers
the profiler at the arm's pose of that instant). It enforces every rule of the protocol and
can be told to misbehave (delayed or dropped STATE, a disconnect).
"""
from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core import motoplus_protocol as mp
from ..core.controller_limits import HELLO_TIMEOUT_S, ControllerLimits, HelloRefused, SessionBounds
from .arm import Arm
from .peer_server import PeerServer

TICK_S = 0.004  # the YRC1000's interpolation clock
HOLD_AFTER_PERIODS = 3


@dataclass
class ControllerFaults:
    state_delay_s: float = 0.0  # every STATE this much late
    state_drop_fraction: float = 0.0
    disconnect_after_periods: int = 0  # close the session after this many armed periods (0: never); once


# The simulated controller's own limits (SI), unless sim_cell's controller_max_* parameters say otherwise
DEFAULT_LIMITS_SI = {"max_step": [2e-4] * 3 + [1e-3] * 3, "max_offset": [5e-3] * 3 + [2e-2] * 3,
                     "max_speed": [0.05] * 3 + [0.25] * 3, "max_watchdog_s": 2.0}
DEFAULT_LIMITS = ControllerLimits.from_si(**DEFAULT_LIMITS_SI)


@dataclass
class Session:
    hello: mp.Hello
    bounds: SessionBounds
    armed_at: float
    last_seq: int
    last_frame: float
    pending: tuple[int, mp.Correction] | None = None
    periods_without: int = 0
    applied_seq: int = 0
    periods: int = 0


class RobotController:
    def __init__(self, arm: Arm, on_period: Callable[[int], None] | None = None, host: str = "127.0.0.1",
                 port: int = 0, period_ticks: int = 3, faults: ControllerFaults | None = None,
                 seed: int = 3, on_applied: Callable[[float, tuple[int, ...]], None] | None = None,
                 limits: ControllerLimits = DEFAULT_LIMITS) -> None:
        """on_applied(wall time, increment in units): every armed period, what the arm was told to move
        (zeros when it held): the ground truth the safety checks compare the bridge against."""
        self.arm = arm
        self.limits = limits  # the controller's own: a HELLO may narrow them, never widen them
        self.on_period = on_period
        self.on_applied = on_applied
        self.period_ticks = period_ticks
        self.faults = faults or ControllerFaults()
        self.rng = np.random.default_rng(seed)
        self.program = np.zeros(6)  # the robot program's target offset from the start pose (m, rad)
        self.correction = np.zeros(6)  # total offset from the bridge's corrections, in controller units
        self.session: Session | None = None
        self.last_fault: tuple[int, str] = (0, "")
        self.faults_raised = 0
        self.clamped = 0
        self.idle_closed = 0  # connections closed for sending no HELLO within HELLO_TIMEOUT_S
        self.sessions_ended = 0
        self.replaced = 0  # CORRECTIONs overwritten by a newer one before a period applied them: lost motion
        self.states_sent = 0
        self.session_end = ""  # why the last session ended: STOP, a FAULT, the peer leaving, a test's disconnect
        self._cut = False  # the last applied increment was clamped
        self._seq = 0
        self._lock = threading.RLock()
        self._start = time.monotonic()
        self._stop = threading.Event()
        self.server = PeerServer("robot_controller", host, port, policy="refuse", on_connect=self._on_connect)
        self._clock = threading.Thread(target=self._run_clock, name="interpolation-clock", daemon=True)

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def period_s(self) -> float:
        return self.period_ticks * TICK_S

    def start(self) -> "RobotController":
        self.arm.advance(0.0)  # loads the compiled dynamics (~0.5 s in a fresh process) before the clock runs
        self.server.start()
        self._clock.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._clock.is_alive():
            self._clock.join(timeout=2.0)
        self.server.close()

    # ---------------------------------------------------------------- clock
    def _run_clock(self) -> None:
        deadline = time.monotonic()
        tick = 0
        while not self._stop.is_set():
            deadline += TICK_S
            delay = deadline - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            with self._lock:
                self.arm.command = self.program + np.array(mp.units_to_metres(self.correction))
                self.arm.advance(TICK_S)
            tick += 1
            if tick % self.period_ticks == 0:
                self._period(int(deadline * 1e9))

    def _period(self, tick_ns: int) -> None:
        self._serve_period()
        if self.on_period is not None:
            # The per-cycle output, right after the STATE, as the real controller's task does both at once
            # (rendering the profile first delayed the STATE by milliseconds). The arm has not moved since;
            # the edge is at the tick's time, however late this thread runs.
            self.on_period(tick_ns)

    def _serve_period(self) -> None:
        with self._lock:
            session = self.session
            if session is None:
                return
            session.periods += 1
            now = time.monotonic()
            if now - session.last_frame > session.bounds.watchdog_ms * 1e-3:
                self._fault(mp.FAULT_WATCHDOG, f"no frame for {now - session.last_frame:.3f} s")
                return
            limit = self.faults.disconnect_after_periods
            if limit and session.periods >= limit:
                self.faults.disconnect_after_periods = 0
                self._end_session("injected disconnect")
                return
            applied = self._apply(session)
            state = self._state(session)
        applied_at = time.time()
        self._deliver(state)
        if self.on_applied is not None:  # after the STATE: publishing it is slow, and the bridge is waiting
            self.on_applied(applied_at, applied)

    def _deliver(self, state: mp.Frame) -> None:
        """Send this period's STATE, unless a fault drops or delays it."""
        if self.faults.state_drop_fraction and self.rng.random() < self.faults.state_drop_fraction:
            return
        if self.faults.state_delay_s > 0:
            threading.Timer(self.faults.state_delay_s, self._send, args=(state,)).start()
        else:
            self._send(state)

    def _apply(self, session: Session) -> tuple[int, ...]:
        """The newest CORRECTION of the last period, clamped; none for 3 periods: hold still. Returns the
        increment applied (zeros when none was)."""
        if session.pending is None:
            session.periods_without += 1
            self._cut = False
            return (0,) * 6
        seq, correction = session.pending
        session.pending = None
        session.periods_without = 0
        step, cut = mp.clamp(correction.increment, session.bounds.max_step)
        total = self.correction + np.array(step)
        bound = np.array(session.bounds.max_offset)
        if np.any(np.abs(total) > bound):
            self._fault(mp.FAULT_LIMIT, f"total offset {total.tolist()} beyond {bound.tolist()}")
            return (0,) * 6
        self.correction = total
        self.clamped += int(cut)
        session.applied_seq = seq
        self._cut = cut
        return tuple(int(v) for v in step)

    def _state(self, session: Session) -> mp.Frame:
        status = mp.ARMED | (mp.HOLDING if session.periods_without >= HOLD_AFTER_PERIODS else 0)
        if self._cut:
            status |= mp.CLAMPED
        pose = mp.metres_to_units(self.arm.position)
        self._seq += 1
        return mp.Frame(self._seq, session.last_seq, mp.State(session.applied_seq, pose,
                                                              tuple(int(v) for v in self.correction), status, 0,
                                                              int((time.monotonic() - self._start) * 1e6)))

    def _send(self, frame: mp.Frame) -> None:
        if self.server.send(mp.encode(frame)):
            self.states_sent += 1

    # ---------------------------------------------------------------- session
    def _on_connect(self, conn: socket.socket) -> None:
        threading.Thread(target=self._read_loop, args=(conn,), name="controller-read", daemon=True).start()

    def _read_loop(self, conn: socket.socket) -> None:
        reader = mp.FrameReader()
        hello_by = time.monotonic() + HELLO_TIMEOUT_S
        armed_once = False
        while not self._stop.is_set():
            if not armed_once and time.monotonic() > hello_by:  # an idle peer must not hold the only slot
                with self._lock:
                    self.idle_closed += 1
                    self.session_end = f"no HELLO within {HELLO_TIMEOUT_S:g} s of connecting"
                break
            try:
                conn.settimeout(0.1)
                data = conn.recv(4096)
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                break
            if not data:
                break
            try:
                frames = reader.feed(data)
            except mp.MotoPlusProtocolError as exc:
                with self._lock:
                    self._fault(mp.FAULT_PROTOCOL, str(exc))
                break
            for frame in frames:
                with self._lock:
                    if not self._handle(frame):
                        break
                    armed_once = armed_once or self.session is not None
        with self._lock:
            if self.server.peer is conn:
                if self.session is not None:  # the peer went away: disarmed, holding still
                    self.session_end = "the bridge disconnected"
                    self.sessions_ended += 1
                self.session = None
                self.server.drop(conn)

    def _handle(self, frame: mp.Frame) -> bool:
        """One frame from the bridge (lock held); False when the session ended."""
        now = time.monotonic()
        body = frame.body
        if isinstance(body, mp.Hello):
            if self.session is not None:
                self._fault(mp.FAULT_PROTOCOL, "a second HELLO in one session (limits are set once, at arming)")
                return False
            if body.period_us != int(round(self.period_s * 1e6)):
                self._fault(mp.FAULT_PROTOCOL, f"HELLO asks for a {body.period_us} us period; this controller runs "
                                               f"{int(round(self.period_s * 1e6))} us")
                return False
            try:
                bounds = self.limits.session(body, int(round(self.period_s * 1e6)))
            except HelloRefused as exc:
                self._fault(mp.FAULT_LIMIT, str(exc))
                return False
            self.session = Session(body, bounds, now, frame.seq, now)
            self._seq += 1
            self._send(mp.Frame(self._seq, frame.seq, mp.State(0, mp.metres_to_units(self.arm.position),
                                                                tuple(int(v) for v in self.correction), mp.ARMED)))
            return True
        session = self.session
        if session is None:
            if isinstance(body, mp.Correction):
                self._fault(mp.FAULT_NOT_ARMED, "CORRECTION before HELLO")
                return False
            return True
        verdict = mp.sequence_verdict(session.last_seq, frame.seq)
        if verdict == "old":
            return True  # old or repeated: ignored
        if verdict == "gap":
            self._fault(mp.FAULT_SEQUENCE_GAP, f"sequence jumped from {session.last_seq} to {frame.seq}")
            return False
        session.last_seq, session.last_frame = frame.seq, now
        if isinstance(body, mp.Correction):
            self.replaced += int(session.pending is not None)
            session.pending = (frame.seq, body)
        elif isinstance(body, mp.Stop):
            self._end_session("STOP")
            return False
        elif isinstance(body, mp.Fault):
            self._fault(body.code, f"bridge reported: {body.text}")
            return False
        return True

    def _fault(self, code: int, text: str) -> None:
        """Latch: disarm, tell the bridge why, and close the session (lock held)."""
        self.faults_raised += 1
        self.last_fault = (code, text)
        ack = self.session.last_seq if self.session else 0
        self.session = None  # disarmed before the peer hears why
        self._seq += 1
        self.server.send(mp.encode(mp.Frame(self._seq, ack, mp.Fault(code, text))))
        self._end_session(f"FAULT {code}: {text}")

    def _end_session(self, reason: str) -> None:
        self.session_end = reason
        self.sessions_ended += 1
        self.session = None
        self.server.drop()
