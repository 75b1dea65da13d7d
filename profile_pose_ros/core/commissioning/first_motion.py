"""The first-motion check: before the loop closes, a small probing move per axis, and the measured response
compared with what the calibration predicts.

The compensator turns pose errors into robot motion through gauge_in_base and profiler_in_tool. If either is
wrong the loop pushes the wrong way: a sign flip or a swapped axis makes it unstable, a rotation error turns
each correction away from the error. Each probe moves the profiler origin by a known amount along one base
axis (or turns it about one), open loop, and the estimated poses, taken into base coordinates with the same
calibration the loop will use, say how it really moved. With the calibration right the 6 x 6 response is the
identity; the check refuses to close the loop, naming what it found, when it is not near enough.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model.rotation import so3_log
from .procedure import minimum_jerk_rate

AXES = ("x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class ProbeDesign:
    amplitude: tuple[float, ...] = (5e-4, 5e-4, 5e-4, 5e-3, 5e-3, 5e-3)  # m, rad
    move_s: float = 0.25
    settle_s: float = 0.35
    record_s: float = 0.25
    max_rotation_error: float = 0.05  # rad: of the response's translation or rotation block
    max_lever_error: float = 5e-3  # m: how far a turn may move the profiler's origin per radian
    gain_range: tuple[float, float] = (0.6, 1.4)  # each axis's response over its command

    @property
    def axis_s(self) -> float:
        return 2 * (self.record_s + self.move_s + self.settle_s)


@dataclass
class FirstMotionCheck:
    """Fed one measured pose vector per pose (base coordinates: the profiler origin, and its rotation
    vector from an anchor), it returns the velocity to command; `verdict` is set when done: "" passed."""

    design: ProbeDesign = field(default_factory=ProbeDesign)
    verdict: str | None = None
    response: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    restarts: int = 0
    _axis: int = 0
    _start: float | None = None
    _before: list[np.ndarray] = field(default_factory=list)
    _after: list[np.ndarray] = field(default_factory=list)

    @property
    def done(self) -> bool:
        return self.verdict is not None

    def reset(self) -> None:
        """The arm stopped answering (the bridge disarmed) or the poses went stale mid-probe: begin again from
        the first axis. A finished check stays finished."""
        if not self.done and (self._axis or self._start is not None):
            self.restarts += 1
            self._axis, self._start, self._before, self._after = 0, None, [], []

    @property
    def probing(self) -> str:
        """The axis being probed."""
        return AXES[min(self._axis, 5)]

    def velocity(self, now: float, measured: np.ndarray) -> np.ndarray:
        if self.done:
            return np.zeros(6)
        if self._start is None:
            self._start = now
        d = self.design
        t = now - self._start
        phases = np.cumsum([d.record_s, d.move_s, d.settle_s, d.record_s, d.move_s, d.settle_s])
        amplitude = np.zeros(6)
        amplitude[self._axis] = d.amplitude[self._axis]
        if t < phases[0]:
            self._before.append(measured)
        elif t < phases[1]:
            return amplitude * minimum_jerk_rate((t - phases[0]) / d.move_s) / d.move_s
        elif phases[2] <= t < phases[3]:
            self._after.append(measured)
        elif phases[3] <= t < phases[4]:
            return -amplitude * minimum_jerk_rate((t - phases[3]) / d.move_s) / d.move_s
        elif t >= phases[5]:
            self._finish_axis(now)
        return np.zeros(6)

    def _finish_axis(self, now: float) -> None:
        if not self._before or not self._after:
            self.verdict = f"first-motion check: no poses while probing {AXES[self._axis]}"
            return
        change = np.mean(self._after, axis=0) - np.mean(self._before, axis=0)
        self.response[:, self._axis] = change / self.design.amplitude[self._axis]
        wrong = judge_axis(self.response[:, self._axis], self._axis, self.design)  # no further probe if so
        self._axis += 1
        self._start, self._before, self._after = now, [], []
        if wrong or self._axis == 6:
            self.verdict = wrong or judge(self.response, self.design)


def judge_axis(column: np.ndarray, axis: int, design: ProbeDesign) -> str:
    """What is wrong with one probe's response (a column of the response), in words; "" if nothing."""
    offset = 0 if axis < 3 else 3
    block, k = column[offset:offset + 3], axis - offset
    kind = "moved" if axis < 3 else "turned"
    strongest = int(np.argmax(np.abs(block)))
    if strongest != k:
        return (f"first-motion check refused: a probe along {AXES[axis]} {kind} the profiler along "
                f"{AXES[offset + strongest]} (response {block.round(2).tolist()}): an axis swap in gauge_in_base or "
                "the controller's frame; the loop stays open")
    if block[k] < 0:
        return (f"first-motion check refused: a probe along {AXES[axis]} {kind} the profiler the opposite way "
                f"(response {block[k]:.2f}): a sign flip; the loop stays open")
    low, high = design.gain_range
    if not low <= block[k] <= high:
        return (f"first-motion check refused: a probe along {AXES[axis]} {kind} the profiler {block[k]:.2f} of the "
                f"command (outside {low:g}..{high:g}: units, a clamp, or a blocked axis); the loop stays open")
    return ""


def judge(response: np.ndarray, design: ProbeDesign) -> str:
    """"" when the response is the identity within the design's bounds, else what is wrong, in words."""
    for axis in range(6):
        wrong = judge_axis(response[:, axis], axis, design)
        if wrong:
            return wrong
    for block, kind in ((response[:3, :3], "moved"), (response[3:, 3:], "turned")):
        u, _, vt = np.linalg.svd(block)
        angle = float(np.linalg.norm(so3_log(u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt)))
        if angle > design.max_rotation_error:
            return (f"first-motion check refused: the profiler {kind} {np.degrees(angle):.1f} deg away from the "
                    f"probes' directions (bound {np.degrees(design.max_rotation_error):.1f} deg): gauge_in_base "
                    "is off by that much; calibrate (profile_pose_calibrate); the loop stays open")
    lever = float(np.linalg.norm(response[:3, 3:], axis=0).max())
    if lever > design.max_lever_error:
        return (f"first-motion check refused: a turn moved the profiler's origin by {lever * 1e3:.1f} mm per rad "
                f"(bound {design.max_lever_error * 1e3:g} mm): profiler_in_tool is off by about that much; "
                "the loop stays open")
    return ""
