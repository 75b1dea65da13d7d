"""pd_compensator: the filter and PD law, zero motion on stale input, validated gains (real rclpy)."""
from __future__ import annotations

import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from hypothesis import given, settings
from hypothesis import strategies as st
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TwistStamped
from rclpy.parameter import Parameter
from rclpy.time import Time

from profile_pose_ros.core.control.compensator import (AxisKalman, Gains, InputShaper, Mounting, covariance_in_base,
                                                       pd_velocity, zvd_impulses)
from profile_pose_ros.core.model.poses import LOOKING_DOWN
from profile_pose_ros.nodes.messages import pose_stamped, pose_with_covariance
from profile_pose_ros.nodes.pd_compensator import PdCompensatorNode
from profile_pose_ros.sim.arm import Arm

from conftest import paced


def filtered_error(declared_variance: np.ndarray, noise: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(0)
    kf = AxisKalman(np.full(6, 0.1))
    errors = []
    for k in range(400):
        t = k * 0.012
        truth = np.full(6, 1e-3 * np.sin(2 * np.pi * 0.5 * t))
        kf.update(t, truth + rng.normal(0, noise), declared_variance)
        errors.append(kf.position - truth)
    return np.array(errors[50:])


def test_kalman_uses_each_poses_variance_and_follows_motion() -> None:
    noise = np.array([1e-6, 1e-4, 1e-6, 1e-6, 1e-6, 1e-6])  # axis 1: the weakly observed one
    told = filtered_error(noise ** 2, noise)
    misled = filtered_error(np.full(6, 1e-12), noise)  # a filter that believed every pose exactly
    assert np.std(told[:, 1]) < 0.95 * np.std(misled[:, 1])
    assert np.max(np.abs(told[:, 0])) < 1e-5  # the well-measured axis still follows the motion


def test_pd_velocity_is_limited_and_gains_are_checked() -> None:
    gains = Gains((10.0,) * 6, (0.5,) * 6, (0.01,) * 6)
    v = pd_velocity(np.array([1e-3, -1e-2, 0, 0, 0, 0]), np.zeros(6), gains)
    assert v[0] == pytest.approx(0.01) and v[1] == pytest.approx(-0.01)
    for bad in (Gains((10.0,) * 5, (0.5,) * 6, (0.01,) * 6), Gains((-1.0,) * 6, (0.5,) * 6, (0.01,) * 6),
                Gains((float("nan"),) * 6, (0.5,) * 6, (0.01,) * 6)):
        with pytest.raises(ValueError):
            bad.check()


def test_covariance_is_rotated_into_the_base_frame() -> None:
    covariance = np.diag([1.0, 4.0, 9.0, 1.0, 1.0, 1.0])
    quarter_turn = Mounting((0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2))
    np.testing.assert_allclose(covariance_in_base(covariance, quarter_turn)[:3], [4.0, 1.0, 9.0], atol=1e-12)


def ringing_after_a_move(shaper: InputShaper | None) -> tuple[float, float]:
    """The simulated arm's y after a 1 mm correction sent as velocity, 12 ms per period as the bridge does:
    (std of the ringing after the move, where it ended)."""
    arm, command, ys = Arm(), np.zeros(6), []
    for k in range(150):
        velocity = np.array([0.0, 0.025 if k < 4 else 0.0, 0.0, 0.0, 0.0, 0.0])  # ~1.2 mm in 48 ms
        if shaper is not None:
            velocity = shaper(k * 0.012, velocity)
        command = command + velocity * 0.012
        arm.command = command
        arm.advance(0.012)
        ys.append(arm.position[1])
    settled = np.array(ys[40:])
    return float(np.std(settled)), float(settled[-1])


def test_the_input_shaper_keeps_the_arms_resonance_out_of_the_corrections() -> None:
    raw_ringing, _ = ringing_after_a_move(None)
    shaped_ringing, shaped_end = ringing_after_a_move(InputShaper(zvd_impulses(10.0, 0.05)))
    assert raw_ringing > 50e-6
    assert shaped_ringing < 0.05 * raw_ringing
    assert shaped_end == pytest.approx(1.2e-3, abs=5e-6)  # the whole move, just without the ringing
    for off_tune in (9.0, 11.0):  # the model's frequency 10 % off
        assert ringing_after_a_move(InputShaper(zvd_impulses(off_tune, 0.05)))[0] < 0.1 * raw_ringing
    assert sum(gain for _, gain in zvd_impulses(10.0, 0.05)) == pytest.approx(1.0)
    for bad in ((0.0, 0.05), (10.0, 1.0), (float("nan"), 0.1)):
        with pytest.raises(ValueError):
            zvd_impulses(*bad)


def compensator(ros, **params) -> PdCompensatorNode:
    """The compensator with its loop closed from the first pose: these tests are about the law and its
    inputs; the first-motion check, which needs an arm that answers, is test_calibrate.py's."""
    params = {"first_motion_check": False, **params}
    return ros.add(PdCompensatorNode(context=ros.context,
                                     parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))


def test_before_the_first_motion_check_nothing_but_zeros_leaves(ros) -> None:
    """Check on (the default), a reference 1 mm away, fresh poses, and no arm answering (no robot_state):
    the loop is not closed, whatever the error; only zeros go out, for the bridge to arm on."""
    node = compensator(ros, first_motion_check=True)
    talker = ros.node("talker")
    poses = talker.create_publisher(PoseWithCovarianceStamped, "pose_with_covariance", 10)
    reference = talker.create_publisher(PoseStamped, "reference_pose", 10)
    corrections = []
    talker.create_subscription(TwistStamped, "correction", corrections.append, 100)
    translation = np.array([0.0, 0.0, 0.45])

    @paced
    def publish_pose() -> None:
        pose = pose_stamped(LOOKING_DOWN, translation, Time(nanoseconds=time.time_ns()).to_msg(), "gauge")
        poses.publish(pose_with_covariance(pose, np.diag([1e-10] * 3 + [1e-8] * 3)))

    assert ros.spin_until(lambda: node.last_measured is not None, 5.0, action=publish_pose)
    reference.publish(pose_stamped(LOOKING_DOWN, translation + [1e-3, 0, 0], talker.get_clock().now().to_msg(),
                                   "gauge"))
    assert ros.spin_until(lambda: node.reference is not None, 5.0, action=publish_pose)
    count = len(corrections)
    assert ros.spin_until(lambda: len(corrections) > count + 50, 5.0, action=publish_pose)
    assert all(not any((m.twist.linear.x, m.twist.linear.y, m.twist.linear.z)) for m in corrections)
    assert node._first_motion_state() == "waiting for the arm"


def test_a_reference_is_taken_as_it_comes_not_at_the_executors_housekeeping(ros) -> None:
    """reference_pose is served with the poses (direct_input.py), not by the executor, which the loop
    processes run only every 50 ms: a planned step started up to four 83.3 Hz periods late. Here the
    node's own input is pumped and its executor never spun: the reference must still be taken."""
    node = compensator(ros)
    talker = ros.node("talker")
    poses = talker.create_publisher(PoseWithCovarianceStamped, "pose_with_covariance", 10)
    reference = talker.create_publisher(PoseStamped, "reference_pose", 10)
    translation = np.array([0.0, 0.0, 0.45])

    @paced
    def publish_pose() -> None:
        pose = pose_stamped(LOOKING_DOWN, translation, Time(nanoseconds=time.time_ns()).to_msg(), "gauge")
        poses.publish(pose_with_covariance(pose, np.diag([1e-10] * 3 + [1e-8] * 3)))

    assert ros.spin_until(lambda: node.last_measured is not None and node.count_subscribers("reference_pose"),
                          5.0, action=publish_pose)
    reference.publish(pose_stamped(LOOKING_DOWN, translation + [1e-3, 0, 0], talker.get_clock().now().to_msg(),
                                   "gauge"))
    deadline = time.monotonic() + 5.0
    while node.reference is None and time.monotonic() < deadline:
        node.pump(0.01)
    assert node.reference is not None


@pytest.mark.parametrize("law", ["pd", "modal"])
def test_stale_pose_gives_zero_correction_within_three_periods(ros, law: str) -> None:
    node = compensator(ros, max_pose_age=0.036, control_law=law)
    talker = ros.node("talker")
    poses = talker.create_publisher(PoseWithCovarianceStamped, "pose_with_covariance", 10)
    reference = talker.create_publisher(PoseStamped, "reference_pose", 10)
    corrections = []
    talker.create_subscription(TwistStamped, "correction", lambda m: corrections.append((time.monotonic(), m)), 100)
    translation = np.array([0.0, 0.0, 0.45])
    covariance = np.diag([1e-10] * 3 + [1e-8] * 3)

    @paced
    def publish_pose() -> None:
        pose = pose_stamped(LOOKING_DOWN, translation, Time(nanoseconds=time.time_ns()).to_msg(), "gauge")
        poses.publish(pose_with_covariance(pose, covariance))

    assert ros.spin_until(lambda: node.count_publishers("reference_pose") and node.count_subscribers("correction"), 5)
    assert ros.spin_until(lambda: node.last_measured is not None, 5.0, action=publish_pose)  # checked against it
    reference.publish(pose_stamped(LOOKING_DOWN, translation + [1e-3, 0, 0], talker.get_clock().now().to_msg(),
                                   "gauge"))
    assert ros.spin_until(lambda: node.reference is not None, 5.0, action=publish_pose)
    moving = lambda: any(abs(m.twist.linear.x) > 0 for _, m in corrections)  # noqa: E731
    assert ros.spin_until(moving, 5.0, action=publish_pose)
    stopped_at = time.monotonic()  # the poses stop (the estimator rejects every profile, say)
    ros.spin_until(lambda: any(t > stopped_at + 0.1 for t, _ in corrections), 2.0)
    after = [(t - stopped_at, m.twist.linear.x) for t, m in corrections if t > stopped_at]
    first_zero = next(t for t, vx in after if vx == 0.0)
    assert first_zero <= 3 * 0.012 + 0.02  # three control periods (and one watchdog tick)
    assert all(vx == 0.0 for t, vx in after if t > first_zero)


def test_gains_out_of_range_are_rejected_at_run_time(ros) -> None:
    node = compensator(ros)
    result = node.set_parameters([Parameter("kp", value=[1.0] * 5)])[0]
    assert not result.successful and "six values" in result.reason
    assert not node.set_parameters([Parameter("kd", value=[9.0] * 6)])[0].successful
    assert node.set_parameters([Parameter("kp", value=[3.0] * 6)])[0].successful and node.gains.kp == (3.0,) * 6


def reference_kalman_step(x: np.ndarray, p: np.ndarray, q: np.ndarray, dt: float, z: np.ndarray,
                          variance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The textbook form, six batched 2 x 2 matrices: what AxisKalman's element-wise update must equal."""
    f = np.array([[1.0, dt], [0.0, 1.0]])
    qm = np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
    x = x @ f.T
    p = f @ p @ f.T + q[:, None, None] * qm
    k = p[:, :, 0] / (p[:, 0, 0] + variance)[:, None]
    x = x + k * (z - x[:, 0])[:, None]
    return x, p - k[:, :, None] * p[:, None, 0, :]


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_kalman_update_equals_the_matrix_form(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.01, 50.0, 6)
    kf = AxisKalman(q)
    t, z = 0.0, rng.normal(0, 1e-3, 6)
    variance = rng.uniform(1e-12, 1e-8, 6)
    kf.update(t, z, variance)
    x = np.column_stack([z, np.zeros(6)])
    p = np.zeros((6, 2, 2))
    p[:, 0, 0], p[:, 1, 1] = variance, 1e-2
    for _ in range(30):
        dt = rng.uniform(1e-4, 0.02)
        t += dt
        z, variance = rng.normal(0, 1e-3, 6), rng.uniform(1e-12, 1e-8, 6)
        kf.update(t, z, variance)
        x, p = reference_kalman_step(x, p, q, dt, z, variance)
        np.testing.assert_allclose(kf.position, x[:, 0], rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(kf.velocity, x[:, 1], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(np.stack([kf.p00, kf.p01, kf.p11], axis=1), p[:, [0, 0, 1], [0, 1, 1]],
                                   rtol=1e-9, atol=1e-20)


@pytest.mark.parametrize("damage", ["zero quaternion", "nan position", "inf covariance", "truncated",
                                    "negative covariance", "zero covariance", "1e300 m away"])
def test_a_corrupt_pose_moves_nothing_and_the_node_goes_on(ros, damage) -> None:
    from rclpy.serialization import serialize_message

    node = compensator(ros, max_pose_age=1.0)
    node.reference = np.zeros(6)
    stamp = Time(nanoseconds=time.time_ns()).to_msg()
    good = pose_with_covariance(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge"),
                                np.diag([1e-10] * 3 + [1e-8] * 3))
    bad = pose_with_covariance(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge"),
                               np.diag([1e-10] * 3 + [1e-8] * 3))
    if damage == "zero quaternion":
        o = bad.pose.pose.orientation
        o.x = o.y = o.z = o.w = 0.0
    elif damage == "nan position":
        bad.pose.pose.position.y = float("nan")
    elif damage == "inf covariance":
        bad.pose.covariance[0] = float("inf")
    elif damage == "negative covariance":  # these two, and the next, poisoned the filter for good (fuzzed)
        bad.pose.covariance[14] = -1e-10
    elif damage == "zero covariance":
        bad.pose.covariance = [0.0] * 36
    elif damage == "1e300 m away":
        bad.pose.pose.position.y = 1e300
    data = serialize_message(bad)
    node._on_pose(data[:40] if damage == "truncated" else data)  # the subscription's callback, as DDS calls it
    assert node.poses == 0 and node.corrections == 0  # not taken, nothing sent
    node._on_pose(serialize_message(good))
    assert node.poses == 1 and node.corrections == 1  # and the next good one is
    assert np.all(np.isfinite(node.last_error))


def test_a_corrupt_reference_is_ignored(ros) -> None:
    node = compensator(ros)
    stamp = Time(nanoseconds=time.time_ns()).to_msg()
    node._on_reference(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge"))
    assert node.reference is None  # nothing measured yet to check it against
    node.last_measured = node._vector(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge").pose)
    node._on_reference(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge"))
    kept = node.reference.copy()
    bad = pose_stamped(LOOKING_DOWN, np.array([0.0, float("nan"), 0.45]), stamp, "gauge")
    node._on_reference(bad)
    np.testing.assert_array_equal(node.reference, kept)


# margins of 30 ms and more either side of each bound: a loaded CI runner stalled 40 ms between stamping and
# taking a pose 10 ms inside a 50 ms window
@pytest.mark.parametrize("ahead, taken", [(3600.0, False), (0.05, False), (0.005, True), (-0.05, True),
                                          (-0.5, False)])
def test_a_pose_is_taken_only_within_its_two_sided_age_window(ros, ahead: float, taken: bool) -> None:
    """A pose stamped in the future is no fresher than a stale one; one taken stays usable for what is
    left of max_pose_age, counted on the node's monotonic clock, never for longer."""
    from rclpy.serialization import serialize_message

    node = compensator(ros, max_pose_age=0.2, max_future=0.02)
    node.reference = np.zeros(6)
    pose = pose_with_covariance(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), Time().to_msg(), "gauge"),
                                np.diag([1e-10] * 3 + [1e-8] * 3))
    pose.header.stamp = Time(nanoseconds=int((time.time() + ahead) * 1e9)).to_msg()  # stamped last
    received = time.monotonic()
    node._on_pose(serialize_message(pose))
    assert (node.poses, node.corrections) == ((1, 1) if taken else (0, 0))
    assert node.pose_fresh_until <= (received + 0.2 if taken else -np.inf) + 1e-3
    if not taken and ahead > 0:
        assert node.refused["future"] == 1


def test_a_pose_or_reference_in_another_frame_or_not_unit_length_is_refused(ros) -> None:
    from rclpy.serialization import serialize_message

    node = compensator(ros)
    node.reference = np.zeros(6)
    stamp = Time(nanoseconds=time.time_ns()).to_msg()
    covariance = np.diag([1e-10] * 3 + [1e-8] * 3)
    tool = pose_with_covariance(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "tool"), covariance)
    tiny = pose_with_covariance(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge"), covariance)
    o = tiny.pose.pose.orientation
    o.x, o.y, o.z, o.w = 0.0, 0.0, 0.0, 1e-30
    for bad in (tool, tiny):
        node._on_pose(serialize_message(bad))
    assert node.poses == 0 and node.refused["frame"] == 1 and node.refused["orientation"] == 1
    node.reference = None
    node.last_measured = node._vector(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge").pose)
    for rogue in (pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "tool"),
                  pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), Time(seconds=1).to_msg(), "gauge"),
                  pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]),
                               Time(nanoseconds=time.time_ns() + 3600 * 10 ** 9).to_msg(), "gauge"),
                  pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45 + 0.05]), stamp, "gauge")):  # a 5 cm jump
        node._on_reference(rogue)
    assert node.reference is None and node.refused["reference"] == 4
    node._on_reference(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.452]), stamp, "gauge"))  # 2 mm: taken
    assert node.reference is not None


