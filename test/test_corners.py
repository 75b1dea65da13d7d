"""Corner detection (paper II-D): exact on clean profiles, robust to gaps and spikes, and honest failure."""
import numpy as np
import pytest

from profile_pose_ros.core import detect_corners, render_profile, sample_pose, true_corners
from profile_pose_ros.core.model.poses import LOOKING_DOWN


@pytest.fixture
def pose(gauge, rng):
    return sample_pose(gauge, rng)


def test_noise_free_corners_are_exact(gauge, rng):
    for _ in range(20):
        rotation, t = sample_pose(gauge, rng)
        found = detect_corners(render_profile(gauge, rotation, t), gauge.n_ridges)
        assert found.ok, found.reason
        assert np.max(np.abs(found.corners - true_corners(gauge, rotation, t))) < 1e-10


def test_nan_gap_inside_a_face_is_harmless(gauge, pose):
    profile = render_profile(gauge, *pose)
    corners = true_corners(gauge, *pose)
    middle = 0.5 * (corners[1, 0] + corners[2, 0])
    profile[np.abs(profile[:, 0] - middle) < 2e-3, 1] = np.nan  # a 4 mm dropout in face 2
    found = detect_corners(profile, gauge.n_ridges)
    assert found.ok, found.reason
    assert np.max(np.abs(found.corners - corners)) < 1e-10


def test_spikes_do_not_become_corners(gauge, pose, rng):
    clean = detect_corners(render_profile(gauge, *pose, noise_std=5e-6, rng=np.random.default_rng(3)),
                           gauge.n_ridges)
    spiky = detect_corners(render_profile(gauge, *pose, noise_std=5e-6, spike_fraction=0.01,
                                          rng=np.random.default_rng(3)), gauge.n_ridges)
    assert clean.ok and spiky.ok, spiky.reason
    assert np.max(np.abs(spiky.corners - true_corners(gauge, *pose))) < 20e-6


def test_missing_face_is_reported_not_guessed(gauge, pose):
    profile = render_profile(gauge, *pose)
    corners = true_corners(gauge, *pose)
    profile[profile[:, 0] > 0.5 * (corners[3, 0] + corners[4, 0]), 1] = np.nan  # face 5 and half of face 4 out of range
    found = detect_corners(profile, gauge.n_ridges)
    assert not found.ok
    assert "found 4 corners" in found.reason and "has 5" in found.reason


def test_pure_noise_and_too_few_points_fail(gauge, rng):
    x = np.linspace(-0.12, 0.12, 3200)
    noise = np.column_stack([x, 0.4 + rng.uniform(-0.02, 0.02, len(x))])
    assert not detect_corners(noise, gauge.n_ridges).ok
    sparse = np.column_stack([x[:50], np.full(50, 0.4)])
    result = detect_corners(sparse, gauge.n_ridges)
    assert not result.ok and "valid points" in result.reason
    assert not detect_corners(np.zeros((10, 3)), 5).ok


def test_flat_plane_has_no_corners(gauge):
    x = np.linspace(-0.1, 0.1, 3200)
    found = detect_corners(np.column_stack([x, 0.4 + 0.1 * x]), gauge.n_ridges)
    assert not found.ok and "found 0 corners" in found.reason


def test_corner_covariance_matches_monte_carlo(gauge, rng):
    """NEES of the corners against their covariance averages the dimension (2n = 10)."""
    rotation, t = sample_pose(gauge, rng)
    truth = true_corners(gauge, rotation, t).ravel()
    nees = []
    for _ in range(150):
        found = detect_corners(render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng), gauge.n_ridges)
        d = found.corners.ravel() - truth
        nees.append(d @ np.linalg.solve(found.covariance(), d))
    assert 8.0 < np.mean(nees) < 12.5


def test_side_wall_is_dropped(gauge):
    from profile_pose_ros.core.model.rotation import so3_exp

    rotation = so3_exp(np.array([0.0, np.radians(9.0), 0.0])) @ LOOKING_DOWN
    t = np.array([0.0, 0.0, 0.03]) - 0.4 * rotation[:, 2]
    found = detect_corners(render_profile(gauge, rotation, t), gauge.n_ridges)
    assert found.ok, found.reason
    assert np.max(np.abs(found.corners - true_corners(gauge, rotation, t))) < 1e-10
