"""The PD compensator's computation without ROS: pose error in the robot base frame, a Kalman filter that
weights each measurement by the estimator's covariance, and a PD law whose output is a velocity (the
bridge integrates it into one increment per controller period).

Why a filter: at 5 um profile noise the estimated pose scatters by tens of um along the gauge's weakly
observable direction; fed straight into the loop that scatter would move the arm. A constant-velocity
Kalman filter per axis, with the measurement variance taken from each pose's published covariance,
follows the arm's 10 Hz motion and averages the noise where the estimator says it is large.

Why an input shaper: the arm's 10 Hz mode is barely damped at small amplitude (the y axis rings for
seconds), and every correction, whether it answers a reference step or the estimate's noise, is a
staircase that excites it. A ZVD shaper (three impulses half a ringing period apart) has a double zero
at the mode, so the commands the loop sends carry (almost) nothing at 10 Hz, with +-20 % tolerance on
the frequency; it costs half a period of mean delay (50 ms), small next to the loop's 0.25 s time constant.
"""
from __future__ import annotations

from bisect import bisect_right
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from math import comb

import numpy as np

from ..model.rotation import so3_exp, so3_log


@dataclass(frozen=True)
class Gains:
    kp: tuple[float, ...]  # 1/s: velocity per metre (radian) of error
    kd: tuple[float, ...]  # velocity per velocity: damping of the arm's own motion
    max_speed: tuple[float, ...]  # m/s and rad/s, per axis

    @cached_property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """kp, kd and max_speed as read-only arrays: built once, not at every pose."""
        return tuple(_read_only(np.array(values, dtype=float)) for values in (self.kp, self.kd, self.max_speed))

    def check(self) -> None:
        for name, values, low, high in (("kp", self.kp, 0.0, 200.0), ("kd", self.kd, -2.0, 5.0),
                                        ("max_speed", self.max_speed, 0.0, 1.0)):
            if len(values) != 6 or not all(np.isfinite(values)) or min(values) < low or max(values) > high:
                raise ValueError(f"{name} needs six values in [{low}, {high}], got {list(values)}")


@dataclass(frozen=True)
class Mounting:
    """Where things are: the gauge in the robot base frame, and the profiler on the controller's tool (each a
    translation and a rotation vector), as profile_pose_calibrate measures them."""

    gauge_in_base: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # x y z (m), rx ry rz (rad)
    profiler_in_tool: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    # computed once: every pose needs them
    # and read-only, since every caller shares them
    @cached_property
    def rotation(self) -> np.ndarray:
        return _read_only(so3_exp(np.asarray(self.gauge_in_base[3:], dtype=float)))

    @cached_property
    def translation(self) -> np.ndarray:
        return _read_only(np.asarray(self.gauge_in_base[:3], dtype=float))

    @cached_property
    def _lever_in_profiler(self) -> np.ndarray:
        """The tool origin -> the profiler origin, in the profiler's frame (R_TP^T t_TP)."""
        return _read_only(so3_exp(np.asarray(self.profiler_in_tool[3:], dtype=float)).T
                          @ np.asarray(self.profiler_in_tool[:3], dtype=float))

    def tool_velocity(self, velocity: np.ndarray, profiler_rotation: np.ndarray) -> np.ndarray:
        """The tool's velocity (base axes) that moves the profiler origin by `velocity`: the controller turns
        the tool about its own origin, which carries the profiler along its lever arm. profiler_rotation: F
        in G, the newest pose's."""
        if not any(self.profiler_in_tool[:3]) or not np.any(velocity[3:]):
            return velocity
        lever = self.rotation @ profiler_rotation @ self._lever_in_profiler  # base coordinates
        return np.concatenate([velocity[:3] - np.cross(velocity[3:], lever), velocity[3:]])

    def profiler_velocity(self, tool_velocity: np.ndarray, profiler_rotation: np.ndarray) -> np.ndarray:
        """tool_velocity's inverse: how the profiler origin moves when the tool moves so."""
        if not any(self.profiler_in_tool[:3]) or not np.any(tool_velocity[3:]):
            return tool_velocity
        lever = self.rotation @ profiler_rotation @ self._lever_in_profiler
        return np.concatenate([tool_velocity[:3] + np.cross(tool_velocity[3:], lever), tool_velocity[3:]])


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def pose_vector_in_base(rotation: np.ndarray, translation: np.ndarray, mounting: Mounting,
                        anchor: np.ndarray) -> np.ndarray:
    """The profiler pose (F in G) as 6 numbers in base coordinates: F's origin in B, and F's rotation in B
    relative to `anchor` (a base-frame rotation, e.g. the first reference) as a rotation vector."""
    r_bg = mounting.rotation
    position = r_bg @ translation + mounting.translation
    return np.concatenate([position, so3_log(r_bg @ rotation @ anchor.T)])


