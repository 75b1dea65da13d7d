"""Where the profiler is at time t: a nominal pose plus scripted steps and sines (the robot model of the
robot-side issue is another source with the same `pose_at`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..core.model.rotation import so3_exp
from ..core.model.transform import Transform, controller_angles

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
    """The profiler carried by the simulated arm, in a cell whose geometry the loop's nodes do not know.

    The truth: the gauge's place in the robot base frame and the profiler's mount on the flange. The
    controller knows only the tool it was told (tool_in_flange, the nominal one) and moves that: the arm's
    offsets are translations of the tool origin in base axes and turns about it. The robot program's start
    pose puts the profiler at the nominal viewing pose (rotation, translation: F in G), as a commissioning
    engineer jogs the arm until the gauge is in view.
    """

    def __init__(self, rotation: np.ndarray, translation: np.ndarray, arm, gauge_in_base,
                 profiler_in_flange=(0.0,) * 6, tool_in_flange=(0.0,) * 6) -> None:
        self.arm = arm
        base_gauge = Transform.from_vector(gauge_in_base)
        flange_profiler, flange_tool = Transform.from_vector(profiler_in_flange), Transform.from_vector(tool_in_flange)
        self.gauge_base = base_gauge.inverse()
        self.tool_profiler = flange_tool.inverse() @ flange_profiler
        self.tool_start = base_gauge @ Transform(rotation, translation) @ self.tool_profiler.inverse()

    def tool_pose(self, offset: np.ndarray) -> Transform:
        """The tool in the base frame with the arm at `offset` from the start pose."""
        return Transform(so3_exp(offset[3:]) @ self.tool_start.rotation, self.tool_start.translation + offset[:3])

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        profiler = self.gauge_base @ self.tool_pose(self.arm.position) @ self.tool_profiler
        return profiler.rotation, profiler.translation

    def controller_pose(self, offset: np.ndarray) -> np.ndarray:
        """What the controller reports (mpGetCartPos): the tool's pose in the base frame, x y z (m) and its
        Rx Ry Rz angles (rad)."""
        tool = self.tool_pose(offset)
        return np.concatenate([tool.translation, controller_angles(tool.rotation)])
