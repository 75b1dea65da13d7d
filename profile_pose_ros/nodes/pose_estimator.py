"""pose_estimator: `profile` (PointCloud2) -> `pose`, `pose_with_covariance`, `/diagnostics`.

Thin glue around profile_pose_ros.core.estimate_pose. A profile that fails any check publishes no
pose; the reason goes to diagnostics and the node keeps running.
"""
from __future__ import annotations

import math
import struct
import sys
from dataclasses import dataclass
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from ..core.compiled import loader
from ..core.design.gauge_check import (narrow_face_warning, profile_pitch, weak_corner_warning,
                                       weakest_bends_and_narrowest_faces)
from ..core.estimation.estimator import estimate_pose, warm_up
from ..core.estimation.result import WEIGHTINGS, EstimatorOptions
from ..core.model.gauge import Gauge, GaugeError
from ..core.timing.latency_window import LatencyWindow
from ..core.wire.pose_cdr import SerializedPosePair
from ..core.wire.profile_cdr import ProfileMessage, decode_profile_cdr
from ..core.wire.profile_cloud import ProfileFormatError
from ..core.model.rotation import HALF_TURN_X
from ..core.model.scene import gauge_triangles, profile_in_gauge
from ..core.timing.sequence_gaps import SequenceGaps
from ..resources import DEFAULT_GAUGE, config_path
from .diagnostics import ERROR, OK, WARN, diagnostic_array
from .direct_input import DirectInput, ServedDirectly, on_message_lost, spin
from .local_topics import LocalTopics, LoopOutput, profile_input_qos
from .messages import cdr_stamp_ns
from .parameters import Param, declare_all, updated
from .process_tuning import REALTIME_PARAMETERS
from .run import run_node
from .scene_messages import MARKER_QOS, TF_QOS, SceneMarkers, transform_stamped

NODE_NAME = "pose_estimator"

