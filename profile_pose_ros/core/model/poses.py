"""Random profiler poses over a gauge, for tests, studies and the demo."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gauge import Gauge
from .render import DEFAULT_PROFILER, ProfilerModel, render_profile, true_corners
from .rotation import so3_exp

LOOKING_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # F x = G x, F z = -G z


@dataclass(frozen=True)
class PoseRange:
    """The acceptance-test pose range of the core issue."""

    standoff: tuple[float, float] = (0.35, 0.55)  # m, along the laser ray, to the gauge's mid-height
    max_tilt: float = np.radians(10.0)  # rad, of F's z axis from straight down
    max_yaw: float = np.radians(10.0)  # rad, of the laser line about the vertical
    max_offset: float = 0.010  # m, of the line's crossing from the gauge centre (x and y)


def corners_visible(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray,
                    profiler: ProfilerModel = DEFAULT_PROFILER, clearance: float = 1e-3, trace=None) -> bool:
    """All n corners inside the measurement range and lit, with `clearance` of lit profile around each."""
    corners = true_corners(gauge, rotation, translation)
    if not np.all(profiler.in_range(corners[:, 0], corners[:, 1])):
        return False
    profile = render_profile(gauge, rotation, translation, profiler=profiler, trace=trace)
    for x, z in corners:
        near = np.abs(profile[:, 0] - x) <= clearance
        if not near.any() or not np.all(np.abs(profile[near, 1] - z) < 5 * clearance):
            return False
    return True


def mid_height(gauge: Gauge) -> float:
    """Halfway between the base and the highest top point: where standoffs are measured to."""
    return 0.5 * (gauge.base_z + float(np.max(gauge.corner_heights())))


def sample_pose(gauge: Gauge, rng: np.random.Generator, pose_range: PoseRange = PoseRange(),
                profiler: ProfilerModel = DEFAULT_PROFILER, max_tries: int = 1000,
                trace=None) -> tuple[np.ndarray, np.ndarray]:
    """A random (R, t) in the range with every corner visible (rejection sampling); `trace` as in
    render_profile."""
    middle = mid_height(gauge)
    for _ in range(max_tries):
        tilt = pose_range.max_tilt * np.sqrt(rng.uniform())  # uniform over the cone's cap
        azimuth = rng.uniform(0, 2 * np.pi)
        tilt_axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        yaw = rng.uniform(-pose_range.max_yaw, pose_range.max_yaw)
        rotation = so3_exp(tilt * tilt_axis) @ so3_exp(np.array([0.0, 0.0, yaw])) @ LOOKING_DOWN
        aim = np.array([rng.uniform(-1, 1) * pose_range.max_offset, rng.uniform(-1, 1) * pose_range.max_offset,
                        middle])
        translation = aim - rng.uniform(*pose_range.standoff) * rotation[:, 2]
        if corners_visible(gauge, rotation, translation, profiler, trace=trace):
            return rotation, translation
    raise RuntimeError(f"no pose with all corners visible after {max_tries} tries")
