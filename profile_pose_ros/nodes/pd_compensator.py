"""pd_compensator: `pose_with_covariance` and `reference_pose` (F in G) -> `correction` (TwistStamped, robot
base frame): a PD law on the Kalman-filtered pose error, through an input shaper that keeps the arm's 10 Hz
resonance out of the commands (core/control/compensator.py); or, with `control_law: modal`, a feedback of the arm
mode's state that damps the resonance (core/control/modal_control.py).

A stale pose (older than max_pose_age by its stamp, or stamped more than max_future ahead), a missing
one (the estimator rejected the profile) or no reference gives a zero correction and a diagnostic. A pose
stays usable for what is left of max_pose_age when it arrives, counted on this node's monotonic clock.
Poses and references in another frame than gauge_frame, or with a quaternion that is not unit length,
are refused, as is a reference further than max_reference_step from the last. Gains change at run time,
validated.
"""
from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from statistics import median

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TwistStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

from ..core.control.compensator import (AxisKalman, Gains, InputShaper, Mounting, covariance_in_base, pd_velocity,
                                        pose_vector_in_base, zvd_impulses)
from ..core.timing.freshness import describe_age, fresh_until, stamp_age_ok
from ..core.timing.latency_window import LatencyWindow
from ..core.commissioning.first_motion import FirstMotionCheck, ProbeDesign
from ..core.control.modal_control import ONE_POSE_A_PERIOD, SPACING_WINDOW, ModalController, ModalDesign
from ..core.control.period_fusion import PeriodPose, fuse_period
from ..core.wire.pose_cdr import (CdrFormatError, decode_pose_with_covariance_cdr, decode_stamp, decode_twist_cdr,
                                   encode_twist_cdr)
from ..core.model.rotation import rotation_from_quaternion_xyzw
from ..core.estimation.result import position_sigma
from .diagnostics import ERROR, OK, WARN, RefusalCounter, diagnostic_array
from .direct_input import DirectInput, ServedDirectly, spin
from .local_topics import LOOP_INPUT_QOS, LocalTopics, LoopOutput
from .messages import rotation_translation
from .parameters import Param, declare_all, updated
from .process_tuning import REALTIME_PARAMETERS
from .run import run_node
from .scene_messages import TF_STATIC_QOS, static_transform

NODE_NAME = "pd_compensator"
ROBOT_LIVE_S = 0.5  # robot_state heard this recently: the bridge is armed and the controller answering