def covariance_in_base(covariance: np.ndarray, mounting: Mounting) -> np.ndarray:
    """Per-axis variances of a ROS-order (x y z rx ry rz) 6x6 covariance in G, expressed in B: the diagonal
    of R C R^T for the position and the rotation blocks (R block-diagonal, so the cross terms drop out)."""
    r = mounting.rotation
    return np.concatenate([((r @ covariance[:3, :3]) * r).sum(axis=1), ((r @ covariance[3:, 3:]) * r).sum(axis=1)])


class AxisKalman:
    """Six independent constant-velocity filters: state [position, velocity] per axis, and each axis's
    2 x 2 covariance as its three distinct entries. On Python floats, axis by axis: numpy's per-call
    overhead on six-element arrays costs several times the arithmetic (docs/design_notes.md)."""

    def __init__(self, acceleration_psd: np.ndarray) -> None:
        self.q = [float(v) for v in np.asarray(acceleration_psd, dtype=float)]  # (m/s^2)^2 / Hz, per axis
        self.reset()

    def reset(self) -> None:
        self.time: float | None = None
        self.pos: list[float] | None = None
        self.vel = [0.0] * 6
        self.p00, self.p01, self.p11 = [0.0] * 6, [0.0] * 6, [0.0] * 6  # position, cross, velocity

    def update(self, time: float, z: np.ndarray, variance: np.ndarray) -> None:
        z = np.asarray(z, dtype=float).tolist()
        variance = [max(v, 1e-18) for v in np.asarray(variance, dtype=float).tolist()]
        if self.pos is None or self.time is None or time <= self.time:
            self.pos, self.vel = z, [0.0] * 6
            self.p00, self.p01, self.p11 = variance, [0.0] * 6, [1e-2] * 6
            self.time = time
            return
        dt = time - self.time
        self.time = time
        dt2, dt3 = dt * dt / 2, dt ** 3 / 3
        pos, vel, p00, p01, p11 = self.pos, self.vel, self.p00, self.p01, self.p11
        for i, q in enumerate(self.q):
            # predict: x <- F x, P <- F P F^T + q Q, F = [[1, dt], [0, 1]], Q = [[dt^3/3, dt^2/2], [dt^2/2, dt]]
            c01 = p01[i] + dt * p11[i]
            c00 = p00[i] + dt * (p01[i] + c01) + q * dt3
            c01 += q * dt2
            c11 = p11[i] + q * dt
            predicted = pos[i] + dt * vel[i]
            # correct with the measured position: k = P H^T / (H P H^T + r), P <- P - k H P
            k0, k1 = c00 / (c00 + variance[i]), c01 / (c00 + variance[i])
            innovation = z[i] - predicted
            pos[i], vel[i] = predicted + k0 * innovation, vel[i] + k1 * innovation
            p00[i], p01[i], p11[i] = c00 - k0 * c00, c01 - k0 * c01, c11 - k1 * c01

    @property
    def position(self) -> np.ndarray:
        return np.array(self.pos)

    @property
    def velocity(self) -> np.ndarray:
        return np.array(self.vel)


