"""Commissioning through the running nodes (each its own process, sim_cell on loopback): profile_pose_calibrate
measures a placement the nodes were not told, and the first-motion check keeps a wrongly mounted loop open,
judged by what the controller applied (sim/robot_increment), not by the loop's own word."""
from __future__ import annotations

import json
import os
import subprocess
import time

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import TwistStamped

from profile_pose_ros.core.model.transform import Transform, difference
from profile_pose_ros.nodes.pd_compensator import PARAMETERS as COMPENSATOR_PARAMETERS
from profile_pose_ros.tools import processes
from profile_pose_ros.tools.calibration_study import start_cell
from profile_pose_ros.tools.experiment import Experiment
from profile_pose_ros.tools.graph import Graph

GAUGE = "config/gauge_designed_n6.yaml"


def test_profile_pose_calibrate_measures_a_hidden_placement_and_writes_its_files(tmp_path) -> None:
    """The command as an engineer runs it, against sim_cell, the driver, the estimator and the bridge in
    calibration mode: without an operator it moves nothing; with --yes it measures what the nodes were not
    told, and its parameter file is one pd_compensator takes."""
    gauge_in_base = np.array([0.03, -0.02, 0.01, 0.05, -0.04, 0.4])
    profiler_in_flange = np.array([0.02, 0.025, -0.015, -0.06, 0.03, 0.05])
    graph = Graph(tmp_path / "logs")
    command = processes.executable("profile_pose_calibrate", "profile_pose_ros.nodes.calibrate") + [
        "--out", str(tmp_path / "calibration"), "--move-time", "0.5", "--settle", "0.5", "--dwell", "0.6", "--wait", "60"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(graph.domain_id))
    try:
        bridge = start_cell(graph, gauge_in_base, profiler_in_flange, GAUGE)
        graph.start("motoplus_bridge", {**bridge, "mode": "calibration"})
        unconfirmed = subprocess.run(command, env=env, stdin=subprocess.DEVNULL, capture_output=True, timeout=120)
        assert unconfirmed.returncode == 1 and b"no operator to confirm" in unconfirmed.stderr, unconfirmed.stderr
        graph.forget("motoplus_bridge")
        assert graph.spin_until(lambda: graph.reported("motoplus_bridge"), 10.0)
        assert graph.diagnostic("motoplus_bridge", "connections") == "0"  # it connects to arm: never armed, never moved
        done = subprocess.run(command + ["--yes"], env=env, stdin=subprocess.DEVNULL, capture_output=True, timeout=180)
    finally:
        graph.close()
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    report = json.loads((tmp_path / "calibration" / "calibration.json").read_text())
    assert report["refused"] is None and len(report["stations"]) == 13 and report["robot_motion_s"] <= 60.0
    assert (tmp_path / "calibration" / "residuals.png").stat().st_size > 0
    values = yaml.safe_load((tmp_path / "calibration" / "calibration.yaml").read_text())["pd_compensator"]["ros__parameters"]
    assert set(values) == {"gauge_in_base", "profiler_in_tool"}
    assert set(values) <= {p.name for p in COMPENSATOR_PARAMETERS}
    mount = difference(Transform.from_vector(profiler_in_flange), Transform.from_vector(values["profiler_in_tool"]))
    place = difference(Transform.from_vector(gauge_in_base), Transform.from_vector(values["gauge_in_base"]))
    assert np.linalg.norm(mount[3:]) < 2e-3 and np.linalg.norm(mount[:3]) < 2e-4, mount
    assert np.linalg.norm(place[3:]) < 1e-3, place


def test_the_first_motion_check_keeps_a_flipped_loop_open(tmp_path) -> None:
    """The gauge stands turned half a turn about the base z axis; the compensator is told it is not: its
    corrections would push x and y the wrong way. The probe of x finds the flip, and nothing moves after."""
    graph = Graph(tmp_path / "logs")
    applied: list[tuple[float, np.ndarray]] = []
    try:
        exp = Experiment(graph, 83.333, 5e-6, gauge_file=GAUGE, first_motion=True,
                         sim_truth={"gauge_in_base": [0.0, 0.0, 0.0, 0.0, 0.0, np.pi]})

        def witness(msg: TwistStamped) -> None:
            t = msg.twist
            applied.append((time.monotonic(), np.array([t.linear.x, t.linear.y, t.linear.z,
                                                        t.angular.x, t.angular.y, t.angular.z])))

        graph.subscribe_fast(TwistStamped, "sim/robot_increment", witness)
        exp.start()
        exp.bridge(arm=True)
        with pytest.raises(RuntimeError, match="sign flip"):
            exp.await_first_motion_check()
        refused_at = time.monotonic()
        assert applied and max(np.abs(a).max() for _, a in applied) > 0  # the probe did move the arm
        graph.spin_until(lambda: exp.value("motoplus_bridge", "state") not in ("armed", ""), 5.0)
        graph.spin_until(lambda: False, 1.0)
        after = [a for t, a in applied if t > refused_at]
        assert all(not a.any() for a in after), after  # no closed-loop motion after the verdict
        assert exp.value("motoplus_bridge", "state") != "armed"  # the stream ended: the bridge stopped the session
    finally:
        graph.close()
