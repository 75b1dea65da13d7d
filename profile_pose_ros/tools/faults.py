"""profile_pose faults: the faults a factory has, injected into the running closed loop on the simulated cell
(sim_cell -> profiler_driver -> pose_estimator -> pd_compensator -> motoplus_bridge, each its own process),
with what the safety invariants saw, the time to a safe stop and the time to recover, per fault.

Each fault hits mid-motion (the reference has just stepped 0.5 mm), is held for a second, then cleared the
way it would be in a cell: the fault goes away by itself, a killed node is restarted, and after a fault that
ended the robot session the operator re-arms (~/start). The ground truth of what the robot was told is
sim_cell's /sim/robot_increment (what its controller applied each armed period). Checked from it:
no increment above the clamp; no motion without a fresh pose (no moving correction computed from a pose
triggered within max_age + one period before it); no session between a session-ending fault and the re-arm; no controller FAULT for the offset bound;
and, from /sim/ground_truth, no pose far from the truth (a damaged profile must never give a pose).
Beside these, the bridge's own monitor (its safety_* diagnostics). Safe stop: from the injection to the
last increment that moved the robot; it must be within 3 control periods for the faults that take away
the data or the session.
"""
from __future__ import annotations

import argparse
import copy
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.estimation.result import REFINE_MODELS
from ..nodes.messages import stamp_ns, twist_vector
from ..nodes.motoplus_bridge import PARAMETERS as BRIDGE_PARAMETERS
from ..nodes.parameters import defaults
from .config_files import CELL_CONTROL_LAW, add_control_law_option
from .experiment import Experiment
from .graph import Graph
from .report import nearest_stamp, run_dir, table, write_json

STEP_M = 5e-4  # the reference step the fault hits in the middle of
MID_MOTION_S = 0.06
HOLD_S = 1.0
SETTLE_S = 1.0
BAD_POSE_M = 1e-3  # a wrong pose, not noise: the shipped gauge's weak y axis has ~75 um std, its worst glint poses ~0.35 mm
STOP_PERIODS = 3
TRUTH_MATCH_NS = 1_500_000  # under half the shortest trigger period (4 ms)
_DEFAULTS = defaults(BRIDGE_PARAMETERS)


# The controller's apply time and the poses' stamps are read in different processes: on a saturated 2-core
# machine those readings lag the events by a few ms (a 2 ms allowance gave false stale-motion counts).
SCHEDULING_SLACK_S = 0.005
# An episode is judged up to its end time, after waiting this long more: the increment the controller
# applied just before the end and the correction behind it come from different processes, and judging
# before the correction had arrived counted a false stale motion.
IN_FLIGHT_S = 0.2
# A pose counts as "during the fault" when its stamp is this much inside the fault's window: a profile
# triggered just before the injection carries the driver's trigger stamp (seen ~5 ms off on a saturated
# machine), and sim_cell applies a fault to a frame after rendering it, so a profile triggered a few ms
# before the fault cleared can still be sent.
STAMP_SLACK_S = 0.010


@dataclass(frozen=True)
class Fault:
    name: str
    inject: Callable[["FaultRun"], None]
    clear: Callable[["FaultRun"], None]
    must_stop: bool  # it takes away the data or the session: the robot must stop within STOP_PERIODS
    rearm: bool = False  # it ends the robot session: the operator re-arms once it has cleared
    input_lost: bool = False  # it stops the corrections: the bridge ends the session after input_timeout
    hold_s: float = HOLD_S  # how long the fault lasts before it is cleared
    check: Callable[["FaultRun"], str] | None = None  # a fault's own expectation: "" if met, else what went wrong
    session_end: str = ""  # how the controller must see the session end, if it does (e.g. STOP)


def _sim(**values) -> Callable[["FaultRun"], None]:
    return lambda run: run.graph.set_parameters("sim_cell", values)


