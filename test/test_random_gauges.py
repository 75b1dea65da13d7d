"""The random-gauge generator (paper III-B): seedable, and every gauge it returns keeps every rule."""
import numpy as np
import pytest

from profile_pose_ros.core import estimate_pose, render_profile, sample_pose
from profile_pose_ros.core.design.gauge_design import RandomGaugeRules, distinct_directions, face_widths, random_gauge

RULES = RandomGaugeRules()


@pytest.mark.parametrize("n", [4, 5, 7, 10])
def test_generated_gauges_keep_every_rule(n):
    rng = np.random.default_rng(n)
    for _ in range(8):
        gauge = random_gauge(n, rng, RULES)
        assert gauge.n_ridges == n
        assert np.min(face_widths(gauge)) >= RULES.min_face_width - 1e-12
        assert np.max(gauge.face_slope_deg()) <= RULES.max_face_angle_deg + 1e-9
        assert np.max(np.abs(np.degrees(np.arctan(gauge.u)))) <= RULES.max_ridge_angle_deg + 1e-9
        assert np.ptp(gauge.corner_heights()) <= RULES.max_relief + 1e-12
        assert distinct_directions(np.arctan(gauge.u), RULES.min_ridge_separation_deg) >= 4
        assert (gauge.width, gauge.length) == (RULES.width, RULES.length)
        sample_pose(gauge, rng)  # every corner visible at a pose of the range (raises otherwise)


def test_generator_is_seedable():
    a = random_gauge(5, np.random.default_rng(42))
    b = random_gauge(5, np.random.default_rng(42))
    assert np.array_equal(a.normals, b.normals) and np.array_equal(a.offsets, b.offsets)
    c = random_gauge(5, np.random.default_rng(43))
    assert not np.array_equal(a.normals, c.normals)


def test_generated_gauges_estimate_for_n_at_least_5():
    rng = np.random.default_rng(3)
    for n in (5, 7, 10):
        gauge = random_gauge(n, rng)
        rotation, t = sample_pose(gauge, rng)
        estimate = estimate_pose(render_profile(gauge, rotation, t), gauge)
        assert estimate.ok, estimate.reason
        assert np.linalg.norm(estimate.t - t) < 1e-9


def test_impossible_rules_say_so():
    with pytest.raises(ValueError, match="do not fit"):
        random_gauge(30, np.random.default_rng(0), RandomGaugeRules(min_face_width=0.005))


def test_distinct_directions_counts_pairwise_separated_ridges():
    degrees = np.radians([-10.0, -9.0, 0.0, 1.5, 2.9, 12.0])
    assert distinct_directions(degrees, 3.0) == 3  # -10 | 0 (1.5 too close, 2.9 too close to 0) | 12
    assert distinct_directions(degrees, 0.5) == 6
    assert distinct_directions(np.radians([5.0, 5.5, 6.0, 20.0]), 3.0) == 2