PARAMETERS = [
    Param("kp", [4.0, 4.0, 4.0, 5.0, 5.0, 5.0], "Proportional gain per axis x y z rx ry rz (1/s): velocity "
          "commanded per unit of pose error."),
    Param("kd", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "Derivative gain per axis (dimensionless): velocity commanded "
          "per unit of the arm's filtered velocity, subtracted."),
    Param("max_speed", [0.05, 0.05, 0.05, 0.2, 0.2, 0.2], "Correction speed limit per axis (m/s, rad/s)."),
    Param("gauge_in_base", [0.0] * 6, "Pose of the gauge frame G in the robot base frame: x y z (m), rotation "
          "vector (rad), as profile_pose_calibrate measures it. Also published on /tf_static (base_frame -> "
          "gauge_frame).", read_only=True),
    Param("profiler_in_tool", [0.0] * 6, "Pose of the profiler frame F on the controller's tool (x y z m, rotation "
          "vector rad), as profile_pose_calibrate measures it: corrections are sent for the tool, which the "
          "controller turns about its own origin. Zero: the tool is the profiler frame.", read_only=True),
    Param("first_motion_check", True, "Before the loop first closes (a reference, poses, and the bridge armed: "
          "robot_state flowing), probe each axis open loop and compare the measured response with what "
          "gauge_in_base and profiler_in_tool predict; on a sign flip, an axis swap or a rotation error the "
          "loop stays open (no corrections; the bridge stops) with an ERROR diagnostic.", read_only=True),
    Param("first_motion_amplitude", [5e-4, 5e-4, 5e-4, 5e-3, 5e-3, 5e-3], "The probes' size per axis (m, rad).",
          read_only=True),
    Param("first_motion_max_rotation_error", 0.05, "The largest rotation between the probes and the measured "
          "response that the check passes (rad).", 0.001, 0.5, read_only=True),
    Param("acceleration_psd", [20.0, 0.5, 20.0, 2.0, 2.0, 2.0], "Kalman filter process noise per axis "
          "((m/s^2)^2/Hz): larger follows faster motion, smaller averages more noise.", read_only=True),
    Param("shaper_frequency", 10.0, "The arm's resonance (Hz, natural frequency) that a ZVD input shaper keeps "
          "out of the corrections; 0 turns the shaper off. Read it off an open-loop step (profile_pose experiment "
          "--modes open prints the ringing).", 0.0, 100.0, read_only=True),
    Param("shaper_damping", 0.05, "Damping ratio of that resonance, for the shaper (the ZVD shaper tolerates "
          "+-20 % error on the frequency).", 0.0, 0.9, read_only=True),
    Param("control_law", "pd", "pd: the PD law behind the input shaper (sends nothing at the resonance, adds no "
          "damping); modal: a Kalman filter on a model of the arm's mode and the loop's delays with an LQR "
          "feedback that damps the mode (docs/robot_side.md). modal: one pose per control period drives it; a "
          "faster profiler's other poses are left out, or fused with it (period_clock robot_state).",
          read_only=True),
    Param("modal_frequency", [10.0] * 6, "modal: the arm mode's natural frequency per axis (Hz), as the open-loop "
          "step shows it (profile_pose experiment --modes open).", read_only=True),
    Param("modal_damping", [0.68, 0.13, 0.53, 0.7, 0.7, 0.7], "modal: the mode's damping ratio per axis (the "
          "open-loop step's; the paper's Table IV for x y z).", read_only=True),
    Param("modal_effort", [10.0, 30.0, 10.0, 10.0, 10.0, 10.0], "modal: the LQR's weight on each increment "
          "against the mode's energy, per axis: larger is slower and passes less of the estimate's noise to the "
          "arm (y: the gauge's noisy axis). Given for a 12 ms period: at another control_period it is scaled by "
          "(0.012 / control_period)^2, which keeps the same loop.", read_only=True),
    Param("modal_acceleration_psd", [1e-3] * 6, "modal: the filter's acceleration noise per axis "
          "((m/s^2)^2/Hz; rad the same): what the model does not predict.", read_only=True),
    Param("modal_offset_walk", [1e-5] * 6, "modal: how fast the filter lets the arm's offset from the commands "
          "it was sent drift (m, rad per period): lost increments, rounding, model error.", read_only=True),
    Param("control_period", 0.012, "modal: the controller's period (s): 0.012 at 83.3 Hz, 0.004 at 250 Hz.",
          0.001, 0.1, read_only=True),
    Param("loop_delay", 0.0226, "modal: from a pose's stamp to the arm moving on the increment it caused (s): "
          "the periods until it is applied (one when the bridge waits for it, answer_wait > 0; two when it "
          "answers at once), plus (period - one interpolation tick) / 2 when the controller spreads each "
          "increment over its ticks, plus the arm's command-to-motion delay.",
          0.001, 0.5, read_only=True),
    Param("period_clock", "pose", "What starts a control period. pose: each pose, when the controller triggers the "
          "profiler (one pose a period); a faster profiler's poses on a grid of control_period, the others left out "
          "(modal law) or each sent on (PD law). robot_state: the controller's STATE, as the bridge relays it: the "
          "poses since the last one, fused by their covariances, drive the law once and the correction leaves then, "
          "one a controller period (a profiler on its own faster clock; the bridge's await_reply holds each answer "
          "for it); until robot_state flows (the bridge arms on a live correction), as pose. Composed with the "
          "bridge (compensator_bridge), the correction is made in the bridge's thread as each STATE comes.",
          read_only=True),
    Param("reference_shaping", "lag", "modal: how a new reference is reached. lag: the feedback alone towards "
          "the reference through a first-order filter (reference_time_constant): ~1.1 s to settle a step. zvdd: "
          "along a planned command, a ramp at 0.8 x max_speed through a ZVDD shaper matched to each axis's mode "
          "(modal_frequency, modal_damping: profile_pose identify; ZVDDD where the damping is under 0.1, ZVD from "
          "0.3; the last reference_approach_share along a slow approach), sent as "
          "feedforward, the feedback acting on the difference from the model's motion: ~0.2 s to settle on "
          "sim_cell when every increment arrives in its period (the bridge's answer_wait 0, and a loop_delay "
          "that counts the extra period; docs/robot_side.md).", read_only=True),
    Param("reference_approach_share", 0.14, "modal, reference_shaping zvdd: this share of a planned step comes "
          "along a minimum-jerk approach of reference_approach_time started with the shaped ramp, so the arm passes "
          "90 % of the step slowly (Table IV's post-rise spectrum, Mf); not on an axis planned through ZVDDD. 0: the "
          "shaped ramp alone.", 0.0, 0.9, read_only=True),
    Param("reference_approach_time", 0.32, "modal, reference_shaping zvdd: how long the approach of "
          "reference_approach_share takes (s); the step settles about when it ends.", 0.01, 2.0, read_only=True),
    Param("reference_time_constant", 0.25, "modal, reference_shaping lag: a new reference is approached through "
          "a first-order filter of this time constant (s), starting from where the arm is.", 0.01, 10.0,
          read_only=True),
    Param("use_covariance", True, "Weight each pose by its published covariance (else by measurement_std)."),
    Param("max_position_sigma", 5e-4, "Refuse a pose whose covariance puts its position's largest standard "
          "deviation beyond this (m; with use_covariance): how precise a pose must be to steer the arm is this "
          "node's decision (pose_estimator's own gate, 0.35 mm by default, can be opened to leave it to this "
          "one alone).", 1e-6, 1.0),
    Param("measurement_std", 5e-5, "Pose noise assumed when use_covariance is false (m; rad the same number).",
          1e-7, 1e-2),
    Param("max_pose_age", 0.05, "A pose older than this (by its stamp) is stale: zero correction (s).", 0.001, 1.0),
    Param("max_pose_range", 2.0, "A pose further than this from the profiler (m) is refused: no profiler measures "
          "that far, and a finite but absurd position would overflow the filter.", 0.01, 100.0),
    Param("max_future", 0.002, "A pose or reference stamped more than this ahead of this host's clock is refused "
          "(s): stamps are trigger times, in the past on a healthy cell.", 0.0, 0.1),
    Param("max_reference_age", 1.0, "A reference_pose stamped longer ago than this is refused (s): an old command "
          "replayed, or a stamp of 0.", 0.01, 3600.0),
    Param("max_reference_step", [0.005, 0.005, 0.005, 0.02, 0.02, 0.02], "A reference_pose further than this "
          "from the current reference (or, for the first one, from the measured pose) on any axis is refused (m, "
          "rad; base-frame axes)."),
    Param("gauge_frame", "gauge", "frame_id that poses and references must carry (the gauge frame G)."),
    Param("base_frame", "base", "frame_id of the corrections, and the parent of the gauge's place (gauge_in_base) "
          "on /tf_static."),
    Param("watchdog_rate", 100.0, "While the pose is stale (or no reference), how often a zero correction is sent "
          "(Hz). Staleness itself is noticed when the newest pose turns max_pose_age old.", 1.0, 1000.0,
          read_only=True),
    Param("diagnostics_period", 1.0, "Period of /diagnostics (s).", 0.02, 60.0, read_only=True),
    *REALTIME_PARAMETERS,
]