def test_a_pose_less_precise_than_the_compensator_needs_steers_nothing(ros) -> None:
    """The precision decision is the consumer's: a pose whose covariance says its position is known to worse
    than max_position_sigma is refused and counted; a precise one right after it is taken."""
    from rclpy.serialization import serialize_message

    node = compensator(ros, max_position_sigma=2e-4)
    node.reference = np.zeros(6)
    stamp = Time(nanoseconds=time.time_ns()).to_msg()
    position = np.array([0.0, 0.0, 0.45])
    vague = pose_with_covariance(pose_stamped(LOOKING_DOWN, position, stamp, "gauge"),
                                 np.diag([1e-10, 1e-10, 9e-8] + [1e-8] * 3))  # z std 0.3 mm
    node._on_pose(serialize_message(vague))
    assert (node.poses, node.corrections, node.refused["imprecise"]) == (0, 0, 1)
    precise = pose_with_covariance(pose_stamped(LOOKING_DOWN, position, stamp, "gauge"),
                                   np.diag([1e-10] * 3 + [1e-8] * 3))
    node._on_pose(serialize_message(precise))
    assert (node.poses, node.corrections) == (1, 1)


def test_a_covariance_near_the_float_limit_is_refused_as_imprecise(ros) -> None:
    """Found by the fuzzer: finite entries whose squares overflow must not raise inside the callback."""
    from rclpy.serialization import serialize_message

    node = compensator(ros)
    node.reference = np.zeros(6)
    stamp = Time(nanoseconds=time.time_ns()).to_msg()
    vast = pose_with_covariance(pose_stamped(LOOKING_DOWN, np.array([0.0, 0.0, 0.45]), stamp, "gauge"),
                                np.diag([1e300, 1e-10, 1e-10] + [1e-8] * 3))
    node._on_pose(serialize_message(vast))
    assert (node.poses, node.refused["imprecise"]) == (0, 1)


