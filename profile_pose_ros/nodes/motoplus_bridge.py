"""motoplus_bridge: `correction` (TwistStamped, base frame) -> one clamped Cartesian increment per
controller period over the MotoPlus protocol (docs/motoplus_protocol.md); `robot_state` and /diagnostics
out; services ~/start (arm) and ~/stop (STOP, disarm).

Thin glue around devices.motoplus_client.MotoPlusClient (its own socket thread, paced by the
controller's STATE). Each STATE's answer waits up to `answer_wait` periods for the correction computed from
that period's measurement, so a pose can reach the robot one period after its trigger (answering at once
sends the previous period's correction). A correction older than `max_age` (by its stamp: the profile's
trigger time), stamped more than `max_future` ahead, in another frame than base_frame, or received more
than max_age ago on this node's monotonic clock moves nothing; a period without a new correction sends
zero, never the last one again. A fault or a lost session disarms until ~/start; STOP goes out on every
shutdown path. In `mode: calibration` the same rules apply to profile_pose_calibrate's open-loop moves on
`~/calibration_move` instead, and `correction` moves nothing.
"""
from __future__ import annotations

import sys
import threading
import time
from collections import deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from std_srvs.srv import Trigger

from ..core.wire import motoplus_protocol as mp
from ..core.control.correction_spacing import CorrectionSpacing
from ..core.timing.freshness import describe_age, stamp_age_ok
from ..core.timing.latency_window import LatencyWindow
from ..core.timing.tick_clock import TickClock
from ..core.wire.pose_cdr import CdrFormatError, decode_twist_cdr, encode_pose_cdr, encode_twist_cdr
from ..core.model.transform import rotation_from_controller_angles
from ..devices.motoplus_client import ARMED, MotoPlusClient, SessionLimits
from .diagnostics import ERROR, OK, WARN, RefusalCounter, diagnostic_array
from .direct_input import DirectInput, ServedDirectly, spin
from .local_topics import LOOP_INPUT_QOS, LocalTopics, LoopOutput
from .parameters import Param, declare_all, updated
from .process_tuning import LOOP_SWITCH_INTERVAL_S, REALTIME_PARAMETERS
from .run import run_node

NODE_NAME = "motoplus_bridge"
FRAMES = {"base": mp.FRAME_BASE, "robot": mp.FRAME_ROBOT, "tool": mp.FRAME_TOOL, "user": mp.FRAME_USER}

PARAMETERS = [
    Param("host", "127.0.0.1", "Robot controller (MotoPlus application) address.", read_only=True),
    Param("port", 11000, "Robot controller port.", 1, 65535, read_only=True),
    Param("period", 0.012, "Controller period (s): 0.012 (83.3 Hz) or 0.004 (250 Hz); must match the controller.",
          0.004, 0.1, read_only=True),
    Param("max_step", [2e-4, 2e-4, 2e-4, 1e-3, 1e-3, 1e-3],
          "Per-cycle increment limit per axis x y z (m) rx ry rz (rad).", read_only=True),
    Param("max_offset", [5e-3, 5e-3, 5e-3, 2e-2, 2e-2, 2e-2],
          "Bound on the total offset from the start pose per axis (m, rad).", read_only=True),
    Param("watchdog", 0.5, "The controller ends the session after this long without a frame (s).", 0.05, 5.0,
          read_only=True),
    Param("max_age", 0.024, "A correction older than this (by its stamp: the trigger time) moves nothing (s). "
          "The robot stops within max_age + one period of losing its data: 2 periods keeps that within 3.",
          0.001, 1.0),
    Param("max_future", 0.002, "A correction stamped more than this ahead of this host's clock moves nothing (s): "
          "stamps are trigger times, in the past on a healthy cell; one from the future comes from a wrong clock "
          "or a rogue publisher.", 0.0, 0.1),
    Param("input_timeout", 0.5, "Armed, with no fresh correction for this long (the estimator, the driver or the "
          "compensator stopped, or their data went stale), the bridge sends STOP and stays disarmed until ~/start: "
          "a restarted node never moves the arm by itself (s).", 0.05, 5.0, read_only=True),
    Param("answer_wait", 0.5, "How long (in periods) a STATE's answer may wait for the correction measured at "
          "that STATE's trigger: it leaves as soon as that arrives, else with the newest one at this deadline. "
          "0 answers at once (the previous period's correction: a period more of loop delay). Past ~0.5 a late "
          "thread may miss the controller's next period (an answer later than 0.75 periods moves nothing).", 0.0, 0.7),
    Param("await_reply", False, "Hold each STATE's answer (up to answer_wait periods) for the first correction that "
          "arrives after the STATE, instead of the one measured at its trigger: for a compensator that answers the "
          "controller's clock (its period_clock robot_state), whose correction is a reply to this STATE's "
          "robot_state, stamped with a pose from before it. Each such correction moves the arm by one period of "
          "its velocity (corrections more than twice a period are still taken for their stamps' spacing).",
          read_only=True),
    Param("frame", "base", "Cartesian frame of the increments: base, robot, tool or user.", read_only=True),
    Param("base_frame", "base", "frame_id of robot_state."),
    Param("mode", "loop", "loop: corrections from the compensator (`correction`). calibration: open-loop moves "
          "from profile_pose_calibrate (`~/calibration_move`, the same TwistStamped velocities and checks) and "
          "none from `correction`, the offset bound narrowed to calibration_envelope.", read_only=True),
    Param("calibration_envelope", [0.005, 0.005, 0.005, 0.04, 0.04, 0.04], "In calibration mode, the bound on the "
          "total offset from the start pose per axis (m, rad), instead of max_offset.", read_only=True),
    Param("arm_on_start", False, "Arm (send HELLO) as soon as connected, without ~/start.", read_only=True),
    Param("diagnostics_period", 1.0, "Period of /diagnostics (s).", 0.02, 60.0, read_only=True),
    *REALTIME_PARAMETERS,
]