_GAINS = ("kp", "kd", "max_speed")
PERIOD_CLOCKS = ("pose", "robot_state")
QUATERNION_NORM_TOLERANCE = 1e-3  # a unit quaternion's norm, as float32 or float64 messages carry it


def unit_quaternion(q) -> bool:
    """Within QUATERNION_NORM_TOLERANCE of unit length (False for NaN): anything else is no orientation."""
    return abs(math.sqrt(sum(c * c for c in q)) - 1.0) <= QUATERNION_NORM_TOLERANCE


def modal_controller_from(values: dict) -> ModalController | None:
    if values["control_law"] == "pd":
        return None
    if values["control_law"] != "modal":
        raise ValueError(f"control_law must be pd or modal, got {values['control_law']!r}")
    return ModalController(ModalDesign(
        tuple(values["modal_frequency"]), tuple(values["modal_damping"]), tuple(values["modal_effort"]),
        tuple(values["modal_acceleration_psd"]), tuple(values["modal_offset_walk"]), values["control_period"],
        values["loop_delay"], values["reference_time_constant"], values["reference_shaping"],
        values["reference_approach_share"], values["reference_approach_time"]), speed_limit=values["max_speed"])


def gains_from(values: dict) -> Gains:
    gains = Gains(tuple(values["kp"]), tuple(values["kd"]), tuple(values["max_speed"]))
    gains.check()
    return gains


