"""pose_estimator with real rclpy: poses from rendered profiles, and every bad input -> no pose, a
diagnostic with the reason, and a node that still works afterwards."""
import subprocess
import sys

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2, PointField

from profile_pose_ros.core import Gauge, GaugeError, pose_error, render_profile, sample_pose, true_corners
from profile_pose_ros.core.design.gauge_design import heightfield_gauge
from profile_pose_ros.core.model.rotation import so3_log
from profile_pose_ros.nodes.messages import cloud_from_points, rotation_translation
from profile_pose_ros.nodes.pose_estimator import PoseEstimatorNode

from conftest import PAPER_GAUGE, on_a_table


class Probe:
    """The test's side of the graph: publishes profiles, records poses and diagnostics."""

    def __init__(self, ros, **overrides):
        params = [Parameter("diagnostics_period", value=0.05)]
        params += [Parameter(k, value=v) for k, v in overrides.items()]
        self.ros = ros
        self.estimator = ros.add(PoseEstimatorNode(context=ros.context, parameter_overrides=params))
        node = ros.node("probe")
        self.node = node
        self.publisher = node.create_publisher(PointCloud2, "profile", qos_profile_sensor_data)
        self.poses, self.covariances, self.diagnostics = [], [], []
        node.create_subscription(PoseStamped, "pose", self.poses.append, 10)
        node.create_subscription(PoseWithCovarianceStamped, "pose_with_covariance", self.covariances.append, 10)
        node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        assert ros.spin_until(lambda: self.publisher.get_subscription_count() > 0), "estimator never subscribed"
        self.sequence = 0

    def stamp(self):
        self.sequence += 1
        return self.node.get_clock().now().to_msg()

    def send_until(self, msg, condition, timeout=10.0):
        return self.ros.spin_until(condition, timeout, action=lambda: self.publisher.publish(msg))

    def diagnostic_value(self, key):
        """The value under `key` in the estimator's latest status received, None before one."""
        values = [dict((kv.key, kv.value) for kv in s.values) for a in self.diagnostics for s in a.status
                  if s.name.startswith("pose_estimator")]
        return values[-1].get(key) if values else None

    def pose_for(self, stamp):
        for pose in self.poses:
            if pose.header.stamp == stamp:
                return pose
        return None

    def errors_seen(self, fragment):
        return [s for a in self.diagnostics for s in a.status
                if s.level == DiagnosticStatus.ERROR and fragment in s.message]


def test_rendered_profiles_yield_poses_with_their_stamps(ros, gauge, rng):
    probe = Probe(ros)
    for _ in range(15):
        rotation, t = sample_pose(gauge, rng)
        stamp = probe.stamp()
        msg = cloud_from_points(render_profile(gauge, rotation, t), stamp, "profiler")
        assert probe.send_until(msg, lambda: probe.pose_for(stamp) is not None), "no pose"
        pose = probe.pose_for(stamp)
        assert pose.header.frame_id == "gauge"
        est_r, est_t = rotation_translation(pose.pose)
        position, angle = pose_error(est_r, est_t, rotation, t)
        assert position < 2e-6 and angle < 10e-6  # float32 rounding of the profile is all that is left
    assert ros.spin_until(lambda: any(c.header.stamp == stamp for c in probe.covariances))
    covariance = np.array(next(c for c in probe.covariances if c.header.stamp == stamp).pose.covariance)
    assert np.all(np.linalg.eigvalsh(covariance.reshape(6, 6)) > 0)
    assert ros.spin_until(lambda: any(s.level == DiagnosticStatus.OK for a in probe.diagnostics for s in a.status))


def _cloud(points=None, **changes):
    msg = cloud_from_points(points if points is not None else np.column_stack([np.linspace(-0.05, 0.05, 500),
                                                                              np.full(500, 0.4)]),
                            PointCloud2().header.stamp, "profiler")
    for key, value in changes.items():
        setattr(msg, key, value)
    return msg


def _fields(*spec):
    return [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in spec]


def _noise(rng):
    x = np.linspace(-0.12, 0.12, 3200)
    return np.column_stack([x, 0.4 + rng.uniform(-0.02, 0.02, len(x))])


def _occluded(gauge, rng):
    rotation, t = sample_pose(gauge, rng)
    profile = render_profile(gauge, rotation, t)
    profile[profile[:, 0] > true_corners(gauge, rotation, t)[3, 0] + 1e-3, 1] = np.nan
    return profile


def _other_gauge(gauge, rng):
    other = heightfield_gauge("other", 0.12, 0.10, [-0.045, -0.02, 0.003, 0.025, 0.046],
                              np.radians([-8.0, 6.0, 12.0, -4.0, -9.0]), [-0.7, 0.75, -0.7, 0.8, -0.75, 0.7])
    return render_profile(other, *sample_pose(other, rng), noise_std=5e-6, rng=rng)


