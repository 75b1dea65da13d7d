"""profile_pose_calibrate: measure where the gauge sits in the robot base frame and where the profiler sits on
the tool, on a running cell (profiler_driver, pose_estimator, and motoplus_bridge with `mode: calibration`).

It moves the arm through a short sequence of stations (core/commissioning/sequence.py, each within the
bridge's calibration envelope), records the estimated poses with their covariances and the controller's own
poses (robot_state) while the arm holds still, and solves A X = Y M (core/commissioning/hand_eye.py). It
writes a parameter file for pd_compensator (gauge_in_base, profiler_in_tool) and a report with the per-station
residuals; a sequence that cannot determine them, or whose residuals the covariances do not explain, is
refused with the reason and writes no parameter file. On hardware it asks the operator before the first move.
A session the bridge ends mid-sequence is armed again (a few times at most): back to the start pose, a new
session there, and the sequence resumed; every move starts from where the controller says the tool is.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
import yaml
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TwistStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from ..core.commissioning.hand_eye import (X_ROTATION, X_TRANSLATION, Y_ROTATION, Y_TRANSLATION, Bounds, Calibration,
                                           CalibrationError, solve)
from ..core.commissioning.procedure import Procedure, Timing
from ..core.commissioning.sequence import stations
from ..core.model.transform import Transform
from .messages import rotation_translation

NODE_NAME = "profile_pose_calibrate"
ARMING_RATE_HZ = 100.0  # zero moves while arming: the bridge arms only on a live input
START_ATTEMPTS = 5
SESSION_LOST_S = 1.0  # no robot_state for this long: the bridge ended the session (its input timeout is 0.5 s)
MAX_REARMS = 3  # sessions lost mid-sequence and re-armed before the calibration gives up


class CalibrationNode(Node):
    def __init__(self, procedure: Procedure, base_frame: str = "base", **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.procedure, self.base_frame = procedure, base_frame
        self.poses = 0
        self.states = 0
        self.armed = False
        self.last_state = -float("inf")  # time.monotonic() of the newest robot_state
        self.move_pub = self.create_publisher(TwistStamped, "motoplus_bridge/calibration_move", 10)
        self.create_subscription(PoseWithCovarianceStamped, "pose_with_covariance", self._on_pose, 100)
        self.create_subscription(PoseStamped, "robot_state", self._on_state, 100)
        self.start_client = self.create_client(Trigger, "motoplus_bridge/start")
        self.stop_client = self.create_client(Trigger, "motoplus_bridge/stop")
        self.create_timer(1.0 / ARMING_RATE_HZ, self._keep_alive)

    def _publish(self, velocity: np.ndarray) -> None:
        msg = TwistStamped()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.base_frame
        (msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z,
         msg.twist.angular.x, msg.twist.angular.y, msg.twist.angular.z) = (float(v) for v in velocity)
        self.move_pub.publish(msg)

    def _keep_alive(self) -> None:
        """Before the session's first STATE: zero moves, so that ~/start finds a live input."""
        if not self.armed:
            self._publish(np.zeros(6))

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        self.poses += 1
        rotation, translation = rotation_translation(msg.pose.pose)
        self.procedure.estimate(Transform(rotation, translation), np.array(msg.pose.covariance).reshape(6, 6))

    def _on_state(self, msg: PoseStamped) -> None:
        """Each controller period, while armed: the period's move."""
        self.states += 1
        self.armed = True
        self.last_state = time.monotonic()
        if self.procedure.done:  # (a failed station's sequence still goes back to the start pose first)
            self._publish(np.zeros(6))
            return
        rotation, translation = rotation_translation(msg.pose)
        self._publish(self.procedure.velocity(time.monotonic(), Transform(rotation, translation)))