class PdCompensatorNode(RefusalCounter, Node):
    def __init__(self, local: LocalTopics | None = None, **kwargs) -> None:
        """local: the composed nodes' topics (cell_container): poses arrive in the estimator's thread and
        corrections go to the bridge of this process the same way; the watchdog is then the container's."""
        super().__init__(NODE_NAME, **kwargs)
        v = self.values = declare_all(self, PARAMETERS)
        self.gains = gains_from(v)
        for name in ("gauge_in_base", "profiler_in_tool", "acceleration_psd", "first_motion_amplitude"):
            if len(v[name]) != 6:
                raise ValueError(f"{name} needs six values")
        if min(v["first_motion_amplitude"]) <= 0:
            raise ValueError("first_motion_amplitude needs six positive values")
        self.mounting = Mounting(tuple(v["gauge_in_base"]), tuple(v["profiler_in_tool"]))
        self.first_motion = (FirstMotionCheck(ProbeDesign(tuple(v["first_motion_amplitude"]),
                                                          max_rotation_error=v["first_motion_max_rotation_error"]))
                             if v["first_motion_check"] else None)
        if v["period_clock"] not in PERIOD_CLOCKS:
            raise ValueError(f"period_clock must be one of {', '.join(PERIOD_CLOCKS)}, not {v['period_clock']!r}")
        self.robot_heard = -math.inf  # time.monotonic() of the newest robot_state: the bridge is armed
        self.period_poses: list[PeriodPose] = []  # period_clock robot_state: the poses since the last STATE
        self.pose_spacing: deque[float] = deque(maxlen=SPACING_WINDOW)  # between the poses' stamps (s)
        # tick - the answering pose's stamp, a STATE: kept here, as the law forgets its own at a stale spell,
        # and loop_delay is commissioned from the figure after the run has stopped
        self.pose_ages_at_state: deque[float] = deque(maxlen=SPACING_WINDOW)
        self.last_rotation = np.eye(3)  # the newest pose's rotation (F in G): the tool's lever arm
        self.modal = modal_controller_from(v)
        # The PD law's filter and shaper; the modal law has its own filter and needs no shaper.
        self.filter = AxisKalman(np.array(v["acceleration_psd"])) if self.modal is None else None
        self.shaper = (InputShaper(zvd_impulses(v["shaper_frequency"], v["shaper_damping"]))
                       if self.modal is None and v["shaper_frequency"] > 0 else None)
        self.anchor: np.ndarray | None = None  # base-frame rotation all rotation vectors are taken from
        self.reference: np.ndarray | None = None  # 6-vector in base coordinates
        self.reference_came = 0.0  # time.monotonic() when it came: a planned step starts from then
        self.last_pose_stamp = 0.0
        self.pose_fresh_until = -math.inf  # time.monotonic() at which the newest pose turns stale
        self.last_measured: np.ndarray | None = None  # the newest pose, base coordinates (for the reference check)
        self.poses = self.corrections = self.stale_zeros = 0
        self.law_stamp_ns = 0
        self.coasted = 0  # controller periods answered by the model alone (modal law, period_clock robot_state)
        self.refused = {"stale": 0, "future": 0, "frame": 0, "orientation": 0, "covariance": 0, "imprecise": 0,
                        "range": 0, "reference": 0, "lost_increment": 0}
        self.lost_told = 0  # increments the bridge said the controller never applied, counted by the model
        self.last_error = np.zeros(6)
        self._lock = threading.Lock()  # composed, poses arrive on another thread than the watchdog's
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.correction_out = LoopOutput(self.create_publisher(TwistStamped, "correction", 10), local,
                                         self.get_logger())
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.tf_static_pub = self.create_publisher(TFMessage, "/tf_static", TF_STATIC_QOS)
        self._publish_gauge_place()
        # Poses are taken straight from their subscription (direct_input.py): through the executor each one
        # waited behind its per-wake-up bookkeeping and the 100 Hz watchdog, about a millisecond per hop here.
        # ... and serialized: read with struct, corrections written the same way (core/wire/pose_cdr.py)
        self.direct_input = DirectInput(None, self.context, tick=self._watchdog)
        if local is not None and local.carries("pose_with_covariance"):
            local.take(self.resolve_topic_name("pose_with_covariance"), self._on_pose)
        else:
            pose_sub = self.create_subscription(PoseWithCovarianceStamped, "pose_with_covariance", self._on_pose,
                                                LOOP_INPUT_QOS, callback_group=ServedDirectly(), raw=True)
            self.direct_input.add(pose_sub, self._on_pose)
        # served directly as well: through the executor a new reference waited for its housekeeping pass, up to
        # 50 ms (four 83.3 Hz periods), and a planned step started that much later
        reference_sub = self.create_subscription(PoseStamped, "reference_pose", self._on_reference, 10,
                                                 callback_group=ServedDirectly())
        self.direct_input.add(reference_sub, self._on_reference)
        if self.modal is not None:  # the PD law has no model of the commands it sent to correct
            if local is not None and local.carries("lost_increment"):  # composed with the bridge: its socket thread
                local.take(self.resolve_topic_name("lost_increment"), self._on_lost)
            else:  # served directly: through the executor a loss would reach the model up to 50 ms (12 periods) late
                lost_sub = self.create_subscription(TwistStamped, "lost_increment", self._on_lost, 100,
                                                    callback_group=ServedDirectly(), raw=True)
                self.direct_input.add(lost_sub, self._on_lost)
        on_state = self._on_controller_period if v["period_clock"] == "robot_state" else self._on_robot_state
        if local is not None and local.carries("robot_state"):  # composed with the bridge: in its socket thread
            local.take(self.resolve_topic_name("robot_state"), on_state)
        elif v["period_clock"] == "robot_state":  # the controller's clock: taken as it comes, like the poses
            state_sub = self.create_subscription(PoseStamped, "robot_state", self._on_controller_period,
                                                 LOOP_INPUT_QOS, callback_group=ServedDirectly(), raw=True)
            self.direct_input.add(state_sub, self._on_controller_period)
        else:
            self.create_subscription(PoseStamped, "robot_state", self._on_robot_state, 10)
        self.latency = LatencyWindow("trigger_to_correction_ms")  # the pose's stamp -> its correction published
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics)

    def pump(self, timeout_sec: float = 0.0) -> int:
        """Handle queued poses (see direct_input.py); spin() or a test harness calls this."""
        return self.direct_input.pump(timeout_sec)

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        try:
            values, gains = updated(self.values, parameters, gains_from)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.values, self.gains = values, gains
        if {p.name for p in parameters} & {"base_frame", "gauge_frame"}:
            self._publish_gauge_place()
        return SetParametersResult(successful=True)

    def _publish_gauge_place(self) -> None:
        """The gauge's place in the base frame (gauge_in_base) on /tf_static, for viewers and tf2 users."""
        self.tf_static_pub.publish(static_transform(self.values["base_frame"], self.values["gauge_frame"],
                                                    self.get_clock().now().nanoseconds, self.values["gauge_in_base"]))

    # ---------------------------------------------------------------- inputs
    def _vector(self, pose) -> np.ndarray:
        return self._pose_vector(*rotation_translation(pose))

    def _pose_vector(self, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
        anchor = self.anchor
        if anchor is None:
            anchor = self.mounting.rotation @ rotation
            if np.isfinite(anchor).all():  # a corrupt first pose (NaN) must not spoil every later one
                self.anchor = anchor
        return pose_vector_in_base(rotation, translation, self.mounting, anchor)

    def _on_reference(self, msg: PoseStamped) -> None:
        v = self.values
        if msg.header.frame_id != v["gauge_frame"]:
            self._refuse("reference", f"reference_pose in frame '{msg.header.frame_id}' ignored (gauge_frame is "
                                      f"'{v['gauge_frame']}')")
            return
        q = msg.pose.orientation
        if not unit_quaternion((q.x, q.y, q.z, q.w)):
            self._refuse("reference", "reference_pose ignored: its quaternion is not unit length")
            return
        age = time.time() - (msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
        if not stamp_age_ok(age, v["max_reference_age"], v["max_future"]):
            self._refuse("reference", "reference_pose ignored: " + describe_age(age, v["max_reference_age"],
                                                                                v["max_future"]))
            return
        with self._lock:
            reference = self._vector(msg.pose)
            if not np.isfinite(reference).all():
                self._refuse("reference", "reference_pose with NaN or inf ignored")
                return
            current = self.reference if self.reference is not None else self.last_measured
            if current is None:
                self._refuse("reference", "reference_pose ignored: no pose measured yet to check it against")
                return
            if np.any(np.abs(reference - current) > np.array(v["max_reference_step"])):
                self._refuse("reference", f"reference_pose ignored: it moves "
                                          f"{np.round(np.abs(reference - current), 6).tolist()} from the "
                                          f"{'current reference' if self.reference is not None else 'measured pose'}"
                                          f", beyond max_reference_step")
                return
            if self.reference is None or np.any(reference != self.reference):
                self.reference_came = time.monotonic()
            self.reference = reference

    def _on_robot_state(self, _msg) -> None:
        self.robot_heard = time.monotonic()

    def _on_controller_period(self, serialized: bytes) -> None:
        """period_clock robot_state: a controller period began; the poses since the last one drive the law.
        When the controller triggers the profiler (one pose a period), the pose of this STATE's own trigger
        waits for the next STATE, however soon it is estimated: loop_delay counts a period from a pose to the
        STATE it answers, and a STATE read late (its host stamp ms after the tick) must not answer with it."""
        try:
            state_stamp = decode_stamp(serialized) * 1e-9
        except CdrFormatError as exc:
            self.get_logger().error(f"malformed robot_state ignored: {exc}", throttle_duration_sec=1.0)
            return
        with self._lock:
            self.robot_heard = time.monotonic()
            period = self.values["control_period"]
            if self.pose_spacing and median(self.pose_spacing) >= ONE_POSE_A_PERIOD * period:
                cutoff = state_stamp - 0.5 * period
                poses = [pose for pose in self.period_poses if pose.stamp <= cutoff]
                self.period_poses = [pose for pose in self.period_poses if pose.stamp > cutoff]
            else:
                poses, self.period_poses = self.period_poses, []
            # fresh ones only: after a pause of the STATEs the buffer may hold poses older than max_pose_age
            oldest = time.time() - self.values["max_pose_age"]
            poses = [pose for pose in poses if pose.stamp >= oldest]
            if self.loop_refused or self.robot_heard > self.pose_fresh_until:
                return  # stale: the watchdog's zeros
            if not poses:
                self._coast(state_stamp)
                return
            velocity = self.modal.arm_velocity if self.modal is not None else self.filter.velocity
            fused = fuse_period(poses, velocity)
            self._drive(fused.stamp, fused.stamp_ns, fused.value, fused.variance, tick=state_stamp)

    def _coast(self, tick: float) -> None:
        """A controller period without a new pose (the estimate late, a profile refused): the modal law carries
        its state by the model and answers anyway, so a planned step's feedforward is not held up by the
        estimate; the PD law has nothing to add."""
        if self.modal is None or self.reference is None or self.probing:
            return
        if self.modal.coast(self.reference, tick, time.monotonic() - self.reference_came) is None:
            return
        self.coasted += 1
        self.corrections += 1
        self._publish(self.modal.limit(self.gains.arrays[2]), self.law_stamp_ns)

    def _on_lost(self, serialized: bytes) -> None:
        """The bridge: the controller never applied this increment (the tool's motion, m and rad) of its answer
        to the period stamped. The modal law's model counts the commands the controller applied (lost())."""
        try:
            stamp_ns, frame_id, motion = decode_twist_cdr(serialized)
        except CdrFormatError as exc:
            self.get_logger().error(f"malformed lost_increment ignored: {exc}", throttle_duration_sec=1.0)
            return
        # at most an answer's worth: anything larger is not one of ours (a stray publisher, a unit error)
        bound = 2.0 * self.gains.arrays[2] * self.values["control_period"]
        if frame_id != self.values["base_frame"] or not np.all(np.abs(motion) <= bound):
            self._refuse("lost_increment", f"lost_increment ignored: frame '{frame_id}', motion "
                                           f"{np.round(motion, 6).tolist()} (at most {np.round(bound, 6).tolist()})")
            return
        with self._lock:
            self.modal.lost(self.mounting.profiler_velocity(motion, self.last_rotation), stamp_ns * 1e-9)
            self.lost_told += 1

    def _on_pose(self, serialized: bytes) -> None:
        with self._lock:
            self._use_pose(serialized)

    @property
    def probing(self) -> bool:
        """The first-motion check is still probing: the loop is open."""
        return self.first_motion is not None and not self.first_motion.done

    @property
    def loop_refused(self) -> bool:
        """The first-motion check failed: this compensator moves nothing, ever (a restart checks again)."""
        return self.first_motion is not None and bool(self.first_motion.verdict)

    def _probe(self, z: np.ndarray, stamp_ns: int) -> None:
        """Before the loop closes: the first-motion check's probes, once the arm answers (robot_state within
        ROBOT_LIVE_S); zeros before, so that the bridge can arm on a live input."""
        check = self.first_motion
        if time.monotonic() - self.robot_heard > ROBOT_LIVE_S:
            check.reset()
            self._publish(np.zeros(6), stamp_ns)
            return
        self._publish(check.velocity(time.monotonic(), z), stamp_ns)
        if check.done:
            if check.verdict:
                self.get_logger().error(check.verdict)
            else:
                self.get_logger().info("first-motion check passed; closing the loop")
            self.get_logger().info(f"first-motion response (column k: the measured motion per unit probe on axis k, "
                                   f"x y z rx ry rz; the identity when the calibration is right):\n"
                                   f"{np.array2string(check.response, precision=3, suppress_small=True)}")
            for state in (self.filter, self.modal, self.shaper):
                if state is not None:
                    state.reset()

    def _use_pose(self, serialized: bytes) -> None:
        received = time.monotonic()
        try:
            pose_stamp_ns, frame_id, pose, covariance = decode_pose_with_covariance_cdr(serialized)
        except CdrFormatError as exc:
            self.get_logger().error(f"malformed pose ignored: {exc}", throttle_duration_sec=1.0)
            return
        v = self.values
        stamp = pose_stamp_ns * 1e-9
        age = time.time() - stamp
        if not stamp_age_ok(age, v["max_pose_age"], v["max_future"]):
            if age < 0 or math.isnan(age):
                self._refuse("future", "pose ignored: " + describe_age(age, v["max_pose_age"], v["max_future"]))
            else:
                self.refused["stale"] += 1  # stale on arrival: the watchdog sends zeros
            return
        if frame_id != v["gauge_frame"]:
            self._refuse("frame", f"pose in frame '{frame_id}' ignored (gauge_frame is '{v['gauge_frame']}')")
            return
        if not unit_quaternion(pose[3:]):
            self._refuse("orientation", "pose ignored: its quaternion is not unit length")
            return
        # a NaN or an inf anywhere survives a sum; checked before any arithmetic, which would warn
        if not math.isfinite(sum(pose) + (covariance.sum() if self.values["use_covariance"] else 0.0)):
            self.get_logger().error("pose with NaN or inf ignored", throttle_duration_sec=1.0)
            return
        if math.hypot(*pose[:3]) > v["max_pose_range"]:
            self._refuse("range", f"pose {math.hypot(*pose[:3]):.3g} m from the profiler ignored (max_pose_range "
                                  f"{v['max_pose_range']:g} m)")
            return
        rotation = rotation_from_quaternion_xyzw(np.array(pose[3:]))
        z = self._pose_vector(rotation, np.array(pose[:3]))
        if self.values["use_covariance"]:
            sigma = position_sigma(covariance[:3, :3])
            if sigma > v["max_position_sigma"]:
                self._refuse("imprecise", f"pose ignored: its position std {sigma * 1e3:.3f} mm exceeds "
                                          f"max_position_sigma {v['max_position_sigma'] * 1e3:g} mm")
                return
            variance = covariance_in_base(covariance, self.mounting)
        else:
            variance = np.full(6, self.values["measurement_std"] ** 2)
        # a zero quaternion (no rotation) gives NaN, a vast covariance inf; a zero or negative variance would
        # poison the filter for good (every later correction NaN)
        if not math.isfinite(z.sum() + variance.sum()) or not np.all(variance > 0.0):
            self._refuse("covariance", "pose with an invalid orientation or a covariance that is not positive "
                                       "ignored")
            return
        if self.last_pose_stamp:
            self.pose_spacing.append(stamp - self.last_pose_stamp)
        self.last_pose_stamp = stamp
        self.pose_fresh_until = fresh_until(received, age, v["max_pose_age"])
        self.last_measured = z
        self.last_rotation = rotation
        self.poses += 1
        if self.probing:
            if self.reference is not None:
                self._probe(z, pose_stamp_ns)
            return  # no reference: the watchdog keeps the output at zero
        if self.loop_refused:
            return
        if self.values["period_clock"] == "robot_state" and received - self.robot_heard <= ROBOT_LIVE_S:
            self.period_poses.append(PeriodPose(stamp, pose_stamp_ns, z, variance))
            return
        # the poses' clock, also while the controller's STATEs do not flow (the bridge arms on a live correction)
        self.period_poses = []
        self._drive(stamp, pose_stamp_ns, z, variance)

    def _drive(self, stamp: float, stamp_ns: int, z: np.ndarray, variance: np.ndarray,
               tick: float | None = None) -> None:
        """One measurement through the law, and its correction (the modal law: one a period). tick: the
        controller's tick that began the period (period_clock robot_state)."""
        self.law_stamp_ns = stamp_ns  # a correction the model makes alone (_coast) carries the newest pose it used
        if self.modal is not None:
            self.modal.update(stamp, z, variance, self.reference, tick, time.monotonic() - self.reference_came)
            if tick is not None:
                self.pose_ages_at_state.append(tick - stamp)
            if self.reference is None:
                return  # no target yet: the watchdog keeps the output at zero
            self.last_error = self.reference - self.modal.position
            velocity = self.modal.limit(self.gains.arrays[2])
            if not self.modal.started_period:
                return  # this period's increment went out with its first pose: one correction a period
        else:
            self.filter.update(stamp, z, variance)
            if self.reference is None:
                return
            self.last_error = self.reference - self.filter.position
            velocity = pd_velocity(self.last_error, self.filter.velocity, self.gains)
            if self.shaper is not None:
                velocity = self.shaper(stamp, velocity)  # a mix of limited velocities: still within max_speed
        self._publish(velocity, stamp_ns)
        self.latency.add(time.time() - stamp)
        self.corrections += 1

    def _publish(self, velocity: np.ndarray, stamp_ns: int) -> None:
        """`velocity`: of the profiler origin; sent as the tool's."""
        velocity = self.mounting.tool_velocity(velocity, self.last_rotation)
        serialized = encode_twist_cdr(velocity, stamp_ns, self.values["base_frame"])
        self.correction_out.publish(serialized)
        self.correction_out.hand_over(serialized)  # composed: to the bridge, in this thread

    def _watchdog(self) -> float:
        """Zero correction while the pose is stale or there is no reference, repeated at watchdog_rate;
        returns when to look again: while poses keep coming, only when the newest would turn stale."""
        with self._lock:
            return self._check_staleness()

    def _check_staleness(self) -> float:
        now = time.monotonic()
        if self.loop_refused:  # silent: the bridge's input timeout stops the session
            return now + 1.0
        if self.reference is not None and now <= self.pose_fresh_until:
            return self.pose_fresh_until + 1e-4
        # The next fresh pose starts the filter again, not from old motion; nor does old shaped motion
        # come back after a stale spell.
        # (a first-motion probe runs on: it is timed, and a stale spell only thins its records)
        for state in (self.filter, self.modal, self.shaper):
            if state is not None:
                state.reset()
        self.period_poses = []
        # Stamped with the newest pose's trigger time: a zero that says how old its information is. Once
        # the poses are stale it is stale too, so the bridge sees the stream end and disarms until ~/start
        # (a zero stamped now would keep a session alive that a restarted estimator then moves again).
        self._publish(np.zeros(6), int(self.last_pose_stamp * 1e9))
        self.stale_zeros += 1
        return now + 1.0 / self.values["watchdog_rate"]

    def _publish_diagnostics(self) -> None:
        age = time.time() - self.last_pose_stamp if self.last_pose_stamp else float("inf")
        if self.loop_refused:
            level, message = ERROR, self.first_motion.verdict
        elif self.reference is None:
            level, message = WARN, "no reference_pose yet: correction zero"
        elif self.probing:
            level, message = WARN, "first-motion check: probing (the loop is open)"
        elif time.monotonic() > self.pose_fresh_until:
            level, message = WARN, f"pose stale ({age:.3f} s old): correction zero"
        else:
            level, message = OK, "correcting"
        values = {"poses": self.poses, "corrections": self.corrections, "zero_corrections": self.stale_zeros,
                  "has_reference": self.reference is not None, "first_motion": self._first_motion_state(),
                  "pose_age_ms": age * 1e3, "error_um": [round(float(e) * 1e6, 1) for e in self.last_error[:3]],
                  "control_law": self.values["control_law"], "kp": list(self.gains.kp), "kd": list(self.gains.kd),
                  **{f"refused_{why}": count for why, count in self.refused.items()},
                  **self.latency.report()}
        if self.modal is not None:
            values["poses_within_a_period"] = self.modal.skipped  # not used: one pose a period drives the law
            values["periods_coasted"] = self.coasted
            values["lost_increments_told"] = self.lost_told
            if self.pose_ages_at_state:  # period_clock robot_state: how old the newest pose is at its STATE
                values["pose_age_at_state_ms"] = round(median(self.pose_ages_at_state) * 1e3, 3)
        self.diagnostics_pub.publish(diagnostic_array(self, "compensator", "pd_compensator",
                                                      level, message, values))


    def _first_motion_state(self) -> str:
        check = self.first_motion
        if check is None:
            return "off"
        if check.done:
            return "refused" if check.verdict else "passed"
        if self.reference is None:
            return "waiting for a reference"
        if time.monotonic() - self.robot_heard > ROBOT_LIVE_S:
            return "waiting for the arm"
        return f"probing {check.probing}" + (f" (restarted {check.restarts}x)" if check.restarts else "")


def main(args=None) -> int:
    return run_node(PdCompensatorNode, NODE_NAME, args, startup_errors=(ValueError,),
                    spin=lambda executor, node, stop: spin(executor, node.direct_input, stop))


if __name__ == "__main__":
    sys.exit(main())