def _with_raw(points, column, value, rows=slice(None)):
    """The cloud of `points` with raw float32 values written into one column of some rows (the encoder would
    sanitise them)."""
    msg = _cloud(points)
    raw = np.frombuffer(bytes(msg.data), dtype="<f4").copy().reshape(-1, 3)
    raw[rows, column] = value
    msg.data = raw.tobytes()
    return msg


BAD_INPUTS = {
    "empty cloud": (lambda g, r: _cloud(width=0, row_step=0, data=b""), "empty cloud"),
    "all NaN": (lambda g, r: _cloud(np.full((500, 2), np.nan)), "are invalid (NaN or +-inf)"),
    "row_step mismatch": (lambda g, r: _cloud(row_step=7), "row_step 7"),
    "data length mismatch": (lambda g, r: _cloud(width=501), "row_step"),
    "missing z field": (lambda g, r: _cloud(fields=_fields(("x", 0, 7), ("y", 4, 7))), "field 'z' is missing"),
    "missing x field": (lambda g, r: _cloud(fields=_fields(("y", 4, 7), ("z", 8, 7))), "field 'x' is missing"),
    "float64 field": (lambda g, r: _cloud(fields=_fields(("x", 0, 8), ("z", 8, 7))), "is FLOAT64"),
    "big-endian": (lambda g, r: _cloud(is_bigendian=True), "big-endian"),
    "inf everywhere": (lambda g, r: _with_raw(None, 2, np.inf), "+-inf"),
    "fewer corners": (lambda g, r: _cloud(_occluded(g, r)), "found 3 corners"),
    "another gauge": (lambda g, r: _cloud(_other_gauge(g, r)), "does not match gauge"),
    "pure noise": (lambda g, r: _cloud(_noise(r)), "corner detection"),
    "wrong frame": (lambda g, r: _cloud(header=PointCloud2().header.__class__(frame_id="camera")), "frame_id"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_gives_no_pose_a_reason_and_a_live_node(ros, gauge, rng, case):
    make, fragment = BAD_INPUTS[case]
    probe = Probe(ros)
    bad = make(gauge, rng)
    assert probe.send_until(bad, lambda: probe.errors_seen(fragment), timeout=10.0), (
        f"no ERROR diagnostic containing {fragment!r}; saw "
        f"{[s.message for a in probe.diagnostics for s in a.status][-3:]}")
    assert probe.poses == [] and probe.covariances == []
    assert probe.estimator.rejected >= 1 and probe.estimator.published == 0
    # the node is still working
    rotation, t = sample_pose(gauge, rng)
    stamp = probe.stamp()
    good = cloud_from_points(render_profile(gauge, rotation, t), stamp, "profiler")
    assert probe.send_until(good, lambda: probe.pose_for(stamp) is not None)


def test_a_profile_with_rep117_infinities_for_invalid_points_gives_the_pose_of_its_nan_twin(ros, gauge, rng):
    """A profiler driver that publishes +inf ("no return", REP-117) where this package's publishes NaN: the same
    pose, to the bit."""
    probe = Probe(ros)
    rotation, t = sample_pose(gauge, rng)
    profile = render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng)
    unlit = np.isnan(profile).any(axis=1)
    assert unlit.sum() > 100
    poses = []
    for value in (np.nan, np.inf):
        stamp = probe.stamp()
        msg = _with_raw(profile, 2, value, rows=unlit)
        msg.header.stamp = stamp
        assert probe.send_until(msg, lambda: probe.pose_for(stamp) is not None), "no pose"
        poses.append(rotation_translation(probe.pose_for(stamp).pose))
    assert np.array_equal(poses[0][0], poses[1][0]) and np.array_equal(poses[0][1], poses[1][1])


def test_a_profile_that_also_sees_the_table_gives_the_gauges_pose(ros, gauge, rng):
    """The laser line meets the plane the gauge stands on either side of it: the node's pose is the gauge's."""
    probe = Probe(ros)
    rotation, t = sample_pose(gauge, rng)
    profile = on_a_table(gauge, rotation, t, render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng), 0.01)
    stamp = probe.stamp()
    assert probe.send_until(cloud_from_points(profile, stamp, "profiler"), lambda: probe.pose_for(stamp) is not None)
    position, angle = pose_error(*rotation_translation(probe.pose_for(stamp).pose), rotation, t)
    assert position < 0.5e-3 and angle < 2e-3
    probe.diagnostics.clear()  # counted, so that an engineer sees the table in view (and what it costs)
    assert ros.spin_until(lambda: int(probe.diagnostic_value("profiles_background_cut") or 0) >= 1)


