"""Cramér-Rao bounds: the depth derivatives against their closed form, the dense model never worse than
the corner model, and the refined estimator close to the corner-model bound (it is ML for that model)."""
import numpy as np

from profile_pose_ros.core import estimate_pose, render_profile, sample_pose
from profile_pose_ros.core.design.crlb import (corner_crlb, dense_crlb, dense_crlb_of_points, depth_jacobian,
                                              position_rotation_rms)
from profile_pose_ros.core.model.poses import LOOKING_DOWN
from profile_pose_ros.core.model.render import DEFAULT_PROFILER, true_corners
from profile_pose_ros.core.model.rotation import so3_log


def test_depth_derivatives_match_the_plane_equation(gauge):
    # Straight down, F's z = -G's z: z = (d - n.(t + x r1)) / (n.r3) so dz/dt = n / n_z on each face.
    t = np.array([0.0, 0.003, 0.45])
    jac, lit = depth_jacobian(gauge, LOOKING_DOWN, t)
    px = DEFAULT_PROFILER.x[lit]
    faces = gauge.face_index(px, np.full(len(px), 0.003))
    normals = gauge.normals[faces]
    assert np.allclose(jac[:, 5], 1.0, atol=1e-6)  # raising the profiler deepens every point equally
    assert np.allclose(jac[:, 3], normals[:, 0] / normals[:, 2], atol=1e-6)
    assert np.allclose(jac[:, 4], normals[:, 1] / normals[:, 2], atol=1e-6)
    assert len(px) > 1500  # the whole top surface is lit and differentiable except at its ridges


def test_dense_bound_is_never_weaker_than_the_corner_bound(gauge, rng):
    for _ in range(5):
        rotation, t = sample_pose(gauge, rng)
        difference = corner_crlb(gauge, rotation, t, 5e-6) - dense_crlb(gauge, rotation, t, 5e-6)
        assert np.min(np.linalg.eigvalsh(0.5 * (difference + difference.T))) > -1e-18


def test_refined_estimate_reaches_the_corner_bound(gauge):
    rng = np.random.default_rng(11)
    rotation, t = sample_pose(gauge, rng)
    bound_position, bound_rotation = position_rotation_rms(corner_crlb(gauge, rotation, t, 5e-6))
    errors = []
    for _ in range(200):
        estimate = estimate_pose(render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng), gauge)
        errors.append(np.concatenate([t - estimate.t, so3_log(rotation @ estimate.R.T)]))
    errors = np.array(errors)
    rms_position = np.sqrt(np.mean(np.sum(errors[:, :3] ** 2, axis=1)))
    rms_rotation = np.sqrt(np.mean(np.sum(errors[:, 3:] ** 2, axis=1)))
    assert 0.85 < rms_position / bound_position < 1.15
    assert 0.85 < rms_rotation / bound_rotation < 1.15


def test_analytic_dense_bound_matches_finite_differences(gauge):
    """Straight down nothing but top faces is lit, so both ways of building the bound must agree."""
    t = np.array([0.002, -0.004, 0.45])
    numeric, _ = depth_jacobian(gauge, LOOKING_DOWN, t)
    from profile_pose_ros.core.estimation.result import ros_covariance

    by_differences = ros_covariance(LOOKING_DOWN, (5e-6) ** 2 * np.linalg.inv(numeric.T @ numeric))
    analytic = dense_crlb(gauge, LOOKING_DOWN, t, 5e-6)
    assert np.allclose(np.sqrt(np.diag(analytic)), np.sqrt(np.diag(by_differences)), rtol=0.02)


def test_the_bound_of_a_profile_with_a_gap_is_that_of_the_points_left(gauge, rng):
    """dense_crlb_of_points: every point, the full view's bound; a gap over a corner, a weaker one (the bound
    `profile_pose robustness --bound` holds a refusal against)."""
    rotation, t = sample_pose(gauge, rng)
    points = render_profile(gauge, rotation, t)
    full = dense_crlb_of_points(gauge, points, rotation, t, 5e-6)
    np.testing.assert_allclose(full, dense_crlb(gauge, rotation, t, 5e-6), rtol=1e-9, atol=1e-24)
    corner = true_corners(gauge, rotation, t)[2, 0]
    gapped = points.copy()
    gapped[np.abs(points[:, 0] - corner) < 6e-3, 1] = np.nan
    weaker = dense_crlb_of_points(gauge, gapped, rotation, t, 5e-6)
    difference = weaker - full
    assert np.min(np.linalg.eigvalsh(0.5 * (difference + difference.T))) > -1e-18
    assert np.trace(weaker[:3, :3]) > 1.05 * np.trace(full[:3, :3])
