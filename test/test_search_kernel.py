"""The compiled basin search's pieces against numpy: the cubic's real roots, the four-ridge starts."""
import numpy as np
from hypothesis import given, settings, strategies as st

from profile_pose_ros.core import render_profile, sample_pose, true_corners
from profile_pose_ros.core.compiled.search_kernel import _cubic_real_roots, four_ridge_starts
from profile_pose_ros.core.design.gauge_design import random_gauge
from profile_pose_ros.core.model.rotation import rotation_angle

coefficient = st.floats(-1e3, 1e3, allow_nan=False).filter(lambda c: c == 0 or abs(c) > 1e-6)


@settings(max_examples=300, deadline=None)
@given(st.lists(coefficient, min_size=4, max_size=4))
def test_cubic_real_roots_are_numpys(c):
    """Every root returned is one, and every simple real root numpy finds is returned. (Near-double roots
    are a matter of rounding either way: whether a pair counts as real there is not compared.)"""
    if not any(c[:3]):
        return
    roots = np.empty(3)
    count = _cubic_real_roots(*c, roots)
    got = roots[:count]
    for x in got:
        size = sum(abs(ci) * abs(x) ** (3 - i) for i, ci in enumerate(c))
        assert abs(np.polyval(c, x)) <= 1e-8 * size, (c, got)
    expected = np.roots(np.trim_zeros(np.array(c), "f"))
    for k, root in enumerate(expected):
        others = np.delete(expected, k)
        separated = np.all(np.abs(others - root) > 1e-3 * (1 + abs(root)))
        if root.imag == 0 and separated:
            assert np.min(np.abs(got - root.real), initial=np.inf) <= 1e-7 * (1 + abs(root.real)), (c, got, expected)


def test_four_ridge_starts_hold_the_true_pose(rng):
    """Noise-free corners of a four-ridge gauge: one of the starts is the pose itself."""
    for _ in range(20):
        gauge = random_gauge(4, rng)
        rotation, translation = sample_pose(gauge, rng)
        render_profile(gauge, rotation, translation)  # the pose lights the gauge
        corners = true_corners(gauge, rotation, translation)
        rotations, translations = np.empty((3, 3, 3)), np.empty((3, 3))
        count = four_ridge_starts(gauge.q, gauge.u, gauge.w, np.ascontiguousarray(corners), rotations, translations)
        assert 1 <= count <= 3
        best = np.argmin(np.linalg.norm(translations[:count] - translation, axis=1))
        assert np.linalg.norm(translations[best] - translation) < 1e-9
        assert rotation_angle(rotations[best], rotation) < 1e-9