FAULTS = (
    Fault("controller ends the session mid-motion", _sim(disconnect_after_periods=1), lambda run: None,
          must_stop=True, rearm=True),
    Fault("STATE 30 ms late", _sim(state_delay_ms=30.0), _sim(state_delay_ms=0.0), must_stop=False),
    Fault("half the STATEs dropped", _sim(state_drop_fraction=0.5), _sim(state_drop_fraction=0.0), must_stop=False),
    Fault("profiler stalls (no frames)", _sim(drop_fraction=1.0), _sim(drop_fraction=0.0), must_stop=True,
          rearm=True, input_lost=True),
    Fault("every profiler frame with a flipped bit", _sim(corrupt_fraction=1.0, corrupt_mode="flip"),
          _sim(corrupt_fraction=0.0, corrupt_mode="mixed"), must_stop=True, rearm=True, input_lost=True),
    Fault("30 % of profiler frames damaged (mixed)", _sim(corrupt_fraction=0.3), _sim(corrupt_fraction=0.0),
          must_stop=False),
    Fault("profiler connection closed every 20 frames", _sim(close_after_frames=20), _sim(close_after_frames=0),
          must_stop=False),
    Fault("glints on 2 % of points", _sim(spike_fraction=0.02), _sim(spike_fraction=0.0), must_stop=False),
    Fault("trigger MCU silent", _sim(mcu_silent=True), _sim(mcu_silent=False), must_stop=True, rearm=True,
          input_lost=True),
    Fault("pose_estimator SIGKILL, restarted", lambda run: run.graph.kill("pose_estimator"),
          lambda run: run.graph.restart("pose_estimator"), must_stop=True, rearm=True, input_lost=True),
    Fault("motoplus_bridge SIGKILL, restarted", lambda run: run.graph.kill("motoplus_bridge"),
          lambda run: run.restart_bridge(), must_stop=True, rearm=True),
    Fault("motoplus_bridge SIGTERM, restarted", lambda run: run.graph.kill("motoplus_bridge", signal.SIGTERM),
          lambda run: run.restart_bridge(), must_stop=True, rearm=True, session_end="STOP"),
    Fault("CPU overload (3 busy processes)", lambda run: run.load(3), lambda run: run.load(0), must_stop=False),
)


def _kill_then(node: str, publish: Callable[["FaultRun"], None]) -> Callable[["FaultRun"], None]:
    def inject(run: "FaultRun") -> None:
        run.graph.kill(node)
        publish(run)
    return inject


def _restart(node: str) -> Callable[["FaultRun"], None]:
    """Start a killed node again; its predecessor's reports no longer count."""
    def clear(run: "FaultRun") -> None:
        run.graph.forget(node)
        run.graph.restart(node)
    return clear


def _signal(node: str, signum: int) -> Callable[["FaultRun"], None]:
    return lambda run: run.graph.processes[node].send_signal(signum)