def test_spiky_profiles_never_give_a_wrong_pose(ros, gauge, rng):
    probe = Probe(ros)
    checked = 0
    for _ in range(10):
        rotation, t = sample_pose(gauge, rng)
        stamp = probe.stamp()
        profile = render_profile(gauge, rotation, t, noise_std=5e-6, spike_fraction=0.01, rng=rng)
        msg = cloud_from_points(profile, stamp, "profiler")
        got = probe.send_until(msg, lambda: any(c.header.stamp == stamp for c in probe.covariances), timeout=1.0)
        if not got:
            continue  # rejected is acceptable; a wrong pose is not
        checked += 1
        pose = next(c for c in probe.covariances if c.header.stamp == stamp)
        est_r, est_t = rotation_translation(pose.pose.pose)
        d = np.concatenate([t - est_t, so3_log(rotation @ est_r.T)])
        nees = d @ np.linalg.solve(np.array(pose.pose.covariance).reshape(6, 6), d)
        assert nees < 30.0  # chi-square(6) beyond 30 happens with probability 4e-5
    assert checked >= 8  # robust detection keeps nearly all of them


def test_parameters_are_validated_at_run_time(ros):
    probe = Probe(ros)
    node = probe.estimator
    assert not node.set_parameters([Parameter("refine_weighting", value="magic")])[0].successful
    assert not node.set_parameters([Parameter("max_reprojection_error", value=5.0)])[0].successful
    assert not node.set_parameters([Parameter("gauge_file", value="/tmp/x.yaml")])[0].successful  # read-only
    assert node.set_parameters([Parameter("rdp_epsilon", value=5e-4)])[0].successful
    assert node.options.corners.rdp_epsilon == 5e-4
    descriptor = node.describe_parameter("max_reprojection_error")
    assert descriptor.floating_point_range[0].to_value == 0.01 and descriptor.description