PARAMETERS = [
    Param("gauge_file", "", "Gauge YAML (DESIGN.md format). Empty: the shipped config/gauge_paper_n5.yaml.",
          read_only=True),
    Param("gauge_frame", "gauge", "frame_id of published poses (the gauge frame G)."),
    Param("profiler_frame", "profiler", "Expected frame_id of incoming profiles; empty accepts any."),
    Param("orientation_hint", list(HALF_TURN_X), "Quaternion (x y z w) near the mounting's orientation: each pose's "
          "quaternion is signed to lie on its hemisphere, so consecutive poses never flip sign (the default, a half "
          "turn about x, is the profiler looking down on the gauge)."),
    Param("visualization_rate", 10.0, "Rate (Hz) at which the latest pose also goes to /tf (gauge_frame -> "
          "tf_child_frame, stamped with its profile's time) and the gauge and that profile, laid on it in the gauge "
          "frame, to `markers` (MarkerArray) for RViz and Foxglove; 0 publishes neither.", 0.0, 1000.0),
    Param("tf_child_frame", "", "Child frame of the /tf transform; empty: the profile's frame_id. Set another name "
          "(e.g. profiler_measured) when a robot model already puts the profiler frame on the flange, so that "
          "the frame keeps one parent."),
    Param("refine", True, "Refine the closed form by maximum likelihood (paper eq. 15)."),
    Param("refine_weighting", "corner_covariance",
          f"Refinement weights: one of {', '.join(WEIGHTINGS)} (uniform = the paper's plain sum of squares)."),
    Param("refine_model", "auto",
          "corners: refine on the corners (paper eq. 15). dense: also fit every point's depth to its face (ML for "
          "depth noise, lower position error on the shipped gauges, about twice the time). auto: corners, and "
          "dense where the corner pose's position std exceeds dense_above_sigma (the views whose corners determine "
          "them poorly: there the corner model refuses or errs, the dense one keeps and is right) and on every "
          "view with a face hidden or out of view (docs/estimator.md)."),
    Param("dense_above_sigma", 2e-4, "refine_model auto: the dense refinement follows a corner pose whose "
          "position's largest standard deviation exceeds this (m); the shipped gauges at 5 um noise are below "
          "it.", 0.0, 1.0),
    Param("basin_search", True, "When a pose is poorly determined (or its cost implausible), also refine from "
          "4-ridge subset and weak-mode starts and keep the lowest minimum (a few ms for such profiles)."),
    Param("basin_search_min_sigma", 2.5e-4, "Search when the refined position's largest standard deviation "
          "exceeds this (m); the shipped gauge at 5 um noise is near 0.07 mm.", 0.0, 1.0),
    Param("max_position_sigma", 3.5e-4, "Reject a pose whose position standard deviation (largest, m) exceeds "
          "this: fewer refused views against more poses over 1 mm off (its covariance stays honest beyond it; "
          "`profile_pose robustness --gates` measures the trade for a gauge, docs/estimator.md). The shipped "
          "gauges are near 0.02-0.2 mm at 5 um noise.", 1e-6, 1.0),
    Param("noise_std", 0.0, "Profiler depth noise (m) for the covariance; 0 estimates it from each face fit.",
          0.0, 1e-3),
    Param("rdp_epsilon", 3e-4, "RDP tolerance for corner candidates (m).", 1e-6, 5e-3),
    Param("trim_fraction", 0.10, "Fraction of each segment dropped at both ends before the line fit.", 0.0, 0.4),
    Param("min_segment_points", 20, "Segments with fewer points are treated as spikes or edge debris.", 3, 3200),
    Param("min_corner_angle", math.radians(5.0), "Adjacent segments closer than this in direction are one face (rad).",
          0.0, 0.5),
    Param("max_face_angle", math.radians(70.0), "End segments steeper than this are side walls (rad).", 0.5, 1.5707),
    Param("max_corner_offset", 1e-3, "A corner must lie between its two faces to within this (m).", 1e-5, 0.01),
    Param("robust_line_fit", True, "Reject outlier points (spikes) in each face line fit."),
    Param("spike_threshold", 1.5e-4, "Drop points this far (m) off the median depth of their five neighbours "
          "before corner detection, and runs of up to 16 side by side this far off their face (glints); 0 keeps "
          "every point.", 0.0, 0.01),
    Param("hidden_faces", True, "When corner detection finds one corner too few beside a gap in the profile, "
          "solve the gauge without the face the gap hid (its neighbours' extrapolated crossing as the corner) and "
          "publish that pose if it puts the hidden face inside the gap."),
    Param("max_reprojection_error", 1e-4, "Reject poses whose mean corner residual exceeds this (m).", 1e-7, 0.01),
    Param("max_residual_ratio", 4.0, "Reject poses whose corner residuals are more than this many times (rms, in "
          "their standard deviations) what the profile's own noise explains: the profile does not match the gauge. "
          "A correct pose exceeds 4 with probability below 1e-7; a gauge machined worse than its file needs more "
          "(docs/estimator.md); 1e9 turns the test off.", 1.0, 1e9),
    Param("diagnostics_period", 1.0, "Period of /diagnostics messages (s).", 0.02, 60.0),
    Param("queue_depth", 20, "Profiles the subscription keeps while this node is busy (sensor-data QoS, newest "
          "kept): 20 rides out a 20 ms stall at 1 kHz (5 lost 0.1-0.5 % of the profiles on a loaded 2-core "
          "machine, 20 none); shallower never works on old profiles. Every one dropped is counted in "
          "profiles_lost.", 1, 1000, read_only=True),
    Param("max_profile_age", 0.0, "Skip, without estimating, a profile older than this when taken (s, its stamp "
          "against this node's clock): a node that fell behind catches up on fresh profiles instead of working "
          "through ones the compensator would refuse as stale (its max_pose_age). 0 never skips: a bag replayed "
          "into a live node carries the recording's stamps. The cell files set 0.05.", 0.0, 10.0),
    *REALTIME_PARAMETERS,
]