# The adversarial class: what a rogue process on the DDS domain, a wrong clock or a stray TCP peer can do.
# Judged like the rest by the controller's record of what it applied, on its own clock.
ADVERSARIAL = (
    Fault("compensator SIGKILL, then one correction stamped +1 h",
          _kill_then("pd_compensator", lambda run: run.rogue_correction(ahead_s=3600.0)),
          _restart("pd_compensator"), must_stop=True, rearm=True, input_lost=True),
    Fault("compensator SIGKILL, then corrections stamped in 1970",
          _kill_then("pd_compensator", lambda run: run.rogue_correction(ahead_s=-time.time() + 1.0, count=20)),
          _restart("pd_compensator"), must_stop=True, rearm=True, input_lost=True),
    Fault("estimator SIGKILL, then one pose stamped +1 h, 1 m off",
          _kill_then("pose_estimator", lambda run: run.rogue_pose(ahead_s=3600.0, offset_m=1.0)),
          lambda run: run.graph.restart("pose_estimator"), must_stop=True, rearm=True, input_lost=True),
    Fault("rogue reference 1 m away, and one stamped +1 h", lambda run: run.rogue_references(), lambda run: None,
          must_stop=False, check=lambda run: run.references_refused(2)),
    Fault("trigger MCU silent 5 s, profiles 150 ms late", _sim(mcu_silent=True, delay_ms=150.0),
          _sim(mcu_silent=False, delay_ms=0.0), must_stop=True, rearm=True, input_lost=True, hold_s=5.0),
    *(Fault(f"{node} SIGSTOP 2 s", _signal(node, signal.SIGSTOP), _signal(node, signal.SIGCONT), must_stop=True,
            rearm=True, input_lost=True, hold_s=2.0)
      for node in ("profiler_driver", "pose_estimator", "pd_compensator", "motoplus_bridge")),
    Fault("profiler_driver SIGKILL, restarted", lambda run: run.graph.kill("profiler_driver"),
          lambda run: run.graph.restart("profiler_driver"), must_stop=True, rearm=True, input_lost=True),
    Fault("pd_compensator SIGKILL, restarted", lambda run: run.graph.kill("pd_compensator"),
          _restart("pd_compensator"), must_stop=True, rearm=True, input_lost=True),
    Fault("rogue controller peers: a second client, extreme and repeated HELLOs, an idle socket",
          lambda run: run.rogue_peers(), lambda run: None, must_stop=True, rearm=True,
          check=lambda run: run.rogue_peer_problems),
)