def test_missing_or_invalid_gauge_refuses_to_start(ros, tmp_path):
    with pytest.raises(GaugeError, match="nope.yaml: not found"):
        PoseEstimatorNode(context=ros.context,
                          parameter_overrides=[Parameter("gauge_file", value=str(tmp_path / "nope.yaml"))])
    bad = tmp_path / "bad_gauge.yaml"
    document = yaml.safe_load(PAPER_GAUGE.read_text())
    document["gauge"]["faces"][0]["normal"][2] *= -1  # face 0 now faces away from the sensor
    bad.write_text(yaml.safe_dump(document))
    result = subprocess.run([sys.executable, "-m", "profile_pose_ros.nodes.pose_estimator", "--ros-args",
                             "-p", f"gauge_file:={bad}"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert "bad_gauge.yaml" in result.stderr and "face 0" in result.stderr and "nz > 0" in result.stderr
    assert Gauge.from_yaml(PAPER_GAUGE).n_ridges == 5


def test_params_file_loads_through_rcl(ros):
    path = PAPER_GAUGE.parent / "pose_estimator.yaml"
    node = ros.add(PoseEstimatorNode(context=ros.context, cli_args=["--ros-args", "--params-file", str(path)]))
    assert node.get_parameter("rdp_epsilon").value == 0.0003
    assert node.get_parameter("max_face_angle").value == 1.2217
    assert node.gauge.name == "paper_n5"


def test_dense_refinement_through_the_node(ros, gauge, rng):
    probe = Probe(ros, refine_model="dense")
    rotation, t = sample_pose(gauge, rng)
    stamp = probe.stamp()
    msg = cloud_from_points(render_profile(gauge, rotation, t), stamp, "profiler")
    assert probe.send_until(msg, lambda: probe.pose_for(stamp) is not None)
    est_r, est_t = rotation_translation(probe.pose_for(stamp).pose)
    position, angle = pose_error(est_r, est_t, rotation, t)
    assert position < 2e-6 and angle < 10e-6
    assert not probe.estimator.set_parameters([Parameter("refine_model", value="magic")])[0].successful


def test_profiles_dropped_from_a_full_queue_are_counted_and_reported(ros, gauge, rng):
    """A burst while the node is busy overflows its queue (oldest dropped, no middleware event): every
    profile is either estimated or counted in profiles_lost, and the diagnostics warn."""
    probe = Probe(ros, queue_depth=5)
    msg = cloud_from_points(render_profile(gauge, *sample_pose(gauge, rng)), probe.stamp(), "profiler")
    estimator, sent = probe.estimator, []

    def publish():
        probe.publisher.publish(msg)
        sent.append(1)
    assert ros.spin_until(lambda: estimator.received > 0, action=publish), "no profile reached the estimator"
    # every warm-up profile accounted for, so that none is still in flight when the burst starts
    assert ros.spin_until(lambda: estimator.received + estimator.gaps.missed >= len(sent))
    received, lost = estimator.received, estimator.gaps.missed
    for _ in range(40):  # without spinning: the estimator cannot take any of them yet
        probe.publisher.publish(msg)
    assert ros.spin_until(lambda: estimator.received - received + estimator.gaps.missed - lost >= 40)
    burst_received, burst_lost = estimator.received - received, estimator.gaps.missed - lost
    assert burst_received + burst_lost == 40 and burst_lost >= 30, (burst_received, burst_lost)
    assert ros.spin_until(lambda: any(
        s.level == DiagnosticStatus.WARN and "profiles lost before processing" in s.message
        and any(kv.key == "profiles_lost" and int(kv.value) >= burst_lost for kv in s.values)
        for a in probe.diagnostics for s in a.status))


def test_a_node_behind_skips_profiles_older_than_max_profile_age(ros, gauge, rng):
    probe = Probe(ros, max_profile_age=0.05)
    points = render_profile(gauge, *sample_pose(gauge, rng))
    old = probe.node.get_clock().now().nanoseconds - 200_000_000  # 0.2 s late: the compensator would refuse it
    old_stamp = cloud_from_points(points, probe.stamp(), "profiler").header.stamp
    old_stamp.sec, old_stamp.nanosec = divmod(old, 1_000_000_000)
    assert probe.send_until(cloud_from_points(points, old_stamp, "profiler"), lambda: probe.estimator.skipped >= 3)
    assert probe.pose_for(old_stamp) is None and probe.estimator.published == 0
    assert ros.spin_until(lambda: any(s.level == DiagnosticStatus.WARN and "older than max_profile_age" in s.message
                                      for a in probe.diagnostics for s in a.status))
    fresh = probe.stamp()
    assert probe.send_until(cloud_from_points(points, fresh, "profiler"), lambda: probe.pose_for(fresh) is not None)
    # 0 (the default) never skips: a bag replayed into a live node carries the recording's stamps
    assert probe.estimator.set_parameters([Parameter("max_profile_age", value=0.0)])[0].successful
    assert probe.send_until(cloud_from_points(points, old_stamp, "profiler"),
                            lambda: probe.pose_for(old_stamp) is not None)


def test_faces_too_narrow_at_the_profiles_pitch_are_reported_while_min_segment_points_is_set(ros, gauge, rng):
    """The paper gauge's inner faces span 15.6-16.8 mm of its profiles: 208-225 points at the 0.075 mm pitch. Read
    from the first profile, the pitch makes min_segment_points 160 name them all (fewer than 1.5 x 160 points each)
    in diagnostics for as long as it is set, and 20 none."""
    probe = Probe(ros)
    narrow_faces = lambda: probe.diagnostic_value("narrow_faces")  # noqa: E731
    assert ros.spin_until(lambda: narrow_faces() == "unknown before the first profile"), narrow_faces()
    stamp = probe.stamp()
    profile = cloud_from_points(render_profile(gauge, *sample_pose(gauge, rng)), stamp, "profiler")
    assert probe.send_until(profile, lambda: probe.pose_for(stamp) is not None)
    probe.diagnostics.clear()
    assert ros.spin_until(lambda: narrow_faces() == "none"), narrow_faces()
    assert probe.estimator.set_parameters([Parameter("min_segment_points", value=160)])[0].successful
    probe.diagnostics.clear()
    assert ros.spin_until(lambda: narrow_faces() not in (None, "none")), narrow_faces()
    named = narrow_faces()
    assert "pitch of 0.075 mm" in named and "face 1 as little as" in named and "face 4 as little as" in named, named
    assert probe.estimator.set_parameters([Parameter("min_segment_points", value=20)])[0].successful
    probe.diagnostics.clear()
    assert ros.spin_until(lambda: narrow_faces() == "none"), narrow_faces()


def test_corners_too_weak_for_min_corner_angle_are_reported_while_it_is_set(ros):
    """The paper gauge's corners bend by 56-62 deg in its profiles: at min_corner_angle 0.5 rad (28.6 deg, half
    of 57.3) its two end corners are named, in diagnostics for as long as the setting holds, and none at 5 deg."""
    probe = Probe(ros)
    weak_corners = lambda: probe.diagnostic_value("weak_corners")  # noqa: E731
    assert ros.spin_until(lambda: weak_corners() == "none"), weak_corners()
    assert probe.estimator.set_parameters([Parameter("min_corner_angle", value=0.5)])[0].successful
    probe.diagnostics.clear()
    assert ros.spin_until(lambda: weak_corners() not in (None, "none")), weak_corners()
    named = weak_corners()
    assert "faces 0/1 as little as 56.3 deg" in named and "faces 4/5" in named and "faces 1/2" not in named, named
    assert probe.estimator.set_parameters([Parameter("min_corner_angle", value=0.0873)])[0].successful
    probe.diagnostics.clear()
    assert ros.spin_until(lambda: weak_corners() == "none"), weak_corners()
