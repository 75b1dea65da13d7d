"""The bridge's side of the MotoPlus protocol without ROS: a socket thread paced by the controller.

Disarmed until arm() is called; then HELLO, and for every STATE exactly one CORRECTION with the
increment `increment(now)` returns (clamped per cycle and to what is left of the total offset bound, here as
well as on the controller), checked last by core.safety.SafetyMonitor. The answer goes out when
`await_correction(arrival time)` returns: the bridge holds it until the correction measured at this
STATE's trigger arrives (or a deadline within the period), so that correction moves the robot at the next
period instead of waiting for the next STATE and a period more. Any fault, protocol error or
disconnect disarms it, and so does a correction stream that stops for input_timeout (the estimator or
the compensator died or stalls): only another arm() re-arms, so neither a fault nor a restarted node
moves the robot again without the operator.
It reconnects with back-off; stop() sends STOP.
"""
from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.wire import motoplus_protocol as mp
from ..core.control.increment_ledger import IncrementLedger
from ..core.control.safety import SafetyMonitor

# disarmed: no session wanted, no connection (the controller closes one that does not arm within a second);
# disconnected: a session wanted, the connection not (yet) up; then connected, arming, armed.
DISARMED, DISCONNECTED, CONNECTED, ARMING, ARMED = "disarmed", "disconnected", "connected", "arming", "armed"
# An answer leaving later than this share of the period after its STATE carries no motion: it could reach
# the controller after its next period, be applied a period later, and so move on a correction older than
# max_age + one period (the stop bound). The bridge's hold (answer_wait <= 0.7) leaves before it.
LATE_ANSWER = 0.75
STOP_DRAIN_S = 0.25  # s: at most this long reading the controller's last frames after STOP (it closes on STOP)


@dataclass(frozen=True)
class SessionLimits:
    period_s: float = 0.012
    max_step: tuple[float, ...] = (2e-4, 2e-4, 2e-4, 1e-3, 1e-3, 1e-3)  # per cycle, m and rad
    max_offset: tuple[float, ...] = (5e-3, 5e-3, 5e-3, 2e-2, 2e-2, 2e-2)  # total, m and rad
    watchdog_s: float = 0.5
    frame: int = mp.FRAME_BASE

    def hello(self) -> mp.Hello:
        return mp.Hello(int(round(self.period_s * 1e6)), mp.metres_to_units(self.max_step),
                        mp.metres_to_units(self.max_offset), int(round(self.watchdog_s * 1e3)), self.frame)


@dataclass
class BridgeCounters:
    states: int = 0
    corrections: int = 0
    zero_corrections: int = 0  # sent because the correction was stale or missing, or the answer late
    late_answers: int = 0  # answers that left too late in the period to move the robot
    clamped: int = 0
    offset_limited: int = 0  # cut to what is left of the total offset bound
    faults: int = 0
    connections: int = 0
    lost_increments: int = 0  # moving answers the controller replaced before applying them (IncrementLedger)
    input_lost: int = 0  # sessions ended because the corrections stopped coming (re-armed by hand only)