def controllers_clock_talker(ros, node):
    """A node publishing poses, robot_state and the reference to `node`, and the corrections it gets back,
    once `node` hears robot_state and sends corrections."""
    talker = ros.node("talker")
    poses = talker.create_publisher(PoseWithCovarianceStamped, "pose_with_covariance", 10)
    states = talker.create_publisher(PoseStamped, "robot_state", 10)
    reference = talker.create_publisher(PoseStamped, "reference_pose", 10)
    corrections: list = []
    talker.create_subscription(TwistStamped, "correction", corrections.append, 100)
    assert ros.spin_until(lambda: node.count_publishers("robot_state") and node.count_subscribers("correction"), 5)
    return talker, poses, states, reference, corrections


def test_on_the_controllers_clock_each_state_gets_one_correction_from_the_poses_before_it(ros) -> None:
    """period_clock robot_state: poses alone drive the law on their own clock until the controller's STATEs
    flow (the bridge arms on such a correction); from then on nothing leaves on a pose, and each robot_state
    gets exactly one correction, made from the poses since the last one and stamped with the newest of them."""
    node = compensator(ros, control_law="modal", period_clock="robot_state", control_period=0.004)
    talker, poses, states, reference, corrections = controllers_clock_talker(ros, node)
    translation = np.array([0.0, 0.0, 0.45])
    covariance = np.diag([1e-10] * 3 + [1e-8] * 3)

    def send_poses(count: int) -> int:
        """`count` fresh poses, each taken before the next is sent; the newest one's stamp (ns)."""
        for _ in range(count):
            taken, stamp = node.poses, time.time_ns()
            pose = pose_stamped(LOOKING_DOWN, translation, Time(nanoseconds=stamp).to_msg(), "gauge")
            poses.publish(pose_with_covariance(pose, covariance))
            assert ros.spin_until(lambda: node.poses > taken, 5.0)
        return stamp

    send_poses(1)
    reference.publish(pose_stamped(LOOKING_DOWN, translation + [1e-3, 0, 0], talker.get_clock().now().to_msg(),
                                   "gauge"))
    assert ros.spin_until(lambda: node.reference is not None, 5.0)
    before_states = node.corrections
    send_poses(20)  # ~20 poses, a few control periods of 4 ms: the poses' clock
    assert ros.spin_until(lambda: len(corrections) >= before_states, 5.0)
    assert node.corrections > before_states
    for _ in range(5):
        heard = node.robot_heard
        states.publish(pose_stamped(np.eye(3), np.zeros(3), talker.get_clock().now().to_msg(), "base"))
        assert ros.spin_until(lambda: node.robot_heard > heard, 5.0)
        made = node.corrections
        newest = send_poses(3)
        assert node.corrections == made, "a correction left on a pose, not on the controller's clock"
        count = len(corrections)
        states.publish(pose_stamped(np.eye(3), np.zeros(3), talker.get_clock().now().to_msg(), "base"))
        assert ros.spin_until(lambda: node.corrections > made, 5.0)
        assert node.corrections == made + 1
        assert ros.spin_until(lambda: any(stamp_ns(m) == newest for m in corrections[count:]), 5.0)
        reply = next(m for m in corrections[count:] if stamp_ns(m) == newest)
        assert reply.twist.linear.x > 0  # towards the reference