MODES = {"loop": "correction", "calibration": "~/calibration_move"}  # mode -> the one topic that moves the arm


def limits_from(v: dict) -> SessionLimits:
    if v["frame"] not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, not {v['frame']!r}")
    if v["mode"] not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, not {v['mode']!r}")
    for name in ("max_step", "max_offset", "calibration_envelope"):
        if len(v[name]) != 6 or min(v[name]) <= 0:
            raise ValueError(f"{name} needs six positive values (x y z rx ry rz)")
    # The loop's bound, or the calibration's: its turns are larger than any the loop should make. Either way
    # the controller's own bound still holds (a HELLO cannot widen it).
    offset = v["calibration_envelope"] if v["mode"] == "calibration" else v["max_offset"]
    return SessionLimits(v["period"], tuple(v["max_step"]), tuple(offset), v["watchdog"], FRAMES[v["frame"]])


class MotoPlusBridgeNode(RefusalCounter, Node):
    def __init__(self, local: LocalTopics | None = None, **kwargs) -> None:
        """local: the composed nodes' topics (cell_container): corrections arrive in the compensator's thread."""
        super().__init__(NODE_NAME, **kwargs)
        # Process-wide: whatever else runs in this process (an executor busy with corrections, a test
        # harness), the socket thread must get the GIL within a fraction of the period.
        v = self.values = declare_all(self, PARAMETERS)
        self.limits = limits_from(v)
        self._lock = threading.Lock()
        # (stamp ns, velocity, monotonic receive time) of the corrections since the last increment
        self._velocities: list[tuple[int, np.ndarray, float]] = []
        self._spacing = CorrectionSpacing(self.limits.period_s)  # what time each correction stands for
        self._latest: tuple[int, np.ndarray] | None = None  # (stamp ns, velocity): what the answer waits for
        self._latest_arrival = -np.inf  # time.monotonic() when it came
        self._state_arrived = -np.inf  # time.monotonic() when the newest STATE came
        self._tick_clock = TickClock()  # the controller's time_us on this host's clock, for robot_state's stamp
        self.refused = {"frame": 0, "future": 0, "stale": 0, "not_finite": 0, "malformed": 0}
        self._fresh = threading.Condition(self._lock)  # a correction arrived
        self.latency = LatencyWindow("trigger_to_send_ms")  # the newest correction's trigger -> its increment sent
        self._sent: list[tuple[int, tuple[int, ...]]] = []  # increments sent, not yet published
        self._lost: list[bytes] = []  # lost_increment messages, serialized, to publish
        self._ticks: deque[tuple[int, float]] = deque(maxlen=64)  # (time_us, host tick) of the recent STATEs
        self.stale_periods = 0
        # armed periods whose answer carried a correction from a pose at most one period old when it left
        # (over the node's life, beside the armed periods): what the arm feels of the loop
        self.answered_in_period = 0
        self.state_pub = self.create_publisher(PoseStamped, "robot_state", 10)
        # composed with the compensator: each STATE reaches it in this thread, and its reply comes back the same way
        self.state_out = LoopOutput(self.state_pub, local if local is not None and local.carries("robot_state")
                                    else None, self.get_logger())
        self.increment_pub = self.create_publisher(TwistStamped, "~/increment", 100)
        # composed with the compensator, a loss reaches its model in this thread before the next STATE's law runs
        self.lost_out = LoopOutput(self.create_publisher(TwistStamped, "lost_increment", 100),
                                   local if local is not None and local.carries("lost_increment") else None,
                                   self.get_logger())
        # Corrections and the sent-increment note are served straight from their wait set (direct_input.py):
        # the socket thread is waiting for each correction, and through the executor each waited behind its
        # per-wake-up bookkeeping, about a millisecond here.
        direct = ServedDirectly()
        self._sent_guard = self.create_guard_condition(self._publish_increments, callback_group=direct)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.direct_input = DirectInput(None, self.context, guard=self._sent_guard)
        if local is not None and local.carries("correction") and v["mode"] == "loop":
            local.take(self.resolve_topic_name(MODES[v["mode"]]), self._on_correction)
        else:
            corrections = self.create_subscription(TwistStamped, MODES[v["mode"]], self._on_correction, LOOP_INPUT_QOS,
                                                   callback_group=direct, raw=True)  # read by core/wire/pose_cdr.py
            self.direct_input.add(corrections, self._on_correction)
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/stop", self._on_stop)
        logger = self.get_logger()
        self.client = MotoPlusClient(v["host"], v["port"], self.limits, self._increment, self._on_state,
                                     max_age_s=lambda: self.values["max_age"],
                                     max_future_s=lambda: self.values["max_future"],
                                     input_timeout_s=v["input_timeout"],
                                     log=lambda text: logger.warn(text, throttle_duration_sec=1.0),
                                     on_sent=self._on_sent, await_correction=self._await_correction,
                                     on_lost=self._on_lost)
        if v["arm_on_start"]:
            self.client.arm()
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.client.start()
        logger.info(f"robot controller tcp://{v['host']}:{v['port']}, period {v['period'] * 1e3:.1f} ms, "
                    f"{v['mode']} mode (moved by {self.resolve_topic_name(MODES[v['mode']])}); "
                    f"{'arming' if v['arm_on_start'] else 'disarmed until ~/start'}")

    # ---------------------------------------------------------------- corrections
    def _on_correction(self, serialized: bytes) -> None:
        received = time.monotonic()
        try:
            stamp, frame_id, velocity = decode_twist_cdr(serialized)
        except CdrFormatError as exc:
            self._refuse("malformed", f"malformed correction ignored: {exc}")
            return
        if frame_id != self.values["base_frame"]:
            self._refuse("frame", f"correction in frame '{frame_id}' ignored (base_frame is "
                                  f"'{self.values['base_frame']}')")
            return
        if not np.all(np.isfinite(velocity)):
            self._refuse("not_finite", "correction with NaN or inf ignored")
            return
        age = time.time() - stamp * 1e-9
        if not stamp_age_ok(age, self.values["max_age"], self.values["max_future"]):
            self._refuse("future" if age < 0 else "stale", "correction ignored: "
                         + describe_age(age, self.values["max_age"], self.values["max_future"]))
            return
        with self._lock:
            self._velocities.append((stamp, velocity, received))
            self._spacing.add(stamp * 1e-9)
            self._latest, self._latest_arrival = (stamp, velocity), received
            self._fresh.notify()

    def _await_correction(self, state_wall_time: float) -> None:
        """Socket thread: hold this STATE's answer until a correction from this period's measurement is here
        (triggered less than half a period before the STATE arrived), for at most answer_wait periods.
        Newer than the last answer is not enough: a chain that ran one period late would stay one period late."""
        period = self.limits.period_s
        deadline = state_wall_time + self.values["answer_wait"] * period
        since_ns = (state_wall_time - 0.5 * period) * 1e9
        reply, state_arrived = self.values["await_reply"], self._state_arrived
        with self._fresh:
            while (self._latest_arrival < state_arrived if reply
                   else self._latest is None or self._latest[0] < since_ns):
                remaining = deadline - time.time()
                if remaining <= 0.0:
                    return
                self._fresh.wait(remaining)

    def _increment(self, now: float) -> tuple[np.ndarray, float] | None:
        """This period's move (socket thread): the motion the corrections that arrived since the last answer
        stand for (core/control/correction_spacing.py), of those still fresh by their stamps (two-sided) and by
        their arrival on this node's monotonic clock, with the newest one's trigger time. None (a zero
        increment) when there is none: a correction moves the arm once only, so a dead compensator's last
        word is not repeated."""
        mono = time.monotonic()
        with self._lock:  # the spacing is read under the lock the executor thread adds to it under
            received, self._velocities = self._velocities, []
            fresh = [(stamp, velocity) for stamp, velocity, arrived in received
                     if self._fresh_at(stamp, arrived, now, mono)]
            if not fresh:
                self.stale_periods += 1
                return None
            move = self._spacing.increment([velocity for _, velocity in fresh], answers=self.values["await_reply"])
        return move, max(stamp for stamp, _ in fresh) * 1e-9

    def _fresh_at(self, stamp_ns: int, arrived: float, now: float, now_monotonic: float) -> bool:
        """A correction may still move the arm: its stamp within [-max_future, max_age] of now (wall) and its
        arrival within max_age of now_monotonic (this node's clock, which no wall-clock step moves)."""
        v = self.values
        return (now_monotonic - arrived <= v["max_age"]
                and stamp_age_ok(now - stamp_ns * 1e-9, v["max_age"], v["max_future"]))

    def _on_sent(self, units: tuple[int, ...], stamp: float, sent: float) -> None:
        """Socket thread, right after a moving CORRECTION left: note it; the executor publishes it.
        Publishing here would make the thread that must answer every STATE within the period wait for the GIL."""
        self.latency.add(sent - stamp)
        self.answered_in_period += sent - stamp <= self.limits.period_s
        with self._lock:
            self._sent.append((int(round(stamp * 1e9)), units))
        self._sent_guard.trigger()

    def _on_lost(self, units: np.ndarray, answered_us: int) -> None:
        """Socket thread: the controller never applied `units` of the answer to its STATE at answered_us; the
        executor publishes it (lost_increment), stamped with that STATE's tick, as robot_state was."""
        tick = next((host for us, host in reversed(self._ticks) if us == answered_us), None)
        if tick is None:
            return  # older than the STATEs remembered: the compensator could not place it
        serialized = encode_twist_cdr(mp.units_to_metres(units), int(round(tick * 1e9)), self.values["base_frame"])
        self.lost_out.hand_over(serialized)
        with self._lock:
            self._lost.append(serialized)
        self._sent_guard.trigger()

    def _publish_increments(self) -> None:
        """`~/increment`: each increment sent (m and rad this period, after clamping), stamped with the
        trigger time of the newest correction in it; `lost_increment`: what the controller never applied."""
        with self._lock:
            sent, self._sent = self._sent, []
            lost, self._lost = self._lost, []
        frame = self.values["base_frame"]
        for stamp_ns, units in sent:  # serialized here (core/wire/pose_cdr.py): 250 a second at the 4 ms clock
            self.increment_pub.publish(encode_twist_cdr(mp.units_to_metres(units), stamp_ns, frame))
        for serialized in lost:
            self.lost_out.publish(serialized)

    def _on_state(self, state: mp.State, host_time: float) -> None:
        """robot_state: the tool's pose in the base frame as the controller reports it (its Rx Ry Rz angles),
        stamped when the controller sampled it (its tick on this host's clock), not when this thread read it."""
        self._state_arrived = time.monotonic()  # before the publish: a reply can come before it returns
        pose = np.array(mp.units_to_metres(state.pose))
        tick = self._tick_clock.host_time(state.time_us, host_time)
        self._ticks.append((state.time_us, tick))
        serialized = encode_pose_cdr(rotation_from_controller_angles(pose[3:]), pose[:3], int(tick * 1e9),
                                     self.values["base_frame"])
        self.state_out.publish(serialized)
        self.state_out.hand_over(serialized)

    def pump(self, timeout_sec: float = 0.0) -> int:
        """Handle queued corrections and sent increments (see direct_input.py); spin() or a test harness calls this."""
        return self.direct_input.pump(timeout_sec)

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """max_age, answer_wait, base_frame at run time (ranges checked by their descriptors; the rest is
        read-only). The socket thread reads self.values afresh each period: one dict swap, never half of one."""
        self.values, _ = updated(self.values, parameters, lambda values: None)  # nothing to rebuild
        return SetParametersResult(successful=True)

    # ---------------------------------------------------------------- services
    def _on_start(self, _request, response):
        """Arm only while the loop is live: armed without fresh corrections, the session would end again
        after input_timeout (a node restarted a moment ago, or one whose subscription has not matched)."""
        with self._lock:
            latest, arrived = self._latest, self._latest_arrival
        if latest is None or not self._fresh_at(latest[0], arrived, time.time(), time.monotonic()):
            response.success = False
            response.message = "not arming: no fresh correction (is the estimator, driver and compensator running?)"
            return response
        self.client.arm()
        response.success = True
        response.message = f"arming (state: {self.client.state})"
        return response

    def _on_stop(self, _request, response):
        self.client.disarm("~/stop")
        response.success = True
        response.message = "STOP sent; disarmed"
        return response

    # ---------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        c = self.client
        monitor = c.monitor
        if monitor.total_violations:
            level, message = ERROR, (f"{c.state}; the safety monitor stopped {monitor.total_violations} increments "
                                     f"(last: {monitor.last_violation})")
        elif c.state == ARMED:
            level, message = OK, "armed, correcting"
            if self.stale_periods:
                level, message = WARN, f"armed; {self.stale_periods} periods with a stale correction (zero sent)"
        elif c.last_fault[0]:
            level, message = ERROR, f"{c.state}; last fault {c.last_fault[0]}: {c.last_fault[1]}"
        else:
            level, message = WARN, f"{c.state}: not moving the robot ({c.last_error or 'not armed'})"
        values = {"state": c.state, "states": c.counters.states, "corrections": c.counters.corrections,
                  "zero_corrections": c.counters.zero_corrections, "late_answers": c.counters.late_answers,
                  "lost_increments": c.counters.lost_increments, "input_lost": c.counters.input_lost,
                  "clamped": c.counters.clamped,
                  "offset_limited": c.counters.offset_limited, "faults": c.counters.faults,
                  "connections": c.counters.connections, "safety_checked": monitor.checked,
                  "safety_violations": monitor.total_violations,
                  **{f"safety_{name}": count for name, count in monitor.violations.items()},
                  "last_error": c.last_error or "none", "stale_periods": self.stale_periods,
                  "armed_periods": c.counters.corrections, "answered_within_a_period": self.answered_in_period,
                  **{f"refused_{why}": count for why, count in self.refused.items()}}
        if c.last_state is not None:
            values.update({"controller_status": c.last_state.status, "echoed_seq": c.last_state.echoed_seq,
                           "total_offset_um": list(c.last_state.offset[:3])})
        values.update(self.latency.report())
        self.stale_periods = 0
        self.diagnostics_pub.publish(diagnostic_array(self, "robot",
                                                      f"tcp://{c.host}:{c.port}", level, message, values))

    def destroy_node(self) -> None:
        self.client.stop()  # STOP first, on every shutdown path
        super().destroy_node()


def main(args=None) -> int:
    return run_node(MotoPlusBridgeNode, NODE_NAME, args, startup_errors=(ValueError,),
                    spin=lambda executor, node, stop: spin(executor, node.direct_input, stop),
                    switch_interval=LOOP_SWITCH_INTERVAL_S)


if __name__ == "__main__":
    sys.exit(main())