def spin_until(executor, condition, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    return bool(condition())


def call(executor, client, timeout: float = 5.0) -> tuple[bool, str]:
    if not client.wait_for_service(timeout_sec=timeout):
        return False, f"{client.srv_name} is not available (is motoplus_bridge running, in calibration mode?)"
    future = client.call_async(Trigger.Request())
    if not spin_until(executor, future.done, timeout):
        return False, f"{client.srv_name} did not answer"
    return future.result().success, future.result().message


def arm(executor, node: CalibrationNode) -> tuple[bool, str]:
    """~/start until the first robot_state: the bridge arms on a live input, and the node's first zero
    moves may still be in flight."""
    message = ""
    for _ in range(START_ATTEMPTS):
        ok, message = call(executor, node.start_client)
        if ok and spin_until(executor, lambda: node.armed, 10.0):
            return True, message
        spin_until(executor, lambda: False, 0.5)
    return False, message


def confirmed(procedure: Procedure, assume_yes: bool) -> bool:
    """The operator's go-ahead before the first move (a real arm is about to move)."""
    reach = np.abs(procedure.offsets).max(axis=0)
    print(f"The arm will move through {len(procedure.offsets)} stations in about {procedure.motion_s:.0f} s, "
          f"at most {reach[:3].max() * 1e3:.1f} mm and {np.degrees(reach[3:].max()):.2f} deg from where it is now, "
          "and return there.", flush=True)
    if assume_yes:
        return True
    if not sys.stdin.isatty():
        print("not moving: no operator to confirm (run it from a terminal, or pass --yes when nobody can be hurt, "
              "e.g. on sim_cell)", file=sys.stderr)
        return False
    return input("Clear of the cell, hand on the enabling device? Type 'move' to start: ").strip() == "move"


def run(procedure: Procedure, args, context=None) -> tuple[Calibration | None, str]:
    """Move, record, solve. Returns the calibration (None when there is none) and what went wrong, if anything."""
    node = CalibrationNode(procedure, args.base_frame, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        if not spin_until(executor, lambda: node.poses >= 20, args.wait):
            return None, f"no poses on {node.resolve_topic_name('pose_with_covariance')} within {args.wait:g} s"
        if not confirmed(procedure, args.yes):
            return None, "the operator did not confirm"
        if not spin_until(executor, lambda: node.move_pub.get_subscription_count() > 0, 10.0):
            return None, (f"nobody listens on {node.move_pub.topic_name}: is motoplus_bridge running with "
                          "mode: calibration?")
        ok, message = arm(executor, node)
        if not ok:
            return None, f"the bridge did not arm: {message}"
        deadline = time.monotonic() + procedure.motion_s + 60.0
        lost = lambda: time.monotonic() - node.last_state > SESSION_LOST_S  # noqa: E731
        rearms = 0
        while not procedure.done and time.monotonic() < deadline:
            spin_until(executor, lambda: procedure.done or procedure.waiting_for_session or lost(),
                       deadline - time.monotonic())
            if procedure.done or time.monotonic() >= deadline:
                break
            if procedure.waiting_for_session:  # back at the start pose: a session from here, as at the start
                call(executor, node.stop_client)
            else:
                # The session ended mid-sequence (this process stalled past the bridge's input timeout, or the
                # controller stopped): arm again, as the operator agreed to the whole sequence; a controller
                # that is not ready refuses. That session's offset bound starts where the tool is, so the
                # procedure goes back to the start pose and a session is started there again.
                if rearms == MAX_REARMS:
                    return None, f"the bridge ended the session {rearms + 1} times mid-sequence"
                rearms += 1
                print(f"the bridge ended the session at station {procedure.index}; arming again", file=sys.stderr)
            node.armed = False
            ok, message = arm(executor, node)
            if not ok:
                return None, f"the session ended mid-sequence and could not be resumed: {message}"
            if procedure.waiting_for_session:
                procedure.session_restarted(time.monotonic())
            else:
                procedure.rehome(time.monotonic())
        if procedure.failed:
            return None, procedure.failed
        if not procedure.done:
            return None, f"the sequence did not finish ({len(procedure.recorded)} stations recorded; robot_state stopped?)"
    finally:
        if node.armed:  # on every way out: the bridge disarms (STOP) rather than waiting for its input timeout
            call(executor, node.stop_client)
        executor.shutdown()
        node.destroy_node()
    try:
        result = solve(procedure.recorded, Bounds(robot_translation_sigma=args.robot_sigma[0],
                                                  robot_rotation_sigma=args.robot_sigma[1]))
    except CalibrationError as exc:
        return None, str(exc)
    return result, result.refused or ""


def report(result: Calibration, procedure: Procedure, tool_in_flange: Transform) -> dict:
    sigma = result.sigma
    flange = tool_in_flange @ result.profiler_in_tool
    return {
        "refused": result.refused,
        "gauge_in_base": result.gauge_in_base.vector().tolist(),
        "profiler_in_tool": result.profiler_in_tool.vector().tolist(),
        "profiler_in_flange": flange.vector().tolist(),
        "sigma": {"profiler_in_tool_translation_m": sigma[X_TRANSLATION].tolist(),
                  "profiler_in_tool_rotation_rad": sigma[X_ROTATION].tolist(),
                  "gauge_in_base_translation_m": sigma[Y_TRANSLATION].tolist(),
                  "gauge_in_base_rotation_rad": sigma[Y_ROTATION].tolist()},
        "covariance": result.covariance.tolist(),
        "chi2": result.chi2, "dof": result.dof, "p_value": result.p_value,
        "stations": [{"offset": procedure.offsets[k].tolist(), "poses": s.poses, "chi2": float(result.station_chi2[k]),
                      "residual_um": (result.station_residuals[k, :3] * 1e6).tolist(),
                      "residual_urad": (result.station_residuals[k, 3:] * 1e6).tolist()}
                     for k, s in enumerate(procedure.recorded)],
        "robot_motion_s": procedure.motion_s,
    }


def plot_residuals(result: Calibration, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    k = np.arange(len(result.station_residuals))
    for axis, label in enumerate("xyz"):
        top.plot(k, result.station_residuals[:, axis] * 1e6, "o-", label=label)
        bottom.plot(k, result.station_residuals[:, 3 + axis] * 1e6, "o-", label=f"r{label}")
    top.set_ylabel("position residual (um, G)")
    bottom.set_ylabel("rotation residual (urad, G)")
    bottom.set_xlabel("station")
    top.legend()
    bottom.legend()
    top.set_title(f"calibration residuals: chi2 {result.chi2:.1f} on {result.dof} dof (p = {result.p_value:.2g})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parameter_file(result: Calibration) -> dict:
    return {"pd_compensator": {"ros__parameters": {
        "gauge_in_base": [round(float(v), 9) for v in result.gauge_in_base.vector()],
        "profiler_in_tool": [round(float(v), 9) for v in result.profiler_in_tool.vector()]}}}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="profile_pose_calibrate", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("calibration"), help="directory for calibration.yaml (the "
                   "parameter file), calibration.json and residuals.png")
    p.add_argument("--translation", type=float, default=4e-3, help="translation of the stations (m, <= 5 mm)")
    p.add_argument("--turn", type=float, default=np.radians(2.0), help="turn of the stations (rad, <= 2 deg)")
    p.add_argument("--move-time", type=float, default=Timing.move_s, help="s per move")
    p.add_argument("--settle", type=float, default=Timing.settle_s, help="s to wait at a station before recording")
    p.add_argument("--dwell", type=float, default=Timing.dwell_s, help="s of recording per station")
    p.add_argument("--tool-in-flange", type=float, nargs=6, default=[0.0] * 6,
                   help="the controller's tool (x y z m, rotation vector rad on the flange), to report the profiler "
                        "on the flange as well as on the tool")
    p.add_argument("--robot-sigma", type=float, nargs=2, default=[Bounds.robot_translation_sigma,
                                                                  Bounds.robot_rotation_sigma],
                   help="the controller's pose noise over a few mm (m, rad): its repeatability")
    p.add_argument("--base-frame", default="base", help="the bridge's base_frame")
    p.add_argument("--wait", type=float, default=30.0, help="s to wait for the first poses")
    p.add_argument("--yes", action="store_true", help="move without asking (sim_cell, or an operator's script)")
    return p


def main(args=None) -> int:
    argv = sys.argv[1:] if args is None else list(args)
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    options = parser().parse_args(argv[:len(argv) - len(ros_args)])
    if options.translation > 5e-3 or options.turn > np.radians(2.0) + 1e-9:
        print("profile_pose_calibrate: stations are limited to 5 mm and 2 deg", file=sys.stderr)
        return 2
    procedure = Procedure(stations(options.translation, options.turn),
                          Timing(options.move_time, options.settle, options.dwell))
    rclpy.init(args=["profile_pose_calibrate", *ros_args])
    try:
        result, problem = run(procedure, options)
    finally:
        rclpy.try_shutdown()
    write_calibration(options.out, result, procedure, problem, Transform.from_vector(options.tool_in_flange))
    if problem:
        print(f"calibration refused: {problem}", file=sys.stderr)
        return 1
    print(summary(result, Transform.from_vector(options.tool_in_flange)))
    print(f"parameter file: {options.out / 'calibration.yaml'}; report: {options.out / 'calibration.json'}, "
          f"{options.out / 'residuals.png'}")
    return 0


def write_calibration(out: Path, result: Calibration | None, procedure: Procedure, problem: str = "",
                      tool_in_flange: Transform = Transform.identity()) -> None:
    """The report and its plot whenever there is a result; the parameter file only for one that may be used."""
    out.mkdir(parents=True, exist_ok=True)
    if result is not None:
        (out / "calibration.json").write_text(json.dumps(report(result, procedure, tool_in_flange), indent=1))
        plot_residuals(result, out / "residuals.png")
    if not problem and result is not None:
        (out / "calibration.yaml").write_text(yaml.safe_dump(parameter_file(result), sort_keys=False))


def summary(result: Calibration, tool_in_flange: Transform) -> str:
    s = result.sigma
    flange = (tool_in_flange @ result.profiler_in_tool).vector()
    return "\n".join([
        f"gauge in base: {np.round(result.gauge_in_base.vector()[:3] * 1e3, 3).tolist()} mm, rotation "
        f"{np.round(result.gauge_in_base.vector()[3:] * 1e3, 2).tolist()} mrad (std {s[Y_ROTATION].max() * 1e3:.3f} mrad)",
        f"profiler on the flange: {np.round(flange[:3] * 1e3, 3).tolist()} mm (std {s[X_TRANSLATION].max() * 1e3:.3f} mm), "
        f"rotation {np.round(flange[3:] * 1e3, 2).tolist()} mrad (std {s[X_ROTATION].max() * 1e3:.3f} mrad)",
        f"residuals: chi2 {result.chi2:.1f} on {result.dof} dof (p = {result.p_value:.2g})"])


if __name__ == "__main__":
    sys.exit(main())
