"""Commissioning without ROS: the hand-eye solve on rendered profiles, its refusals, the calibration's moves,
the first-motion verdicts, and the tool velocity that carries the profiler along its lever arm."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from profile_pose_ros.core import Gauge, estimate_pose, render_profile
from profile_pose_ros.core.commissioning.first_motion import FirstMotionCheck, ProbeDesign, judge
from profile_pose_ros.core.commissioning.hand_eye import Bounds, CalibrationError, Station, solve, station
from profile_pose_ros.core.commissioning.procedure import Procedure, Timing
from profile_pose_ros.core.commissioning.sequence import stations
from profile_pose_ros.core.control.compensator import Mounting
from profile_pose_ros.core.model.rotation import so3_exp
from profile_pose_ros.core.model.transform import (Transform, controller_angles, difference,
                                                   rotation_from_controller_angles)
from profile_pose_ros.nodes.sim_cell import DEFAULT_POSE
from profile_pose_ros.sim.motion import ArmMotion
from profile_pose_ros.tools.calibration_study import hidden_placement

EXACT_ROBOT = Bounds(robot_translation_sigma=0.3e-6, robot_rotation_sigma=1e-6)  # sim_cell reports 1 um units


class HeldArm:
    position = np.zeros(6)


@pytest.fixture(scope="module")
def designed() -> Gauge:
    return Gauge.from_yaml("config/gauge_designed_n6.yaml")


def record(gauge: Gauge, motion: ArmMotion, arm: HeldArm, offsets: np.ndarray, rng, poses: int = 30,
           moved: dict[int, np.ndarray] | None = None) -> list[Station]:
    """Stations as the calibrate command records them, from rendered profiles; moved: station -> the gauge's
    displacement in G there (a gauge knocked mid-sequence)."""
    out = []
    for k, offset in enumerate(offsets):
        arm.position = offset
        rotation, translation = motion.pose_at(0.0)
        translation = translation - (moved or {}).get(k, np.zeros(3))
        estimates, covariances = [], []
        for _ in range(poses):
            estimate = estimate_pose(render_profile(gauge, rotation, translation, noise_std=5e-6, rng=rng), gauge)
            assert estimate.ok, estimate.reason
            estimates.append(Transform(estimate.R, estimate.t))
            covariances.append(estimate.covariance)
        out.append(station([motion.tool_pose(offset)], estimates, covariances))
    return out


def test_calibration_recovers_hidden_placements_within_bounds_and_its_own_sigmas(designed) -> None:
    rng = np.random.default_rng(11)
    nominal = Transform.from_vector(DEFAULT_POSE)
    for _ in range(3):
        gauge_in_base, profiler_in_flange = hidden_placement(rng)
        arm = HeldArm()
        motion = ArmMotion(nominal.rotation, nominal.translation, arm, gauge_in_base, profiler_in_flange)
        result = solve(record(designed, motion, arm, stations(), rng), EXACT_ROBOT)
        assert result.refused is None, result.refused
        error = np.r_[difference(Transform.from_vector(profiler_in_flange), result.profiler_in_tool),
                      difference(Transform.from_vector(gauge_in_base), result.gauge_in_base)]
        assert np.linalg.norm(error[3:6]) < 2e-3 and np.linalg.norm(error[:3]) < 2e-4  # profiler on the flange
        assert np.linalg.norm(error[9:]) < 1e-3  # gauge rotation in the base frame
        assert np.all(np.abs(error) < 3 * result.sigma), (error / result.sigma).round(2)


def test_a_gauge_knocked_mid_sequence_is_refused_as_inconsistent(designed) -> None:
    rng = np.random.default_rng(12)
    nominal = Transform.from_vector(DEFAULT_POSE)
    arm = HeldArm()
    motion = ArmMotion(nominal.rotation, nominal.translation, arm, [0.01, 0, 0, 0, 0, 0.2], [0.01, 0.02, 0, 0.03, 0, 0])
    knocked = {k: np.array([1e-4, 0.0, 0.0]) for k in range(7, 13)}  # 0.1 mm from station 7 on
    result = solve(record(designed, motion, arm, stations(), rng, moved=knocked), EXACT_ROBOT)
    assert result.refused is not None and result.refused.startswith("inconsistent"), result.refused


def test_moves_that_cannot_determine_the_mount_are_refused(designed) -> None:
    rng = np.random.default_rng(13)
    nominal = Transform.from_vector(DEFAULT_POSE)
    arm = HeldArm()
    motion = ArmMotion(nominal.rotation, nominal.translation, arm, [0, 0, 0, 0, 0, 0.1], [0.01, 0, 0, 0, 0, 0])
    one_axis = np.array([[0, 0, 0, 0, 0, 0], [4e-3, 0, 0, 0, 0, 0], [0, 0, 0, 0.03, 0, 0], [0, 0, 0, -0.03, 0, 0]])
    with pytest.raises(CalibrationError, match="fewer than two different axes"):
        solve(record(designed, motion, arm, one_axis, rng, poses=5), EXACT_ROBOT)
    tiny_turns = stations(turn=np.radians(0.05))  # the profiler's lever arm is measured by turns
    result = solve(record(designed, motion, arm, tiny_turns, rng, poses=10), EXACT_ROBOT)
    assert result.refused is not None and result.refused.startswith("badly conditioned"), result.refused


def test_the_procedure_visits_every_station_within_a_minute_and_comes_back() -> None:
    offsets = stations()
    procedure = Procedure(offsets, Timing())
    assert procedure.motion_s <= 60.0
    position, now, period = np.zeros(6), 0.0, 0.012
    visited = []
    while not procedure.done and now < 100.0:
        position += procedure.velocity(now, Transform.from_vector(np.r_[position[:3], position[3:]])) * period
        if procedure.phase == "recording":
            procedure.estimate(Transform.identity(), np.eye(6) * 1e-10)
            visited.append(position.copy())
        now += period
    assert procedure.done and procedure.failed is None and len(procedure.recorded) == len(offsets)
    assert np.abs(position).max() < 1e-6  # back at the start pose (to the sampling of the moves)
    for target, recorded in zip(offsets, procedure.recorded):
        assert np.allclose(recorded.tool_in_base.translation, target[:3], atol=1e-6)


def test_a_move_cut_short_is_resumed_from_where_the_tool_is() -> None:
    """The arm stops following for half a second mid-move: the move goes on from the reported pose. Later a
    session is lost and armed again at a station: the tool goes to the start pose, waits for a session to
    be started there, and goes on. Every station is still where it was designed."""
    offsets = stations()
    procedure = Procedure(offsets, Timing())
    position, now, period, stalled = np.zeros(6), 0.0, 0.012, False
    while not procedure.done and now < 100.0:
        velocity = procedure.velocity(now, Transform.from_vector(position))
        position += velocity * period
        if procedure.phase == "recording":
            procedure.estimate(Transform.identity(), np.eye(6) * 1e-10)
        now += period
        if not stalled and procedure.index == 4 and procedure.phase == "moving" and now - procedure.phase_start > 0.3:
            now, stalled = now + 0.5, True  # no period for 0.5 s: what the arm was told meanwhile never came
        if stalled is True and procedure.index == 7 and procedure.phase == "settling":
            procedure.rehome(now)  # a session lost and armed again here: back to the start pose first
            stalled, rehomed_from = "rehoming", position.copy()
        if procedure.waiting_for_session:
            assert np.abs(position).max() < 1e-6  # at the start pose, where the caller starts a session
            procedure.session_restarted(now)
            stalled = "rehomed"
    assert stalled == "rehomed" and np.abs(rehomed_from).max() > 1e-3
    assert procedure.done and procedure.resumed >= 1 and len(procedure.recorded) == len(offsets)
    for target, recorded in zip(offsets, procedure.recorded):
        assert np.allclose(recorded.tool_in_base.vector(), target, atol=1e-6)
    assert np.abs(position).max() < 1e-6


def test_a_station_without_poses_fails_the_procedure_and_it_returns_home() -> None:
    procedure = Procedure(stations(), Timing(0.1, 0.1, 0.1))
    position, now = np.zeros(6), 0.0
    while not procedure.done and now < 10.0:
        position += procedure.velocity(now, Transform.identity()) * 0.01
        now += 0.01
    assert procedure.failed is not None and "station 0" in procedure.failed
    assert np.abs(position).max() < 1e-9


@pytest.mark.parametrize("response, words", [
    (np.eye(6), ""),
    (np.diag([-1.0, -1.0, 1, 1, 1, 1]), "opposite way"),
    (np.eye(6)[[1, 0, 2, 3, 4, 5]], "an axis swap"),
    (np.diag([1, 1, 1, 0.3, 1, 1]), "0.30 of the command"),
    (np.block([[so3_exp(np.array([0, 0, 0.2])), np.zeros((3, 3))], [np.zeros((3, 3)), np.eye(3)]]), "11.5 deg"),
    (np.block([[np.eye(3), np.array([[0, 0.02, 0], [0, 0, 0], [0, 0, 0]])], [np.zeros((3, 3)), np.eye(3)]]),
     "profiler_in_tool is off"),
])
def test_first_motion_verdicts(response, words) -> None:
    verdict = judge(response, ProbeDesign())
    assert (verdict == "") if not words else (words in verdict), verdict


def test_the_first_motion_check_probes_each_axis_and_passes_a_true_response() -> None:
    check, position, now = FirstMotionCheck(), np.zeros(6), 0.0
    while not check.done and now < 30.0:
        position += check.velocity(now, position.copy()) * 0.012
        now += 0.012
    assert check.verdict == "" and np.allclose(check.response, np.eye(6), atol=0.02)
    assert np.abs(position).max() < 1e-6 and now < 6 * ProbeDesign().axis_s + 1.0  # back, to the sampling


def test_the_tool_velocity_moves_the_profiler_origin_as_asked() -> None:
    mounting = Mounting((0.0, 0.0, 0.0, 0.0, 0.0, 0.3), (0.03, -0.01, 0.02, 0.05, -0.04, 0.1))
    profiler_in_gauge = so3_exp(np.array([np.pi, 0.0, 0.0]))
    wanted = np.array([1e-3, -2e-3, 0.5e-3, 0.02, -0.01, 0.03])
    tool = mounting.tool_velocity(wanted, profiler_in_gauge)
    base_profiler = mounting.rotation @ profiler_in_gauge  # the profiler's rotation in the base frame
    x = Transform.from_vector(mounting.profiler_in_tool)
    tool_rotation = base_profiler @ x.rotation.T
    dt = 1e-4  # a small step of the tool: turn about its origin, then the profiler's origin follows
    turned = so3_exp(tool[3:] * dt) @ tool_rotation
    moved = tool[:3] * dt + turned @ x.translation - tool_rotation @ x.translation
    assert np.allclose(moved / dt, wanted[:3], atol=1e-5 * np.abs(wanted[:3]).max() + 1e-9)


def test_controller_angles_round_trip_and_the_sim_reports_its_tool() -> None:
    angles = np.array([3.0, -0.2, 1.1])
    assert np.allclose(controller_angles(rotation_from_controller_angles(angles)), angles)
    arm = HeldArm()
    nominal = Transform.from_vector(DEFAULT_POSE)
    motion = ArmMotion(nominal.rotation, nominal.translation, arm, [0.1, 0, 0, 0, 0, 0.5], [0, 0, 0.05, 0, 0.1, 0])
    arm.position = np.array([1e-3, 0, 0, 0, 0, 0.01])
    reported = motion.controller_pose(arm.position)
    tool = motion.tool_pose(arm.position)
    assert np.allclose(rotation_from_controller_angles(reported[3:]), tool.rotation)
    assert np.allclose(reported[:3], tool.translation)


@settings(max_examples=200, deadline=None)
@given(st.floats(-np.pi, np.pi), st.floats(-1.5, 1.5), st.floats(-np.pi, np.pi))
def test_the_written_out_controller_angles_are_scipys_xyz_euler_angles(rx: float, ry: float, rz: float) -> None:
    from scipy.spatial.transform import Rotation

    angles = np.array([rx, ry, rz])
    expected = Rotation.from_euler("xyz", angles).as_matrix()
    np.testing.assert_allclose(rotation_from_controller_angles(angles), expected, atol=1e-12)
    np.testing.assert_allclose(rotation_from_controller_angles(controller_angles(expected)), expected, atol=1e-9)
    apart = controller_angles(expected) - Rotation.from_matrix(expected).as_euler("xyz")
    np.testing.assert_allclose(np.angle(np.exp(1j * apart)), 0.0, atol=1e-9)  # the same angles, up to 2 pi