class FaultRun:
    def __init__(self, graph: Graph, rate_hz: float, refine_model: str, control_law: str) -> None:
        from geometry_msgs.msg import TwistStamped

        self.graph = graph
        self.exp = Experiment(graph, rate_hz, 5e-6, refine_model=refine_model,
                              compensator={"control_law": control_law})
        self.period = self.exp.period
        self.max_step = self.exp.max_step
        self.max_age = float(_DEFAULTS["max_age"])
        self.input_timeout = float(_DEFAULTS["input_timeout"])
        self.applied: list[tuple[float, np.ndarray]] = []
        self.moving_corrections: list[float] = []
        graph.node.create_subscription(TwistStamped, "sim/robot_increment", self._on_applied, 1000)
        graph.node.create_subscription(TwistStamped, "correction", self._on_correction, 1000)
        from geometry_msgs.msg import PoseWithCovarianceStamped

        # made before any fault, so that DDS has matched them when a rogue message is sent
        self._rogue_correction = graph.node.create_publisher(TwistStamped, "correction", 10)
        self._rogue_pose = graph.node.create_publisher(PoseWithCovarianceStamped, "pose_with_covariance", 10)
        self._refused_before = 0
        self.rogue_peer_problems = ""
        self.fresh_corrections: list[float] = []  # when a correction the bridge would take arrived here
        self._hogs: list[subprocess.Popen] = []
        self._sign = 1.0
        self._target = np.zeros(3)

    def _on_applied(self, msg) -> None:
        self.applied.append((stamp_ns(msg.header.stamp) * 1e-9, twist_vector(msg.twist)))

    def _on_correction(self, msg) -> None:
        """A non-zero correction is stamped with the trigger time of the pose it was computed from (the
        compensator's zeros for a stale pose carry the newest pose's time and move nothing). One stamped
        in the future (a rogue's) vouches for nothing."""
        stamp = stamp_ns(msg.header.stamp) * 1e-9
        now = time.time()
        if np.any(twist_vector(msg.twist) != 0.0) and stamp <= now + 0.002:
            self.moving_corrections.append(stamp)
        if 0.0 <= now - stamp <= self.max_age:
            self.fresh_corrections.append(now)

    # ---------------------------------------------------------------- a rogue on the domain, a stray peer
    def rogue_correction(self, ahead_s: float, count: int = 1) -> None:
        from geometry_msgs.msg import TwistStamped
        from rclpy.time import Time

        for _ in range(count):
            msg = TwistStamped()
            msg.header.stamp = Time(nanoseconds=int((time.time() + ahead_s) * 1e9)).to_msg()
            msg.header.frame_id = "base"
            msg.twist.linear.x = 0.01  # 10 mm/s: 120 um a period, under the clamp
            self._rogue_correction.publish(msg)
            self.exp.wait(0.005)

    def rogue_pose(self, ahead_s: float, offset_m: float) -> None:
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from rclpy.time import Time

        msg = PoseWithCovarianceStamped()
        msg.header.stamp = Time(nanoseconds=int((time.time() + ahead_s) * 1e9)).to_msg()
        msg.header.frame_id = "gauge"
        msg.pose.pose = copy.deepcopy(self.exp.last_pose)
        msg.pose.pose.position.x += offset_m
        msg.pose.covariance = list(np.diag([1e-10] * 3 + [1e-8] * 3).ravel())
        self._rogue_pose.publish(msg)

    def rogue_references(self) -> None:
        from rclpy.time import Time

        from ..nodes.messages import pose_stamped

        rotation, position = self.exp.home
        self._refused_before = int(self.graph.diagnostic("pd_compensator", "refused_reference", "0") or 0)
        now = self.graph.node.get_clock().now()
        self.exp.reference_pub.publish(pose_stamped(rotation, position + [1.0, 0.0, 0.0], now.to_msg(), "gauge"))
        ahead = Time(nanoseconds=now.nanoseconds + 3600 * 10 ** 9).to_msg()
        self.exp.reference_pub.publish(pose_stamped(rotation, position + [0.0, 2e-4, 0.0], ahead, "gauge"))

    def references_refused(self, expected: int) -> str:
        self.graph.forget("pd_compensator")
        self.graph.spin_until(lambda: self.graph.reported("pd_compensator"), 5.0)
        refused = int(self.graph.diagnostic("pd_compensator", "refused_reference", "0") or 0) - self._refused_before
        return "" if refused >= expected else f"the compensator refused {refused} of {expected} rogue references"

    def rogue_peers(self) -> None:
        """While the bridge is armed a second client is turned away; then, the bridge stopped, a rogue
        arms with limits of 2^31-1 (refused), one that asks within them sends a second, wider HELLO (a
        FAULT), and an idle socket is closed within the HELLO deadline."""
        import socket as sockets

        from ..core.wire import motoplus_protocol as mp

        problems = []
        port = self.exp.robot_port

        def answer(sock, frames: list, timeout: float = 2.0) -> list:
            sock.settimeout(timeout)
            reader = mp.FrameReader()
            got = []
            try:
                if frames:  # in one write: the controller reads them together, so no period falls between
                    sock.sendall(b"".join(mp.encode(frame) for frame in frames))
                while True:
                    data = sock.recv(4096)
                    if not data:
                        return got + ["closed"]
                    got += [f.body for f in reader.feed(data)]
            except (TimeoutError, sockets.timeout):
                return got + ["open"]
            except OSError:
                return got + ["closed"]

        hello = lambda step, seq=1: mp.Frame(seq, 0, mp.Hello(int(round(self.period * 1e6)), (step,) * 6,  # noqa
                                                               (min(step * 10, 2 ** 31 - 1),) * 6, 500))
        with sockets.create_connection(("127.0.0.1", port), timeout=2.0) as second:
            if answer(second, [hello(2 ** 31 - 1)])[-1] != "closed":
                problems.append("a second client was not turned away while the bridge was armed")
        self.exp.bridge(arm=False)
        with sockets.create_connection(("127.0.0.1", port), timeout=2.0) as rogue:
            got = answer(rogue, [hello(2 ** 31 - 1)])
            if not any(isinstance(b, mp.Fault) and b.code == mp.FAULT_LIMIT for b in got) or got[-1] != "closed":
                problems.append(f"a HELLO of 2^31-1 was not refused: {got}")
        with sockets.create_connection(("127.0.0.1", port), timeout=2.0) as rogue:
            got = answer(rogue, [hello(10), hello(200, seq=2)])
            if not any(isinstance(b, mp.Fault) and b.code == mp.FAULT_PROTOCOL for b in got):
                problems.append(f"a second, wider HELLO was not refused: {got}")
        with sockets.create_connection(("127.0.0.1", port), timeout=2.0) as idle:
            opened = time.monotonic()
            got = answer(idle, [], timeout=3.0)
            if got[-1] != "closed" or time.monotonic() - opened > 1.5:
                problems.append(f"an idle socket was held {time.monotonic() - opened:.2f} s ({got[-1]})")
        self.rogue_peer_problems = "; ".join(problems)

    def load(self, processes: int) -> None:
        for hog in self._hogs:
            hog.kill()
            hog.wait()
        self._hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(processes)]

    def restart_bridge(self) -> None:
        self.graph.forget("motoplus_bridge")  # its old "armed" report must not pass for the new process's
        self.graph.restart("motoplus_bridge")

    def rearm(self) -> float:
        """The operator: once the bridge reports it is disarmed (and holds no connection) and poses flow again,
        sends the target again (a restarted compensator has none) and ~/start. Re-armed before the data is
        back, the bridge would rightly end the session again for want of corrections."""
        self.graph.forget("motoplus_bridge")
        if not self.graph.spin_until(lambda: self.graph.diagnostic("motoplus_bridge", "state") == "disarmed",
                                     30.0):
            raise RuntimeError("the bridge did not come back disarmed")
        cleared = time.time()
        if not self.graph.spin_until(lambda: self.exp.poses and self.exp.poses[-1][0] > cleared, 60.0):
            raise RuntimeError("no fresh pose after the fault cleared")
        measured = lambda: int(self.graph.diagnostic("pd_compensator", "poses", "0") or 0) > 0  # noqa: E731
        if not self.graph.spin_until(measured, 30.0):  # a restarted one takes a target only once it has a pose
            raise RuntimeError("the compensator has no pose after the fault cleared")
        self.graph.forget("pd_compensator")  # a restarted one's subscription may not have matched the first
        has_target = lambda: self.graph.diagnostic("pd_compensator", "has_reference") == "True"  # noqa: E731
        for _ in range(50):
            self.exp.reference(self._target)
            if self.graph.spin_until(has_target, 0.2):
                break
        # and the chain correcting on time again (a restarted node's first poses can come late), as the
        # compensator's status would tell an operator: armed earlier, the bridge would end it again
        live = lambda: sum(t > time.time() - 0.3 for t in self.fresh_corrections[-50:]) >= 10  # noqa: E731
        if not self.graph.spin_until(live, 30.0):
            raise RuntimeError("the corrections did not come fresh again after the fault cleared")
        requested = time.time()
        self.exp.bridge(arm=True)
        return requested

    def start(self) -> None:
        self.exp.close_loop()

    def episode(self, fault: Fault) -> dict:
        self._sign = -self._sign
        self._target = np.array([self._sign * STEP_M, 0.0, 0.0])
        self.exp.reference(self._target)
        self.exp.wait(MID_MOTION_S)
        monitor_before = self._monitor_violations()
        ended_before = self.graph.diagnostic("sim_cell", "robot_sessions_ended", "0")
        fault_before = self.graph.diagnostic("sim_cell", "robot_last_fault", "none")
        fault.inject(self)
        t_inject = time.time()  # in effect: sim_cell has applied the parameter, or the killed process has exited
        self.exp.wait(fault.hold_s)
        session_end = self.graph.diagnostic("sim_cell", "robot_session_end", "none")
        ended = self.graph.diagnostic("sim_cell", "robot_sessions_ended", "0")
        t_clear = time.time()
        fault.clear(self)
        t_rearm = self.rearm() if fault.rearm else None
        resume = t_rearm or t_clear
        recovered = self.graph.spin_until(lambda: self._first_motion(resume) is not None, 60.0)
        self.exp.wait(SETTLE_S)
        t_end = time.time()
        self.exp.wait(IN_FLIGHT_S)  # what was published before t_end reaches this client before it judges
        result = self._evaluate(fault, t_inject, t_clear, t_rearm, resume, t_end, recovered, monitor_before,
                                fault_before)
        result["session_end"] = session_end if ended != ended_before else "-"
        if fault.session_end and session_end != fault.session_end:
            result["ok"] = False
        result["expectation"] = fault.check(self) if fault.check is not None else ""
        if result["expectation"]:
            result["ok"] = False
        return result

    def _monitor_violations(self) -> int:
        return int(self.graph.diagnostic("motoplus_bridge", "safety_violations", "0") or 0)

    def _moving(self, start: float, end: float) -> list[float]:
        return [t for t, step in self.applied if start <= t <= end and np.any(step != 0.0)]

    def _first_motion(self, after: float) -> float | None:
        return next((t for t, step in self.applied if t > after and np.any(step != 0.0)), None)

    def _pose_errors(self, start: float, end: float) -> list[float]:
        """|estimated - true position| of each pose in the window, matched by trigger time (the driver's
        stamp comes from the MCU's clock, so it is the truth's to within its sync error, not bit-equal)."""
        truth = {int(round(t * 1e9)): p for t, p in self.exp.truth if start - 0.1 <= t <= end + 0.1}
        stamps = np.array(sorted(truth), dtype=np.int64)
        errors = []
        for t, p in self.exp.poses:
            if start <= t <= end:
                match = nearest_stamp(stamps, int(round(t * 1e9)), TRUTH_MATCH_NS)
                if match is not None:
                    errors.append(float(np.linalg.norm(p - truth[match])))
        return errors

    def _evaluate(self, fault: Fault, t_inject: float, t_clear: float, t_rearm: float | None, resume: float,
                  t_end: float, recovered: bool, monitor_before: int, fault_before: str) -> dict:
        window = [(t, s) for t, s in self.applied if t_inject - 0.2 <= t <= t_end]
        clamp = sum(bool(np.any(np.abs(s) > self.max_step + 1.5e-6)) for _, s in window)
        fresh = np.array(sorted(self.moving_corrections))  # trigger times of the poses behind moving corrections
        stale = 0
        for t, s in window:
            if np.any(s != 0.0):
                k = np.searchsorted(fresh, t, side="right")
                newest = fresh[k - 1] if k else -np.inf
                stale += int(t - newest > self.max_age + self.period + SCHEDULING_SLACK_S)
        session_before_rearm = 0
        if fault.rearm and t_rearm is not None:  # the bridge ends a session whose input stopped after input_timeout
            ends_by = t_inject + 2 * self.period + SCHEDULING_SLACK_S + (
                self.max_age + self.input_timeout if fault.input_lost else 0.0)
            session_before_rearm = sum(1 for t, _ in window if ends_by < t < t_rearm)
        errors = self._pose_errors(t_inject, t_end)
        bad_poses = sum(e > BAD_POSE_M for e in errors)
        last_fault = self.graph.diagnostic("sim_cell", "robot_last_fault", "none")  # latched: new in this episode?
        offset_faults = int(last_fault != fault_before and "total offset" in last_fault)
        moving = self._moving(t_inject, t_clear)
        stop_s = max(moving) - t_inject if moving else 0.0
        first = self._first_motion(resume)
        during = [t for t, _ in self.exp.poses if t_inject + STAMP_SLACK_S <= t <= t_clear - STAMP_SLACK_S]
        result = {
            "fault": fault.name, "must_stop": fault.must_stop,
            "stop_ms": stop_s * 1e3, "stop_periods": stop_s / self.period,
            "moving_periods_during_fault": len(moving),
            "rearmed_after_s": (t_rearm - t_clear) if t_rearm else None,
            "recovered": recovered, "recovered_after_s": (first - t_clear) if first else None,
            "poses_during_fault": len(during), "max_pose_error_um": float(max(errors) * 1e6) if errors else None,
            "violations": {"clamp": clamp, "stale_motion": stale, "session_before_rearm": session_before_rearm,
                           "offset_fault": offset_faults, "bad_poses": bad_poses,
                           "bridge_monitor": max(0, self._monitor_violations() - monitor_before)},
        }
        result["stopped_in_time"] = (not fault.must_stop) or result["stop_periods"] <= STOP_PERIODS
        result["ok"] = recovered and result["stopped_in_time"] and not any(result["violations"].values())
        return result

    def close(self) -> None:
        self.load(0)