def pd_velocity(error: np.ndarray, velocity: np.ndarray, gains: Gains) -> np.ndarray:
    """v = kp * error - kd * velocity, limited per axis to max_speed."""
    kp, kd, limit = gains.arrays
    return np.minimum(np.maximum(kp * error - kd * velocity, -limit), limit)


def zvd_impulses(frequency_hz: float, damping: float) -> tuple[tuple[float, float], ...]:
    """(delay s, gain) of the zero-vibration-derivative shaper for a mode at frequency_hz (natural) and
    damping; the gains sum to 1, so a shaped command reaches the same place."""
    return zero_vibration_impulses(frequency_hz, damping, derivatives=1)


def zero_vibration_impulses(frequency_hz: float, damping: float, derivatives: int) -> tuple[tuple[float, float], ...]:
    """(delay s, gain) of the zero-vibration shaper with `derivatives` zero derivatives (0: ZV, 1: ZVD,
    2: ZVDD): each one more half period long and more tolerant of a wrong frequency (ZVD leaves ~5 % of the
    vibration at +-15 % frequency error, ZVDD at +-25 %). Gains are (1 + K)^m's binomial terms, m =
    derivatives + 1, normalised to sum to 1."""
    if not (frequency_hz > 0 and 0 <= damping < 1) or derivatives < 0:
        raise ValueError(f"shaper needs a frequency > 0 and a damping in [0, 1), got {frequency_hz}, {damping}")
    root = np.sqrt(1 - damping ** 2)
    k = np.exp(-damping * np.pi / root)
    half_period = 0.5 / (frequency_hz * root)
    m = derivatives + 1
    gains = [comb(m, i) * k ** i for i in range(m + 1)]
    return tuple((i * half_period, float(g / sum(gains))) for i, g in enumerate(gains))


class InputShaper:
    """Shapes a sampled command (e.g. the velocity of each control period) by a set of impulses:
    out(t) = sum of gain * command(t - delay). Delays fall between samples (50 ms is 4.17 periods of
    12 ms): there the command is interpolated between its two samples, since rounding the delay to whole
    periods would move the shaper's zero by up to 24 %, past what it tolerates. One sampling period
    before the first sample (or a reset) the command was zero."""

    def __init__(self, impulses: tuple[tuple[float, float], ...]) -> None:
        self.impulses = impulses
        self.span = max(delay for delay, _ in impulses)
        self.times: deque[float] = deque()
        self.values: deque[np.ndarray] = deque()
        self.period = 0.0  # the latest sampling interval: where the zero before the first sample sits

    def reset(self) -> None:
        self.times.clear()
        self.values.clear()

    def __call__(self, time: float, command: np.ndarray) -> np.ndarray:
        if self.times and time <= self.times[-1]:
            self.reset()  # time went backwards: start again rather than mix two histories
        if self.times:
            self.period = time - self.times[-1]
        self.times.append(time)
        self.values.append(np.asarray(command, dtype=float))
        while len(self.times) > 1 and self.times[1] <= time - self.span:
            self.times.popleft()  # the sample at or before time - span is the oldest any impulse needs
            self.values.popleft()
        out = np.zeros_like(self.values[-1])
        for delay, gain in self.impulses:
            out += gain * self._at(time - delay)
        return out

    def _at(self, when: float) -> np.ndarray:
        after = bisect_right(self.times, when)
        if after == 0:
            share = 1 - (self.times[0] - when) / self.period if self.period > 0 else 0.0
            return max(share, 0.0) * self.values[0]
        if after == len(self.times):
            return self.values[-1]
        t0, t1 = self.times[after - 1], self.times[after]
        share = (when - t0) / (t1 - t0)
        return (1 - share) * self.values[after - 1] + share * self.values[after]