# the parameters that are EstimatorOptions (or CornerOptions) fields, under the same names
ESTIMATOR_PARAMETERS = ("refine", "refine_weighting", "refine_model", "dense_above_sigma", "noise_std",
                        "rdp_epsilon", "trim_fraction", "min_segment_points", "min_corner_angle", "max_face_angle",
                        "max_corner_offset", "robust_line_fit", "spike_threshold", "max_reprojection_error",
                        "max_residual_ratio", "basin_search", "basin_search_min_sigma", "max_position_sigma",
                        "hidden_faces")


def options_from(values: dict) -> EstimatorOptions:
    """EstimatorOptions from parameter values; raises ValueError for an invalid combination (or hint)."""
    hint = values.get("orientation_hint", HALF_TURN_X)
    if len(hint) != 4 or not any(hint) or not all(math.isfinite(v) for v in hint):
        raise ValueError(f"orientation_hint must be a quaternion x y z w, not {list(hint)}")
    changes = {name: values[name] for name in ESTIMATOR_PARAMETERS if name in values}
    return EstimatorOptions().with_changes(**changes)


@dataclass
class ProfileResult:
    reason: str = ""  # why no pose; empty when there is one
    pose: bytes | None = None  # serialized PoseStamped and PoseWithCovarianceStamped (SerializedPosePair)
    pose_with_covariance: bytes | None = None
    reprojection_error: float | None = None
    stamp_ns: int | None = None  # the profile's, when it had a pose
    profile: ProfileMessage | None = None  # the decoded profile, if it decoded; the pose's R, t (F in G) if it had one
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    background_cut: bool = False  # the estimate left out what the gauge stands on (estimation/background.py)


def poses_from_profile(serialized: bytes, gauge: Gauge, options: EstimatorOptions, profiler_frame: str,
                       gauge_frame: str, into: SerializedPosePair | None = None,
                       hint=HALF_TURN_X) -> ProfileResult:
    """The node's whole computation for one profile (a serialized PointCloud2, as taken from the topic or
    read from a bag), without the node: profile_pose replay runs exactly this on recorded profiles, so a
    replay reproduces the published poses bit for bit. The poses are `into`'s bytes, refilled, when it is
    given (the node's, reused), else new ones; `hint` is orientation_hint (the quaternion's hemisphere)."""
    try:
        profile = decode_profile_cdr(serialized)
    except ProfileFormatError as exc:
        return ProfileResult(f"bad profile: {exc}")
    if profiler_frame and profile.frame_id != profiler_frame:
        return ProfileResult(f"profile frame_id '{profile.frame_id}' is not '{profiler_frame}'")
    estimate = estimate_pose(profile.points, gauge, options)
    if not estimate.ok:
        return ProfileResult(estimate.reason, reprojection_error=estimate.reprojection_error, profile=profile,
                             background_cut=estimate.background_cut)
    into = into or SerializedPosePair()
    into.fill(estimate.R, estimate.t, estimate.covariance, profile.stamp_sec, profile.stamp_nanosec, gauge_frame,
              hint)
    return ProfileResult("", into.pose, into.with_covariance, estimate.reprojection_error, profile.stamp_ns,
                         profile, estimate.R, estimate.t, estimate.background_cut)