def run(rate_hz: float, refine_model: str, out, names: list[str] | None = None,
        control_law: str = CELL_CONTROL_LAW) -> list[dict]:
    faults = [f for f in FAULTS + ADVERSARIAL if names is None or any(n.lower() in f.name.lower() for n in names)]
    graph = Graph(out / "logs", client_name="profile_pose_faults")
    results = []
    fault_run = None
    try:
        fault_run = FaultRun(graph, rate_hz, refine_model, control_law)
        fault_run.start()
        for fault in faults:
            print(f"  {fault.name} ...", flush=True)
            results.append(fault_run.episode(fault))
    finally:
        if fault_run is not None:
            fault_run.close()
        graph.close()
    return results


def print_table(results: list[dict], period_ms: float) -> None:
    rows = []
    for r in results:
        v = r["violations"]
        rows.append((r["fault"], "yes" if r["must_stop"] else "no",
                     f"{r['stop_ms']:.0f} ms = {r['stop_periods']:.1f}" if r["moving_periods_during_fault"] or
                     r["must_stop"] else "-",
                     str(r["moving_periods_during_fault"]),
                     f"{r['recovered_after_s']:.2f} s" if r["recovered_after_s"] is not None else "NO",
                     f"{r['rearmed_after_s']:.2f} s" if r["rearmed_after_s"] is not None else "-",
                     str(r["poses_during_fault"]),
                     f"{r['max_pose_error_um']:.0f}" if r["max_pose_error_um"] is not None else "-",
                     "/".join(str(v[k]) for k in ("clamp", "stale_motion", "session_before_rearm", "offset_fault",
                                                  "bad_poses", "bridge_monitor")),
                     "ok" if r["ok"] else "FAIL"))
    print(table(("fault", "must stop", "last motion after (periods)", "moving periods", "moving again after",
                 "re-armed after", "poses in fault", "max pose err um", "violations*", "verdict"), rows,
                f"fault injection on the running closed loop ({period_ms:g} ms control period)"))
    print("* clamp / motion on a stale pose / session before the re-arm / offset-bound FAULT / poses > "
          f"{BAD_POSE_M * 1e6:.0f} um from the truth / the bridge's own monitor")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=83.333, help="control rate: 83.333 (12 ms) or 250 (4 ms)")
    parser.add_argument("--refine-model", default="corners", choices=REFINE_MODELS)
    parser.add_argument("--only", nargs="+", help="only the faults whose names contain one of these words")
    add_control_law_option(parser)
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    out = run_dir(args.out, "faults")
    print(f"injecting faults into the closed loop at {args.rate:g} Hz, {args.control_law} law (logs in "
          f"{out / 'logs'})", flush=True)
    results = run(args.rate, args.refine_model, out, args.only, args.control_law)
    print_table(results, 12.0 if args.rate < 200 else 4.0)
    write_json(out / "faults.json", {"rate_hz": args.rate, "results": results})
    failed = [r["fault"] for r in results if not r["ok"]]
    print(f"results: {out / 'faults.json'}; " + (f"FAILED: {', '.join(failed)}" if failed else
                                                 "every fault: no violation, stopped in time, recovered"))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
