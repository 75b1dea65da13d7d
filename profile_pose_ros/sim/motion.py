"""Where the profiler is at time t: a nominal pose plus scripted steps and sines (the robot model of the
robot-side issue is another source with the same `pose_at`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..core.model.rotation import so3_exp

AXES = ("x", "y", "z", "rx", "ry", "rz")


class MotionSource(Protocol):
    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of the profiler frame F in the gauge frame G at time t (s since the cell started)."""


def pose_from_vector(vector: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[x, y, z, rx, ry, rz] (m, rotation vector in rad) -> (R, t)."""
    vector = np.asarray(vector, dtype=float)
    return so3_exp(vector[3:]), vector[:3].copy()


@dataclass(frozen=True)
class Step:
    time: float  # s
    axis: int  # index into AXES
    size: float  # m or rad


@dataclass
class ScriptedMotion:
    """Nominal pose, plus steps (held after they happen) and sines per axis, offsets in the gauge frame.

    Rotation offsets turn F about its own origin (the profiler's optical centre), about gauge-frame axes.
    """

    rotation: np.ndarray
    translation: np.ndarray
    steps: list[Step] = field(default_factory=list)
    sine_amplitude: np.ndarray = field(default_factory=lambda: np.zeros(6))
    sine_frequency: np.ndarray = field(default_factory=lambda: np.zeros(6))

    def offset_at(self, t: float) -> np.ndarray:
        offset = np.asarray(self.sine_amplitude, float) * np.sin(2 * np.pi * np.asarray(self.sine_frequency) * t)
        for step in self.steps:
            if t >= step.time:
                offset[step.axis] += step.size
        return offset

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        offset = self.offset_at(t)
        return so3_exp(offset[3:]) @ self.rotation, self.translation + offset[:3]


def steps_from_lists(times: list[float], axes: list[str], sizes: list[float]) -> list[Step]:
    """Three parallel parameter lists -> steps; raises ValueError naming the bad entry."""
    if not (len(times) == len(axes) == len(sizes)):
        raise ValueError(f"step_times, step_axes and step_sizes differ in length "
                         f"({len(times)}, {len(axes)}, {len(sizes)})")
    steps = []
    for t, axis, size in zip(times, axes, sizes):
        if axis not in AXES:
            raise ValueError(f"step axis '{axis}' is not one of {', '.join(AXES)}")
        steps.append(Step(float(t), AXES.index(axis), float(size)))
    return steps


class ArmMotion:
    """The profiler carried by the simulated arm: the nominal pose moved by the arm's offsets, which are
    in the robot base frame (gauge_in_base gives the base's axes in G) and act at the profiler origin."""

    def __init__(self, rotation: np.ndarray, translation: np.ndarray, arm, gauge_in_base: np.ndarray) -> None:
        self.rotation, self.translation, self.arm = rotation, translation, arm
        self.r_gb = so3_exp(np.asarray(gauge_in_base[3:], dtype=float)).T

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        offset = self.arm.position
        turn = self.r_gb @ so3_exp(offset[3:]) @ self.r_gb.T
        return turn @ self.rotation, self.translation + self.r_gb @ offset[:3]