class PoseEstimatorNode(Node):
    def __init__(self, local: LocalTopics | None = None, **kwargs) -> None:
        """local: the composed nodes' topics (cell_container): profiles come from the driver of this process,
        handed over in its thread, and poses go to the compensator of this process the same way."""
        super().__init__(NODE_NAME, **kwargs)
        self.values = declare_all(self, PARAMETERS)
        self.gauge_file = self.values["gauge_file"] or str(config_path(DEFAULT_GAUGE))
        self.gauge = Gauge.from_yaml(self.gauge_file)  # GaugeError: main() reports it and exits
        self.options = options_from(self.values)
        if loader.will_compile():
            self.get_logger().info("compiling the estimator for this machine before the first profile "
                                   "(once per installed version, about a minute)")
        compile_s = warm_up(self.gauge, self.options)  # compile (or load) before the first profile
        # per corner, read against min_corner_angle; per inner face, read against the profiles' pitch
        self.profile_bends, self.face_widths = weakest_bends_and_narrowest_faces(self.gauge)
        self.weak_corners = None
        self._check_corner_bends()
        self.pitch = None  # the first decoded profile's
        self.narrow_faces = None
        self.add_on_set_parameters_callback(self._on_set_parameters)

        # rclpy attaches default QoS-event handlers to every endpoint, and its executor walks all of them on
        # each wake-up; at 1 kHz that is a large share of the node's time. Only message loss on the input
        # is worth a handler here.
        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        self.pose_pub = self.create_publisher(PoseStamped, "pose", 10, event_callbacks=quiet)
        self.covariance_pub = self.create_publisher(PoseWithCovarianceStamped, "pose_with_covariance", 10,
                                                    event_callbacks=quiet)
        self.covariance_out = LoopOutput(self.covariance_pub, local, self.get_logger())
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10, event_callbacks=quiet)
        self.latency = LatencyWindow("trigger_to_pose_ms")  # the profile's stamp -> its pose published
        self.diagnostics_timer = self.create_timer(self.values["diagnostics_period"], self._publish_diagnostics)
        self.received = self.published = self.rejected = self.lost_in_transport = self.skipped = 0
        self.background_cuts = 0  # profiles whose estimate left out what the gauge stands on (one writer: the input)
        self.gaps = SequenceGaps()  # profiles never taken: overwritten in the queue, or lost on the way
        self.stats_lock = threading.Lock()  # callbacks may run on other executors' threads
        self.window = self._new_window(time.monotonic())
        self.direct_input = DirectInput(None, self.context)
        if local is not None and local.carries("profile"):
            local.take(self.resolve_topic_name("profile"), self._on_profile)
        else:
            self._subscribe_profiles()
        self.outgoing = SerializedPosePair()  # published as bytes: core/wire/pose_cdr.py
        self.tf_pub = self.create_publisher(TFMessage, "/tf", TF_QOS, event_callbacks=quiet)
        self.markers_pub = self.create_publisher(MarkerArray, "markers", MARKER_QOS, event_callbacks=quiet)
        self.scene = SceneMarkers(gauge_triangles(self.gauge), self.values["gauge_frame"])
        self.next_scene = 0.0  # monotonic time of the next /tf and markers update
        self.last_error = ""
        self.last_reprojection_error = float("nan")
        self.get_logger().info(f"gauge '{self.gauge.name}' ({self.gauge.n_ridges} ridges) from {self.gauge_file}; "
                               f"estimator ({loader.kernel_name()}) ready in {compile_s:.2f} s"
                               f"{'; composed' if local is not None else ''}")

    def _subscribe_profiles(self) -> None:
        # Sensor-data QoS keeps the newest profiles: a consumer that falls behind drops the oldest. The
        # middleware reports only samples that never arrived (message-lost handler); the gaps in the
        # driver's sequence numbers count the overwritten ones too.
        self.profile_sub = self.create_subscription(
            PointCloud2, "profile", self._on_profile,
            profile_input_qos(self.values["queue_depth"]),
            callback_group=ServedDirectly(), raw=True,  # serialized: decode_profile_cdr reads it in place
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
        on_message_lost(self, self.profile_sub, self._on_lost)
        self.direct_input.add(self.profile_sub, self._on_profile, with_info=True)

    def pump(self, timeout_sec: float = 0.0) -> int:
        """Handle queued profiles (see direct_input.py); spin() or a test harness calls this."""
        return self.direct_input.pump(timeout_sec)

    # ------------------------------------------------------------------ parameters
    def _on_set_parameters(self, parameters) -> SetParametersResult:
        try:
            values, options = updated(self.values, parameters, options_from)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        if "diagnostics_period" in {p.name for p in parameters}:
            self.diagnostics_timer.timer_period_ns = int(values["diagnostics_period"] * 1e9)
        self.values, self.options = values, options
        self._check_corner_bends()
        self._check_face_widths()
        return SetParametersResult(successful=True)

    def _check_corner_bends(self) -> None:
        """Say, when it changes, which corners bend too little in the profile for the min_corner_angle now set
        (their profiles refused as a face short); diagnostics carry it for as long as it holds."""
        warning = weak_corner_warning(self.gauge, self.options.corners.min_corner_angle, self.profile_bends)
        if warning is not None and warning != self.weak_corners:
            self.get_logger().warning(warning)
        self.weak_corners = warning

    def _check_face_widths(self) -> None:
        """Say, when it changes, which faces hold too few points at the profiles' pitch for the min_segment_points
        now set (their profiles refused as a face short: a binned or thinned profiler); diagnostics carry it."""
        warning = narrow_face_warning(self.gauge, self.options.corners.min_segment_points, self.pitch or np.nan,
                                      self.face_widths)
        if warning is not None and warning != self.narrow_faces:
            self.get_logger().warning(warning)
        self.narrow_faces = warning

    # ------------------------------------------------------------------ profiles
    @staticmethod
    def _new_window(start: float) -> dict:
        return {"received": 0, "rejected": 0, "lost": 0, "skipped": 0, "busy": 0.0, "cpu": 0.0, "max_age": 0.0,
                "start": start}

    def _on_lost(self, info) -> None:
        with self.stats_lock:
            self.lost_in_transport += info.total_count_change

    def _on_profile(self, serialized: bytes, info: dict | None = None) -> None:
        """One profile (a serialized PointCloud2) and rmw's message info, taken by DirectInput."""
        start = time.perf_counter()
        cpu_start = time.thread_time()
        missed = self.gaps.update(info.get("publication_sequence_number")) if info else 0
        try:
            age = (self.get_clock().now().nanoseconds - cdr_stamp_ns(serialized)) * 1e-9
        except struct.error:
            age = 0.0  # too short to hold a stamp: decoding rejects it below
        max_age = self.values["max_profile_age"]
        skip = 0.0 < max_age < age
        reason = ""
        if not skip:
            try:
                reason = self._estimate_and_publish(serialized)
            except Exception as exc:  # noqa: BLE001 - a malformed input must never take the node down
                reason = f"internal error: {exc!r}"
                # a profile stream that trips it does so hundreds of times a second: the count is in diagnostics
                self.get_logger().error(reason, throttle_duration_sec=1.0)
        if reason:
            self.last_error = reason
            self.get_logger().warn(f"profile rejected: {reason}", throttle_duration_sec=1.0)
        with self.stats_lock:
            self.received += 1
            self.window["received"] += 1
            self.window["lost"] += missed
            self.window["max_age"] = max(self.window["max_age"], age)
            self.skipped += skip
            self.window["skipped"] += skip
            if reason:
                self.rejected += 1
                self.window["rejected"] += 1
            self.window["busy"] += time.perf_counter() - start
            self.window["cpu"] += time.thread_time() - cpu_start

    def _estimate_and_publish(self, serialized: bytes) -> str:
        result = poses_from_profile(serialized, self.gauge, self.options, self.values["profiler_frame"],
                                    self.values["gauge_frame"], self.outgoing, self.values["orientation_hint"])
        if self.pitch is None and result.profile is not None:  # once: the profiler's pitch is set before it runs
            pitch = profile_pitch(result.profile.points)
            if pitch > 0:
                self.pitch = pitch
                self._check_face_widths()
        self.background_cuts += result.background_cut
        if result.reprojection_error is not None:
            self.last_reprojection_error = result.reprojection_error
        if result.reason:
            return result.reason
        if self.pose_pub.get_subscription_count():  # publishing to nobody still costs a write
            self.pose_pub.publish(result.pose)
        self.covariance_out.publish(result.pose_with_covariance)  # it checks the same
        self.latency.add(time.time() - result.stamp_ns * 1e-9)
        self.published += 1
        self.covariance_out.hand_over(result.pose_with_covariance)  # composed: the correction follows here
        self._publish_scene(result)
        return ""

    def _publish_scene(self, result: ProfileResult) -> None:
        """/tf and the markers from this pose, at most at visualization_rate (the loop's rate is not theirs)."""
        rate, now = self.values["visualization_rate"], time.monotonic()
        if rate <= 0.0 or now < self.next_scene:
            return
        self.next_scene = now + 1.0 / rate
        gauge_frame = self.values["gauge_frame"]
        child = self.values["tf_child_frame"] or result.profile.frame_id
        self.tf_pub.publish(TFMessage(transforms=[transform_stamped(
            gauge_frame, child, result.stamp_ns, result.rotation, result.translation,
            self.values["orientation_hint"])]))
        self.scene.set_frame(gauge_frame)
        self.markers_pub.publish(self.scene.update(
            profile_in_gauge(result.profile.points, result.rotation, result.translation), result.stamp_ns))

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        with self.stats_lock:
            w, self.window = self.window, self._new_window(now)
        elapsed = max(now - w["start"], 1e-9)
        received, rejected = w["received"], w["rejected"]
        if received == 0:
            level, message = WARN, f"no profiles on '{self.resolve_topic_name('profile')}' for {elapsed:.1f} s"
        elif rejected == received:
            level, message = ERROR, f"all {received} profiles rejected; last: {self.last_error}"
        elif rejected:
            level, message = WARN, f"{rejected} of {received} profiles rejected; last: {self.last_error}"
        elif w["lost"]:
            level, message = WARN, (f"{w['lost']} profiles lost before processing (this node too slow, or the "
                                    f"link dropping)")
        elif w["skipped"]:
            level, message = WARN, (f"{w['skipped']} of {received} profiles skipped, older than max_profile_age "
                                    f"(this node behind)")
        else:
            level, message = OK, f"estimating at {received / elapsed:.1f} Hz"
        values = {
            "rate_hz": received / elapsed, "profiles_received": self.received, "poses_published": self.published,
            "profiles_rejected": self.rejected, "profiles_lost": self.gaps.missed,
            "profiles_lost_in_transport": self.lost_in_transport, "profile_writers": self.gaps.writers,
            "profiles_skipped_stale": self.skipped,
            "profiles_background_cut": self.background_cuts,
            "last_error": self.last_error or "none",
            "max_profile_age_ms": w["max_age"] * 1e3,
            "last_reprojection_error_um": self.last_reprojection_error * 1e6,
            "mean_processing_ms": 1e3 * w["busy"] / received if received else 0.0,
            "mean_processing_cpu_ms": 1e3 * w["cpu"] / received if received else 0.0,
            "gauge": self.gauge.name, "gauge_file": self.gauge_file, "weak_corners": self.weak_corners or "none",
            "narrow_faces": self.narrow_faces or ("none" if self.pitch else "unknown before the first profile"),
            "pose_subscribers": self.pose_pub.get_subscription_count(),  # matched: who gets the poses now
            **self.latency.report(),
        }
        self.diagnostics_pub.publish(diagnostic_array(self, "pose estimation", self.gauge.name,
                                                      level, message, values))


def main(args=None) -> int:
    return run_node(PoseEstimatorNode, NODE_NAME, args, startup_errors=(GaugeError,),
                    spin=lambda executor, node, stop: spin(executor, node.direct_input, stop))


if __name__ == "__main__":
    sys.exit(main())
