"""The poses of a controller period fused into one measurement (core/control/period_fusion.py)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from profile_pose_ros.core.control.period_fusion import PeriodPose, fuse_period


def pose(stamp: float, value, variance) -> PeriodPose:
    return PeriodPose(stamp, int(stamp * 1e9), np.broadcast_to(np.asarray(value, float), (6,)).copy(),
                      np.broadcast_to(np.asarray(variance, float), (6,)).copy())


@settings(max_examples=50, deadline=None)
@given(st.floats(-0.05, 0.05), st.floats(-1e-3, 1e-3), st.integers(1, 6))
def test_poses_of_a_steady_motion_fuse_to_where_the_arm_is_at_the_newest(velocity: float, start: float,
                                                                         count: int) -> None:
    """Noise-free poses along a constant velocity, out of order: the fused pose is the newest one's position,
    stamped with it, whatever the weights."""
    stamps = 0.001 * np.arange(count)[::-1]
    poses = [pose(t, start + velocity * t, 1e-12 * (k + 1)) for k, t in enumerate(stamps)]
    fused = fuse_period(poses, np.full(6, velocity))
    assert fused.stamp == pytest.approx(stamps.max()) and fused.stamp_ns == int(stamps.max() * 1e9)
    np.testing.assert_allclose(fused.value, start + velocity * stamps.max(), atol=1e-15)


def test_fusion_weights_each_pose_by_its_variance_per_axis() -> None:
    good, poor = pose(0.0, 1.0, [1.0, 4.0, 1.0, 1.0, 1.0, 1.0]), pose(0.001, 0.0, [4.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    fused = fuse_period([good, poor], np.zeros(6))
    np.testing.assert_allclose(fused.value[:3], [0.8, 0.2, 0.5])
    np.testing.assert_allclose(fused.variance[:3], [0.8, 0.8, 0.5])  # below either pose's
    assert fuse_period([poor], np.zeros(6)) is poor


def test_four_noisy_poses_a_period_halve_the_noise() -> None:
    rng = np.random.default_rng(0)
    sigma = 5e-6
    fused = [fuse_period([pose(k * 1e-3, rng.normal(0.0, sigma), sigma ** 2) for k in range(4)], np.zeros(6)).value[0]
             for _ in range(4000)]
    assert np.std(fused) == pytest.approx(sigma / 2, rel=0.05)