class MotoPlusClient:
    def __init__(self, host: str, port: int, limits: SessionLimits,
                 increment: Callable[[float], tuple[np.ndarray, float] | None],
                 on_state: Callable[[mp.State, float], None], max_age_s: Callable[[], float] = lambda: 0.024,
                 max_future_s: Callable[[], float] = lambda: 0.002, input_timeout_s: float = 0.5,
                 log: Callable[[str], None] = print, backoff_min: float = 0.1, backoff_max: float = 1.0,
                 on_sent: Callable[[tuple[int, ...], float, float], None] | None = None,
                 await_correction: Callable[[float], None] | None = None,
                 on_lost: Callable[[np.ndarray, int], None] | None = None) -> None:
        """increment(now, the wall time of this STATE's answer): (this period's move in m and rad, the
        trigger time of the correction it comes from), or None to hold still; max_age_s, max_future_s: the
        monitor's limits on a stamp's age (two-sided);
        on_sent(units, trigger time, wall time just after the send): each moving CORRECTION as it left;
        await_correction(wall time the STATE arrived): returns when the answer should go out."""
        self.host, self.port, self.limits = host, port, limits
        self.input_timeout_s = input_timeout_s
        self._last_input = 0.0  # monotonic: the last period answered from a fresh correction (or the arming)
        self.monitor = SafetyMonitor(mp.metres_to_units(limits.max_step), mp.metres_to_units(limits.max_offset),
                                     max_age_s, max_future_s)
        self.rounding = mp.CarriedRounding()  # to units, each remainder carried into the next increment
        self.on_sent = on_sent
        self.await_correction = await_correction
        self.on_lost = on_lost  # (units the controller never applied, time_us of the STATE their answer was for)
        self.increment, self.on_state, self.log = increment, on_state, log
        self.backoff_min, self.backoff_max = backoff_min, backoff_max
        self.state = DISARMED
        self.last_error = ""
        self.last_fault: tuple[int, str] = (0, "")
        self.last_state: mp.State | None = None
        self.last_state_time = 0.0
        self.counters = BridgeCounters()
        self.ledger = IncrementLedger()
        self._seq = 0
        self._peer_seq = 0
        self._sock: socket.socket | None = None
        self._send_lock = threading.RLock()  # re-entered by _send_stop, which sends while holding it
        self._stop_sent = False  # on this connection: its close drains (see _close)
        self._arm_requested = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="motoplus-client", daemon=True)

    def start(self) -> "MotoPlusClient":
        self._thread.start()
        return self

    @property
    def armed(self) -> bool:
        return self.state == ARMED

    def arm(self) -> None:
        """Ask for a session; sends HELLO now if connected, else on the next connection."""
        self.monitor.rearmed()
        self.rounding.reset()
        self._arm_requested.set()

    def disarm(self, reason: str) -> None:
        """Send STOP and hold still until arm() is called again. The state changes before STOP leaves, so
        the socket thread reads the controller's closing the session as the end it asked for, not a loss."""
        self._arm_requested.clear()
        if self.state in (ARMED, ARMING):
            self._send_stop()
        self.log(f"disarmed: {reason}")

    def stop(self) -> None:
        """STOP to the controller, then close (every shutdown path ends here). The close is graceful: STOP
        and then our FIN, and the socket thread reads what the controller still sends until it closes too.
        Closing with its STATEs unread would make the kernel send a reset, and a controller that had not
        yet read STOP would lose it to the reset and see a dropped connection instead of the end asked for."""
        self._arm_requested.clear()
        self._send_stop()
        self._finish_sending()
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._close()

    # ---------------------------------------------------------------- socket thread
    def _run(self) -> None:
        backoff = self.backoff_min
        while not self._stop.is_set():
            if not self._arm_requested.is_set():  # connect only to arm: an idle client would hold the
                self.state = DISARMED              # controller's one slot
                self._arm_requested.wait(0.05)
                continue
            self.state = DISCONNECTED
            try:
                sock = socket.create_connection((self.host, self.port), timeout=1.0)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._sock = sock
                self.counters.connections += 1
                self.state = CONNECTED
                backoff = self.backoff_min
                self._session(sock)
            except (OSError, mp.MotoPlusProtocolError) as exc:
                self.last_error = f"tcp://{self.host}:{self.port}: {exc}"
            except Exception as exc:  # noqa: BLE001 - a bug here must disarm, not kill the thread
                self.last_error = f"unexpected {exc!r}"
                self.log(f"bridge socket thread: {self.last_error}")
            if self.state in (ARMED, ARMING):  # a session lost without STOP is a fault: re-arm by hand
                self._arm_requested.clear()
                self.monitor.fault()
                self.counters.faults += 1
                self.log(f"session lost ({self.last_error}); disarmed until ~/start")
            self._close()
            self.state = DISCONNECTED if self._arm_requested.is_set() else DISARMED
            if self._stop.is_set():
                return
            self._stop.wait(backoff)
            backoff = min(2 * backoff, self.backoff_max)

    def _session(self, sock: socket.socket) -> None:
        reader = mp.FrameReader()
        sock.settimeout(0.05)
        while not self._stop.is_set():
            if not self._arm_requested.is_set() and self.state == CONNECTED:
                return  # disarmed (STOP sent, or the controller's FAULT): leave the slot free
            if self._arm_requested.is_set() and self.state == CONNECTED:
                self.state = ARMING
                self._send(self.limits.hello())
            try:
                data = sock.recv(4096)
            except (TimeoutError, socket.timeout):
                if self.state == ARMED and time.monotonic() - self.last_state_time > self.limits.watchdog_s:
                    raise ConnectionError(f"no STATE for {self.limits.watchdog_s} s")
                continue
            if not data:
                raise ConnectionError("the controller closed the connection")
            frames = reader.feed(data)
            for k, frame in enumerate(frames):
                self._peer_seq = frame.seq
                self._handle(frame, behind=any(isinstance(f.body, mp.State) for f in frames[k + 1:]))

    def _handle(self, frame: mp.Frame, behind: bool = False) -> None:
        """behind: a newer STATE is already here, so this one is answered at once (this thread was late)."""
        body = frame.body
        now = time.monotonic()
        if isinstance(body, mp.State):
            self.counters.states += 1
            self.last_state, self.last_state_time = body, now
            arrived = time.time()
            if self.state == ARMED:  # before on_state: a composed compensator's law for this STATE knows of it
                self._note_losses(body)
            self.on_state(body, arrived)
            if self.state == ARMING and body.status & mp.ARMED:
                self.state = ARMED
                self._last_input = now
                self.ledger.reset(body.offset)
                return  # the arming STATE: the first CORRECTION answers the next one
            if self.state == ARMED:
                if self.await_correction is not None and not behind:
                    self.await_correction(arrived)
                if self.state == ARMED:  # not stopped (~/stop) while it waited
                    self._correct(arrived)
        elif isinstance(body, mp.Fault):
            self.last_fault = (body.code, body.text)
            self.last_error = f"controller FAULT {body.code}: {body.text}"
            self.counters.faults += 1
            self._arm_requested.clear()
            self.monitor.fault()
            self.state = CONNECTED
            self.log(self.last_error)
        elif isinstance(body, mp.Stop):
            self._arm_requested.clear()
            self.state = CONNECTED

    def _note_losses(self, state: mp.State) -> None:
        """Counted and told (on_lost: the compensator's model then counts what the controller applied), not
        resent: the loop makes the loss up itself, and resending it as well corrected twice (tried: the held
        arm wandered by ~50 um)."""
        lost = self.ledger.state(state.echoed_seq, state.offset)
        if np.any(lost):
            self.counters.lost_increments += 1
            if self.on_lost is not None and self.ledger.lost_answered is not None:
                self.on_lost(lost, self.ledger.lost_answered)

    def _correct(self, state_arrived: float) -> None:
        now = time.time()
        late = now - state_arrived > LATE_ANSWER * self.limits.period_s
        move = None if late else self.increment(now)
        units, stamp = (0,) * 6, None
        if late:  # it may reach the controller after its next period and move the robot a period later
            self.counters.late_answers += 1
        if move is None:
            self.counters.zero_corrections += 1
        else:
            step, stamp = move
            units = self.units_for(step)
            self._last_input = time.monotonic()
        offset = self.last_state.offset if self.last_state is not None else None
        broken = self.monitor.check(units, self.state == ARMED, stamp, now, offset)
        if broken:
            units, stamp = (0,) * 6, None
            self.rounding.reset()
        if self._send(mp.Correction(units, self.limits.frame)) and stamp is not None and self.on_sent is not None:
            self.on_sent(units, stamp, time.time())
        self.counters.corrections += 1
        if broken:
            self.monitor.fault()
            self.disarm(f"safety monitor: {self.monitor.last_violation} (sent zero instead)")
        elif time.monotonic() - self._last_input > self.input_timeout_s and self.state == ARMED:
            self.counters.input_lost += 1
            self.monitor.fault()
            self.last_error = (f"no fresh correction for {self.input_timeout_s:.2f} s (estimate or compensator "
                               "stopped); ~/start to re-arm")
            self.disarm(self.last_error)

    def units_for(self, step) -> tuple[int, ...]:
        """A period's step (m, rad) as the increment to send: rounded with the carried remainder, clamped,
        and cut to the offset bound. A step beyond twice the clamp is cut first: it is clamped anyway, and a
        finite but absurd one (a rogue correction of 1e300 m/s) must not overflow the conversion."""
        bound = 2.0 * np.asarray(self.limits.max_step, dtype=float)
        return self._limit(self.rounding(np.clip(np.asarray(step, dtype=float), -bound, bound)))

    def _limit(self, units: tuple[int, ...]) -> tuple[int, ...]:
        """Clamped per cycle, then to what is left of the total offset bound (the controller would FAULT)."""
        units, cut = mp.clamp(units, mp.metres_to_units(self.limits.max_step))
        self.counters.clamped += int(cut)
        if self.last_state is None:
            return units
        bound = mp.metres_to_units(self.limits.max_offset)
        limited = tuple(int(np.clip(u, -b - o, b - o)) for u, o, b in zip(units, self.last_state.offset, bound))
        self.counters.offset_limited += int(limited != units)
        return limited

    def _send(self, body: mp.Body) -> bool:
        with self._send_lock:
            sock = self._sock
            if sock is None:
                return False
            self._seq += 1
            try:
                sock.sendall(mp.encode(mp.Frame(self._seq, self._peer_seq, body)))
                if isinstance(body, mp.Correction):
                    self.ledger.sent(self._seq, body.increment,
                                     self.last_state.time_us if self.last_state is not None else 0)
                return True
            except OSError as exc:
                self.last_error = f"send: {exc}"
                return False

    def _send_stop(self) -> None:
        """STOP, with the state changed under the send lock: the socket thread leaves a disarmed session
        (state CONNECTED) and closes the socket, and had it seen the state before STOP left, it would have
        closed first: STOP would find no socket, and the controller, its STATEs unread at the close, a reset
        instead of the end asked for."""
        with self._send_lock:
            if self.state in (ARMED, ARMING):
                self.state = CONNECTED  # before STOP leaves: the close that follows is the end asked for
            self._stop_sent = self._send(mp.Stop()) or self._stop_sent

    def _finish_sending(self) -> None:
        """Our FIN after everything sent so far (the controller reads STOP, then the end of the stream)."""
        with self._send_lock:
            if self._sock is not None:
                try:
                    self._sock.shutdown(socket.SHUT_WR)
                except OSError:
                    pass

    def _close(self) -> None:
        """Close the socket. After our STOP, first read (and drop) what the controller still sends, until
        it closes its side or STOP_DRAIN_S passes, so the close is a FIN and not a reset."""
        with self._send_lock:
            sock, self._sock = self._sock, None
            drain_s, self._stop_sent = (STOP_DRAIN_S if self._stop_sent else 0.0), False
        if sock is None:
            return
        try:
            deadline = time.monotonic() + drain_s
            while (left := deadline - time.monotonic()) > 0:
                sock.settimeout(left)
                if not sock.recv(4096):
                    break
        except OSError:
            pass
        finally:
            sock.close()
