"""profile_pose fuzz's node targets: decoded but absurd values through the nodes' own logic.

The decoders only promise a documented error for bytes they cannot read. What a node then does with a
well-formed message carrying a non-unit quaternion, a NaN, a stamp an hour ahead, a foreign frame or a
covariance of -1e300 is the other half. Here pd_compensator and motoplus_bridge run composed in this
process (as cell_container runs them, LocalTopics carrying the correction), nobody spinning: each case is
one pose (or reference) handed to the compensator's callback; whatever correction it produces goes on to the
bridge's, and through the bridge's client the increment it would send is computed. An oracle that shares no
code with the nodes re-derives from the raw values what must be refused, and the case is unexpected when:

- a pose in another frame, with a quaternion off unit length by more than 1e-3, a non-finite value, a
  position beyond max_pose_range, or a stamp outside [-max_future, max_pose_age] of now yields a correction;
- the bridge takes a correction (from the compensator, or handed to it directly as a rogue publisher would)
  in another frame, non-finite, or stamped outside its own [-max_future, max_age];
- the compensator publishes a non-finite correction, or one faster than its max_speed (whatever state
  earlier cases left its filter in);
- a correction is non-finite or faster than the compensator's max_speed, or an increment leaves the
  bridge's per-period clamp, or the bridge's safety monitor objects to it.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..core.wire.motoplus_protocol import metres_to_units
from ..core.wire.pose_cdr import decode_twist_cdr, encode_pose_with_covariance_cdr, encode_twist_cdr
from ..core.model.rotation import quaternion_xyzw, so3_exp
from .processes import fresh_domain_id

NOMINAL = np.array([0.01, -0.02, 0.40])
# (age of the stamp in seconds, as the case's first byte picks it; None: stamped 0, 1970)
AGES = (0.0, 0.0, 0.0, 0.001, 0.01, -0.001, -0.004, 0.2, 2.0, -3600.0, 3600.0, None)
SCALES = (1.0, 1.0, 1.0, 1.0 + 5e-4, 1.0 - 5e-4, 1.0 + 2e-3, 0.5, 0.0, 1e-30, 1e3)  # of the quaternion
FRAMES = ("gauge", "gauge", "gauge", "gauge", "", "base", "cell_2/gauge", "gauge ")


class Refused(Exception):
    """The nodes refused the case, as the oracle said they must or for a reason of their own."""


class UnsafeOutcome(AssertionError):
    """What the fuzzer looks for: not caught as expected."""


def _norm(q: np.ndarray) -> float:
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 squared: inf, which is "not unit" too
        return float(np.linalg.norm(q))


def _raw_float(data: bytes, at: int) -> float:
    return float(np.frombuffer(data[at:at + 8].ljust(8, b"\0"), dtype="<f8")[0])


def pose_case(data: bytes) -> tuple[np.ndarray, np.ndarray, float | None, str]:
    """Bytes -> (px py pz qx qy qz qw, 6x6 covariance, stamp age, frame): near a real pose, with each of
    its parts pushed to an edge as the bytes say."""
    b = data.ljust(48, b"\0")
    age = AGES[b[0] % len(AGES)]
    frame = FRAMES[b[1] % len(FRAMES)]
    scale = SCALES[(b[1] >> 3) % len(SCALES)]
    flags = b[2]
    small = np.frombuffer(b[3:9], dtype=np.int8).astype(float)
    position = NOMINAL + small[:3] * 1e-5
    quaternion = quaternion_xyzw(so3_exp(small[3:] * 1e-3)) * scale
    covariance = np.diag([1e-10] * 3 + [1e-8] * 3)
    pose = np.concatenate([position, quaternion])
    if flags & 1:
        pose[b[9] % 7] = _raw_float(b, 10)  # any double: NaN, inf, 1e308, a denormal
    if flags & 2:
        covariance[b[18] % 6, b[18] % 6] = _raw_float(b, 19)
    if flags & 4:
        covariance = -covariance
    if flags & 8:
        covariance = np.zeros((6, 6))
    return pose, covariance, age, frame


class NodeChain:
    """pd_compensator -> motoplus_bridge in one process, with a reference at the nominal pose."""

    def __init__(self) -> None:
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from rclpy.context import Context
        from rclpy.time import Time

        from ..nodes.local_topics import LocalTopics
        from ..nodes.motoplus_bridge import MotoPlusBridgeNode
        from ..nodes.pd_compensator import PdCompensatorNode

        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=fresh_domain_id())
        local = LocalTopics()
        # the bridge is never armed: no connection is made, and its client still computes each increment
        self.bridge = MotoPlusBridgeNode(local=local, context=self.context)
        self.compensator = PdCompensatorNode(local=local, context=self.context)
        self.published: list[np.ndarray] = []  # every correction the compensator hands on, as the bridge gets it
        local.take(self.bridge.resolve_topic_name("correction"), lambda data: self.published.append(decode_twist_cdr(data)[2]))
        self.c = self.compensator.values
        self.b = self.bridge.values
        self.client = self.bridge.client
        self.max_step_units = np.array(metres_to_units(self.client.limits.max_step))
        self.client.monitor.rearmed()  # judged as in an armed session, at the start pose
        self.max_correction_speed = np.full(6, np.inf)  # a rogue correction may be fast: the clamp bounds it
        self._pose(np.concatenate([NOMINAL, [0.0, 0.0, 0.0, 1.0]]), np.diag([1e-10] * 3 + [1e-8] * 3), 0.0, "gauge")
        reference = PoseStamped()
        reference.header.frame_id = self.c["gauge_frame"]
        reference.header.stamp = Time(nanoseconds=time.time_ns()).to_msg()
        reference.pose.position.x, reference.pose.position.y, reference.pose.position.z = (NOMINAL + 1e-3).tolist()
        reference.pose.orientation.w = 1.0
        self.compensator._on_reference(reference)
        if self.compensator.reference is None:
            raise RuntimeError("the node fuzzer could not set its reference")
        self._reference_type = PoseStamped
        self._time = Time

    def close(self) -> None:
        self.compensator.destroy_node()
        self.bridge.destroy_node()
        self.rclpy.shutdown(context=self.context)

    def _pose(self, pose: np.ndarray, covariance: np.ndarray, age: float | None, frame: str) -> list:
        """Hands one pose to the compensator; returns the corrections the bridge took from it."""
        stamp_ns = 0 if age is None else int((time.time() - age) * 1e9)
        before = len(self.bridge._velocities)
        self.compensator._on_pose(encode_pose_with_covariance_cdr(pose, covariance, stamp_ns, frame))
        return self.bridge._velocities[before:]

    def pose_case(self, data: bytes) -> None:
        pose, covariance, age, frame = pose_case(data)
        must_refuse = (frame != self.c["gauge_frame"] or age is None or not -self.c["max_future"] < age < self.c["max_pose_age"]
                       or not np.all(np.isfinite(pose)) or abs(_norm(pose[3:]) - 1.0) > 1e-3
                       or _norm(pose[:3]) > self.c["max_pose_range"]
                       or (self.c["use_covariance"] and not np.all(np.isfinite(covariance))))
        with self.bridge._lock:
            self.bridge._velocities.clear()
        self.published.clear()
        taken = self._pose(pose, covariance, age, frame)
        if must_refuse and self.published:
            raise UnsafeOutcome("pd_compensator corrected from a pose that must be refused "
                                f"(frame {frame!r}, age {age}, pose {pose.tolist()})")
        for velocity in self.published:
            if not np.all(np.isfinite(velocity)) or np.any(np.abs(velocity) > np.array(self.c["max_speed"]) + 1e-12):
                raise UnsafeOutcome(f"pd_compensator published {velocity.tolist()} (covariance diagonal "
                                    f"{np.diag(covariance).tolist()})")
        self._judge(taken, must_refuse)

    def correction_case(self, data: bytes) -> None:
        """A correction straight to the bridge, as a rogue or broken publisher would send it."""
        b = data.ljust(48, b"\0")
        age = AGES[b[0] % len(AGES)]
        frame = ("base", "base", "base", "", "gauge", "base ")[b[1] % 6]
        velocity = np.frombuffer(b[2:8], dtype=np.int8).astype(float) * 1e-3
        if b[8] & 1:
            velocity[b[9] % 6] = _raw_float(b, 10)
        must_refuse = (frame != self.b["base_frame"] or age is None or not np.all(np.isfinite(velocity))
                       or not -self.b["max_future"] < age < self.b["max_age"])
        with self.bridge._lock:
            self.bridge._velocities.clear()
        stamp_ns = 0 if age is None else int((time.time() - age) * 1e9)
        self.bridge._on_correction(encode_twist_cdr(velocity, stamp_ns, frame))
        taken = list(self.bridge._velocities)
        if must_refuse and taken:
            raise UnsafeOutcome(f"the bridge took a correction that must be refused (frame {frame!r}, age {age})")
        self._judge(taken, must_refuse, self.max_correction_speed)

    def reference_case(self, data: bytes) -> None:
        """A fuzzed reference, then a valid pose: whatever reference was taken, the correction stays bounded."""
        pose, _, age, frame = pose_case(data)
        msg = self._reference_type()
        msg.header.frame_id = frame
        msg.header.stamp = self._time(nanoseconds=0 if age is None else int((time.time() - age) * 1e9)).to_msg()
        p, q = msg.pose.position, msg.pose.orientation
        p.x, p.y, p.z, q.x, q.y, q.z, q.w = (float(v) for v in pose)
        previous = self.compensator.reference
        self.compensator._on_reference(msg)
        reference = self.compensator.reference
        if reference is not None and not np.all(np.isfinite(reference)):
            raise UnsafeOutcome(f"a non-finite reference was taken: {reference}")
        if previous is not None and reference is not None and np.any(
                np.abs(reference - previous) > np.array(self.c["max_reference_step"]) + 1e-12):
            raise UnsafeOutcome(f"the reference jumped {np.abs(reference - previous)}")
        with self.bridge._lock:
            self.bridge._velocities.clear()
        taken = self._pose(np.concatenate([NOMINAL, [0.0, 0.0, 0.0, 1.0]]), np.diag([1e-10] * 3 + [1e-8] * 3), 0.0,
                           "gauge")
        self._judge(taken, False)
        if reference is previous:
            raise Refused("reference refused")

    def _judge(self, taken: list, must_refuse: bool, max_speed: np.ndarray | None = None) -> None:
        """What the bridge took, and the increment it would send from it, against the bounds."""
        max_speed = np.array(self.c["max_speed"]) if max_speed is None else max_speed
        if must_refuse and taken:
            raise UnsafeOutcome(f"a correction from a pose that must be refused: {taken}")
        now = time.time()
        for stamp_ns, velocity, _ in taken:
            age = now - stamp_ns * 1e-9
            if not -self.b["max_future"] - 1e-3 < age < self.b["max_age"] + 1e-3:
                raise UnsafeOutcome(f"the bridge took a correction {age:.3f} s old")
            if not np.all(np.isfinite(velocity)) or np.any(np.abs(velocity) > max_speed + 1e-12):
                raise UnsafeOutcome(f"correction {velocity} beyond max_speed")
        move = self.bridge._increment(now)
        if move is not None:
            step, stamp = move
            units = self.client.units_for(step)
            if np.any(np.abs(units) > self.max_step_units):
                raise UnsafeOutcome(f"increment {units} beyond the clamp {self.max_step_units}")
            broken = self.client.monitor.check(units, True, stamp, now, (0,) * 6)
            if broken:
                raise UnsafeOutcome(f"the bridge's safety monitor: {self.client.monitor.last_violation}")
        if not taken:
            raise Refused("no correction")


def pose_seeds() -> list[bytes]:
    """A valid pose, and one per edge: each age, frame, scale and flag."""
    seeds = [bytes(48)]
    seeds += [bytes([k]) + bytes(47) for k in range(len(AGES))]
    seeds += [bytes([0, k]) + bytes(46) for k in range(0, 8 * len(SCALES), 3)]
    seeds += [bytes([0, 0, flag, 5, 250, 1, 3, 0, 2, 3]) + np.array([math.nan], "<f8").tobytes() + bytes([4])
              + np.array([-1e300], "<f8").tobytes() + bytes(21) for flag in (1, 2, 3, 4, 8)]
    return seeds