def stamp_ns(message) -> int:
    return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec


def test_on_the_controllers_clock_the_pose_a_state_triggered_answers_the_next_state(ros) -> None:
    """A profiler the controller triggers: one pose a period, stamped at its STATE's tick. However soon that
    pose is estimated, and however late the STATE is read, the STATE is answered from the pose before it;
    its own pose answers the next one (loop_delay counts that period)."""
    period = 0.004
    node = compensator(ros, control_law="modal", period_clock="robot_state", control_period=period, max_pose_age=1.0)
    talker, poses, states, reference, corrections = controllers_clock_talker(ros, node)
    translation = np.array([0.0, 0.0, 0.45])
    covariance = np.diag([1e-10] * 3 + [1e-8] * 3)
    start = time.time_ns() - 40_000_000  # every stamp below in the past, and fresh (max_pose_age) for a second
    tick = int(period * 1e9)

    def send(publisher, message, count) -> None:
        before = count()
        publisher.publish(message)
        assert ros.spin_until(lambda: count() > before, 5.0)

    def pose_at(k: int):
        return pose_with_covariance(pose_stamped(LOOKING_DOWN, translation, Time(nanoseconds=start + k * tick)
                                                 .to_msg(), "gauge"), covariance)

    def state_at(k: int, late_ns: int = 0):
        return pose_stamped(np.eye(3), np.zeros(3), Time(nanoseconds=start + k * tick + late_ns).to_msg(), "base")

    first = 3  # poses on their own clock, one a period, until STATEs flow
    for k in range(first):
        send(poses, pose_at(k), lambda: node.poses)
    reference.publish(pose_stamped(LOOKING_DOWN, translation + [1e-3, 0, 0], talker.get_clock().now().to_msg(),
                                   "gauge"))
    assert ros.spin_until(lambda: node.reference is not None, 5.0)
    for k in range(first, first + 5):
        send(poses, pose_at(k), lambda: node.poses)  # this STATE's own pose, estimated before the STATE is read
        count = len(corrections)
        send(states, state_at(k, late_ns=tick // 3), lambda: node.robot_heard)  # read a third of a period late
        assert ros.spin_until(lambda: len(corrections) > count, 5.0)
        if k > first:  # (the first STATE has no earlier pose of its own: the law coasts)
            assert stamp_ns(corrections[-1]) == start + (k - 1) * tick, "answered with the pose it triggered"
    # what the pose was worth at its STATE, for loop_delay's commissioning: a period and the third read late;
    # still told once the poses have gone stale and the law has forgotten them (the run is over)
    reports: list[tuple[str, dict]] = []
    talker.create_subscription(DiagnosticArray, "/diagnostics", lambda m: reports.extend(
        (status.message, {v.key: v.value for v in status.values})
        for status in m.status if status.hardware_id == "pd_compensator"), 10)
    assert ros.spin_until(lambda: any(message.startswith("pose stale") for message, _ in reports), 5.0)
    stale = next(values for message, values in reports if message.startswith("pose stale"))
    age = float(stale["pose_age_at_state_ms"])
    assert age == pytest.approx(1e3 * (period + period / 3), abs=0.01)
