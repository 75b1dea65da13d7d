"""TF and markers for viewers: the estimated gauge -> profiler transform on /tf, the gauge's place on
/tf_static, and a MarkerArray whose geometry is the gauge model's and whose profile lies on the gauge."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from profile_pose_ros.core import pose_error, render_profile, sample_pose
from profile_pose_ros.core.model.rotation import rotation_from_quaternion_xyzw, so3_exp
from profile_pose_ros.core.model.scene import gauge_triangles, profile_in_gauge
from profile_pose_ros.nodes.messages import cloud_from_points
from profile_pose_ros.nodes.pd_compensator import PdCompensatorNode
from profile_pose_ros.nodes.pose_estimator import PoseEstimatorNode
from profile_pose_ros.nodes.scene_messages import MARKER_QOS, TF_QOS, TF_STATIC_QOS


@pytest.mark.parametrize("package, name", [("tf2_msgs", "TFMessage"), ("tf2_msgs", "TF2Error"),
                                           ("visualization_msgs", "MarkerArray")])
def test_interfaces_have_jazzys_type_hashes(package, name):
    """tf2_msgs is built from its definition at set-up (no wheel): only the same type hash as Jazzy's lets
    RViz, Foxglove and tf2 listeners match it."""
    description = Path(sys.prefix, "share", package, "msg", f"{name}.json")  # the venv is their prefix
    built = json.loads(description.read_text())["type_hashes"][0]["hash_string"]
    assert built == get_typestore(Stores.ROS2_JAZZY).hash_rihs01(f"{package}/msg/{name}")


def _centroids(triangles):
    return triangles.reshape(-1, 3, 3).mean(axis=1)


def test_gauge_triangles_are_the_gauge_models_surfaces(gauge):
    triangles = gauge_triangles(gauge)
    assert triangles.shape[1] == 3 and len(triangles) % 3 == 0
    centroids = _centroids(triangles)
    on_top = np.abs(centroids[:, 2] - gauge.surface_z(centroids[:, 0], centroids[:, 1])) < 1e-9
    on_bottom = np.abs(centroids[:, 2] - gauge.base_z) < 1e-9
    on_wall = ((np.abs(np.abs(centroids[:, 0]) - gauge.width / 2) < 1e-9)
               | (np.abs(np.abs(centroids[:, 1]) - gauge.length / 2) < 1e-9))
    assert np.all(on_top | on_bottom | on_wall)
    corners = triangles.reshape(-1, 3, 3)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    top_area = 0.5 * np.abs(cross[on_top & ~on_wall, 2]).sum()  # projected onto the x-y plane
    assert top_area == pytest.approx(gauge.width * gauge.length, rel=1e-9)
    # every face of the gauge shows: a top triangle on each of the n + 1 faces
    faces = gauge.face_index(centroids[on_top, 0], centroids[on_top, 1])
    assert set(np.unique(faces)) == set(range(gauge.n_ridges + 1))


def test_profile_in_gauge_frame_lies_on_the_gauge(gauge, rng):
    rotation, t = sample_pose(gauge, rng)
    points = render_profile(gauge, rotation, t)
    laid = profile_in_gauge(points, rotation, t, max_points=200)
    assert 100 <= len(laid) <= 200
    wall = np.abs(laid[:, 0]) > gauge.width / 2 - 1e-9  # a side wall the profiler also sees
    assert np.abs(np.abs(laid[wall, 0]) - gauge.width / 2).max(initial=0.0) < 1e-9
    top = laid[~wall]
    assert np.abs(top[:, 2] - gauge.surface_z(top[:, 0], top[:, 1])).max() < 1e-9
    wrong = profile_in_gauge(points, rotation, t + [0, 0, 1e-3], max_points=200)[~wall]
    assert np.abs(wrong[:, 2] - gauge.surface_z(wrong[:, 0], wrong[:, 1])).min() > 0.9e-3


def _pose_of(transform):
    r, t = transform.rotation, transform.translation
    return rotation_from_quaternion_xyzw(np.array([r.x, r.y, r.z, r.w])), np.array([t.x, t.y, t.z])


def test_estimator_broadcasts_the_pose_on_tf_and_the_scan_on_the_gauge(ros, gauge, rng):
    estimator = ros.add(PoseEstimatorNode(context=ros.context, parameter_overrides=[
        Parameter("visualization_rate", value=1000.0)]))
    probe = ros.node("viewer")
    publisher = probe.create_publisher(PointCloud2, "profile", qos_profile_sensor_data)
    tf, markers, poses = [], [], []
    probe.create_subscription(PoseStamped, "pose", poses.append, 10)
    probe.create_subscription(TFMessage, "/tf", tf.append, TF_QOS)
    probe.create_subscription(MarkerArray, "markers", markers.append, MARKER_QOS)
    assert ros.spin_until(lambda: publisher.get_subscription_count() > 0)
    rotation, t = sample_pose(gauge, rng)
    stamp = probe.get_clock().now().to_msg()
    cloud = cloud_from_points(render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng), stamp, "profiler")
    assert ros.spin_until(lambda: tf and markers and poses, action=lambda: publisher.publish(cloud)), "no /tf"

    (transform,) = tf[-1].transforms
    assert (transform.header.frame_id, transform.child_frame_id) == ("gauge", "profiler")
    assert transform.header.stamp == stamp  # the profile's time, so tf2 pairs it with that scan
    pose = poses[-1].pose  # /tf carries the published pose itself, quaternion sign included
    assert [transform.transform.translation.x, transform.transform.translation.y,
            transform.transform.translation.z] == [pose.position.x, pose.position.y, pose.position.z]
    r = transform.transform.rotation
    assert [r.x, r.y, r.z, r.w] == [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
    position, angle = pose_error(*_pose_of(transform.transform), rotation, t)
    assert position < 1e-3 and angle < 5e-3

    gauge_marker, profile_marker = markers[-1].markers
    assert gauge_marker.type == Marker.TRIANGLE_LIST and profile_marker.type == Marker.POINTS
    assert {gauge_marker.header.frame_id, profile_marker.header.frame_id} == {"gauge"}
    drawn = np.array([[p.x, p.y, p.z] for p in gauge_marker.points])
    assert np.array_equal(drawn, gauge_triangles(gauge))
    scan = np.array([[p.x, p.y, p.z] for p in profile_marker.points])
    assert len(scan) > 100
    # the estimated pose lays the scan on the gauge's faces, to within the noise and the pose's error
    assert np.median(np.abs(scan[:, 2] - gauge.surface_z(scan[:, 0], scan[:, 1]))) < 2e-5

    # 0 turns both off; a child frame of one's own keeps a robot model's profiler link its single parent
    estimator.set_parameters([Parameter("visualization_rate", value=0.0)])
    unseen = []  # stamps of profiles estimated while visualization_rate was 0
    for _ in range(5):
        unseen.append(stamp := probe.get_clock().now().to_msg())
        cloud.header.stamp = stamp
        assert ros.spin_until(lambda: any(p.header.stamp == stamp for p in poses),
                              action=lambda: publisher.publish(cloud))
    estimator.set_parameters([Parameter("visualization_rate", value=1000.0),
                              Parameter("tf_child_frame", value="profiler_measured")])
    cloud.header.stamp = stamp = probe.get_clock().now().to_msg()
    # /tf is in order: once this profile's transform is in, any of the five before it would be too
    assert ros.spin_until(lambda: tf[-1].transforms[0].header.stamp == stamp, action=lambda: publisher.publish(cloud))
    assert tf[-1].transforms[0].child_frame_id == "profiler_measured"
    assert not [m for m in tf if m.transforms[0].header.stamp in unseen]


def test_compensator_latches_the_gauges_place_on_tf_static(ros):
    gauge_in_base = [0.8, -0.1, 0.25, 0.0, 0.0, 0.5]
    compensator = ros.add(PdCompensatorNode(context=ros.context, parameter_overrides=[
        Parameter("gauge_in_base", value=gauge_in_base)]))
    static = []
    # a viewer that starts after the compensator still gets it (transient local, like tf2_ros)
    ros.node("late_viewer").create_subscription(TFMessage, "/tf_static", static.append, TF_STATIC_QOS)
    assert ros.spin_until(lambda: static), "no /tf_static"
    (transform,) = static[-1].transforms
    assert (transform.header.frame_id, transform.child_frame_id) == ("base", "gauge")
    rotation, translation = _pose_of(transform.transform)
    assert np.allclose(translation, gauge_in_base[:3])
    assert np.allclose(rotation, so3_exp(np.array(gauge_in_base[3:])), atol=1e-12)

    compensator.set_parameters([Parameter("base_frame", value="cell2/base")])
    assert ros.spin_until(lambda: static[-1].transforms[0].header.frame_id == "cell2/base")
