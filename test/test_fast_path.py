"""The compiled runtime path (core/compiled/estimate_kernel.py) against the readable numpy reference: same decisions, same
reasons, and the same numbers within 1e-12 m (the refined pose is a Gauss-Newton fixed point, so both
land on it to rounding)."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from profile_pose_ros.core import estimate_pose, render_profile, sample_pose, true_corners
from profile_pose_ros.core.design.gauge_design import heightfield_gauge


def both(points, gauge, **options):
    return (estimate_pose(points, gauge, backend="fast", **options),
            estimate_pose(points, gauge, backend="numpy", **options))


def assert_same(fast, plain):
    assert fast.ok == plain.ok and fast.reason == plain.reason
    if not plain.ok:
        return
    assert np.max(np.abs(fast.t - plain.t)) < 1e-12
    assert np.max(np.abs(fast.R - plain.R)) < 1e-12
    assert np.max(np.abs(fast.corners - plain.corners)) < 1e-12
    assert np.max(np.abs(fast.closed_form.translation - plain.closed_form.translation)) < 1e-12
    assert np.max(np.abs(fast.closed_form.rotation - plain.closed_form.rotation)) < 1e-12
    assert fast.reprojection_error == pytest.approx(plain.reprojection_error, rel=1e-6, abs=1e-15)
    assert np.allclose(fast.covariance, plain.covariance, rtol=1e-6, atol=1e-24)


@pytest.mark.parametrize("noise,spikes", [(0.0, 0.0), (5e-6, 0.0), (20e-6, 0.0), (5e-6, 0.01)])
def test_fast_equals_plain_on_random_poses(gauge, rng, noise, spikes):
    for _ in range(40):
        rotation, t = sample_pose(gauge, rng)
        points = render_profile(gauge, rotation, t, noise_std=noise, spike_fraction=spikes, rng=rng)
        assert_same(*both(points, gauge))


@pytest.mark.parametrize("options", [dict(refine=False, max_reprojection_error=2e-3), dict(weighting="uniform"),
                                     dict(noise_std=5e-6), dict(robust=False), dict(trim_fraction=0.0)])
def test_fast_equals_plain_for_each_option(gauge, rng, options):
    for _ in range(10):
        rotation, t = sample_pose(gauge, rng)
        assert_same(*both(render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng), gauge, **options))


def test_fast_and_plain_fail_with_the_same_reason(gauge, rng):
    rotation, t = sample_pose(gauge, rng)
    clean = render_profile(gauge, rotation, t)
    cut = clean.copy()
    cut[cut[:, 0] > true_corners(gauge, rotation, t)[3, 0] + 1e-3, 1] = np.nan
    x = np.linspace(-0.12, 0.12, 3200)
    other = heightfield_gauge("other", 0.12, 0.10, [-0.045, -0.02, 0.003, 0.025, 0.046],
                              np.radians([-8.0, 6.0, 12.0, -4.0, -9.0]), [-0.7, 0.75, -0.7, 0.8, -0.75, 0.7])
    cases = [
        (np.full((3200, 2), np.nan), gauge),
        (cut, gauge),
        (np.column_stack([x, 0.4 + rng.uniform(-0.02, 0.02, len(x))]), gauge),
        (np.column_stack([x, 0.4 + 0.1 * x]), gauge),
        (clean[::-1], gauge),
        (render_profile(other, *sample_pose(other, rng)), gauge),
    ]
    reasons = set()
    for points, g in cases:
        fast, plain = both(points, g)
        assert not plain.ok
        assert_same(fast, plain)
        reasons.add(plain.reason.split(":")[0] if plain.reason.startswith("corner") else plain.reason)
    assert {"corner detection"} <= reasons and any("reprojection" in r for r in reasons)
    bad_shape = estimate_pose(np.zeros((10, 3)), gauge)
    assert not bad_shape.ok and "(N, 2)" in bad_shape.reason


@pytest.mark.parametrize("n", [4, 5, 7])
def test_compiled_refine_equals_solver_refine_from_far_starts(rng, n):
    """The basin search's hops and the four-ridge starts (refine_compiled) on random gauges: the same minimum,
    the same covariance, with and without the polish and the weights."""
    from profile_pose_ros.core.estimation.corners import detect_corners
    from profile_pose_ros.core.estimation.compiled_path import refine_compiled
    from profile_pose_ros.core.design.gauge_design import random_gauge
    from profile_pose_ros.core.model.rotation import so3_exp
    from profile_pose_ros.core.estimation.solver import PoseSolution, corner_residuals, refine

    compared = 0
    while compared < 12:
        gauge = random_gauge(n, rng)
        rotation, t = sample_pose(gauge, rng)
        found = detect_corners(render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng), n)
        if not found.ok:
            continue
        cov = found.covariance(None)
        start_rotation = rotation @ so3_exp(rng.normal(0.0, 0.02, 3))
        start_t = t + rng.normal(0.0, 2e-3, 3)
        start = PoseSolution(start_rotation, start_t, corner_residuals(gauge, found.corners, start_rotation, start_t))
        for weighted, iterations, polish in [(True, 30, True), (False, 30, True), (True, 4, False)]:
            plain = refine(gauge, found.corners, start, cov, weighted, iterations, polish)
            compiled = refine_compiled(gauge, found.corners, start, cov, weighted, iterations, polish)
            # a converged refinement is a fixed point both land on to rounding; the triage's four steps are
            # not, and a Cholesky and an LU solve round differently along the way
            tolerance = 1e-12 if polish else 1e-8
            assert compiled.iterations == plain.iterations
            assert np.max(np.abs(compiled.solution.translation - plain.solution.translation)) < tolerance
            assert np.max(np.abs(compiled.solution.rotation - plain.solution.rotation)) < tolerance
            assert np.max(np.abs(compiled.solution.residuals - plain.solution.residuals)) < tolerance
            assert np.allclose(compiled.covariance, plain.covariance, rtol=1e-6 if polish else 1e-4, atol=1e-24)
        compared += 1


def test_fast_equals_plain_on_four_ridge_and_searched_poses(rng):
    """The compiled path's fallbacks (n = 4 starts, the basin search) now refine with the compiled kernel."""
    from profile_pose_ros.core.design.gauge_design import random_gauge

    searched = 0
    for n in (4, 5, 7):
        for _ in range(6):
            gauge = random_gauge(n, rng)
            for _ in range(5):
                rotation, t = sample_pose(gauge, rng)
                points = render_profile(gauge, rotation, t, noise_std=5e-6, rng=rng)
                fast, plain = both(points, gauge)
                # random gauges are often poorly conditioned (sigma ~100 um): rounding shows at 1e-12
                assert fast.ok == plain.ok and fast.reason == plain.reason
                assert fast.search_starts == plain.search_starts
                if plain.ok:
                    assert np.max(np.abs(fast.t - plain.t)) < 1e-10
                    assert np.max(np.abs(fast.R - plain.R)) < 1e-10
                    assert np.allclose(fast.covariance, plain.covariance, rtol=1e-5, atol=1e-24)
                searched += plain.search_starts > 0
    assert searched > 0


def test_compiled_detection_equals_detect_corners(rng):
    """The numpy stages' compiled corner detection: same corners, face fits, covariance and failure reasons."""
    from profile_pose_ros.core.estimation.corners import CornerOptions, detect_corners
    from profile_pose_ros.core.estimation.compiled_path import detect_corners_compiled
    from profile_pose_ros.core.design.gauge_design import random_gauge

    for n in (4, 5, 7, 10):
        gauge = random_gauge(n, rng)
        for options in (CornerOptions(), CornerOptions(robust=False)):
            for noise, spikes in [(5e-6, 0.0), (5e-6, 0.01), (50e-6, 0.0)]:
                rotation, t = sample_pose(gauge, rng)
                points = render_profile(gauge, rotation, t, noise_std=noise, spike_fraction=spikes, rng=rng)
                for count in (n, n + 1):  # a wrong count fails: the reasons must match too
                    plain, compiled = detect_corners(points, count, options), detect_corners_compiled(points, count,
                                                                                                      options)
                    assert (compiled.ok, compiled.reason) == (plain.ok, plain.reason)
                    if plain.ok:
                        assert np.max(np.abs(compiled.corners - plain.corners)) < 1e-12
                        assert compiled.fit_rms == pytest.approx(plain.fit_rms, rel=1e-9)
                        for noise_std in (None, 5e-6):
                            assert np.allclose(compiled.covariance(noise_std), plain.covariance(noise_std),
                                               rtol=1e-9, atol=1e-30)
    empty = np.full((50, 2), np.nan)
    assert detect_corners_compiled(empty, 5).reason == detect_corners(empty, 5).reason


@given(st.integers(0, 2**32 - 1), st.floats(1e-9, 0.3), st.floats(0.2, 5.0))
@settings(max_examples=200, deadline=None)
def test_polar_rotation_is_the_svd_s_nearest_rotation(seed, noise, scale):
    """The closed form's projection onto SO(3) without LAPACK: U V^T of the SVD to rounding, or it declines."""
    from scipy.spatial.transform import Rotation

    from profile_pose_ros.core.compiled import estimate_kernel

    rng = np.random.default_rng(seed)
    m = scale * (Rotation.random(random_state=seed).as_matrix() + rng.normal(0.0, noise, (3, 3)))
    out = np.full((3, 3), np.nan)
    u, _, vt = np.linalg.svd(m)
    if estimate_kernel._polar_rotation(m, out):
        assert np.max(np.abs(out - u @ vt)) < 1e-13
        assert np.linalg.det(m) > 0
    else:  # only for a reflection, which the SVD path then handles
        assert np.linalg.det(m) <= 0
    assert not estimate_kernel._polar_rotation(-m, out) or np.linalg.det(-m) > 0


@given(st.integers(0, 2**32 - 1), st.integers(3, 400), st.sampled_from([0.0, 1e-6, 5e-5]),
       st.sampled_from([1e-5, 3e-4, 2e-3]))
@settings(max_examples=300, deadline=None)
def test_compiled_rdp_keeps_the_reference_s_vertices(seed, n, noise, epsilon):
    """estimate_kernel._rdp (vectorised passes, argmax by bit pattern) against rdp.rdp_vertices, ties included: a
    noiseless polyline has many equal distances, and both must split at the first."""
    from profile_pose_ros.core.compiled import estimate_kernel
    from profile_pose_ros.core.estimation.rdp import rdp_vertices

    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(-0.05, 0.05, n)) + np.arange(n) * 1e-9  # strictly increasing, as detection needs
    knots = np.sort(rng.uniform(-0.05, 0.05, 4))
    z = np.interp(x, knots, rng.uniform(0.0, 0.02, 4)) + rng.normal(0.0, noise, n)
    if rng.random() < 0.3:
        z = np.round(z, 4)  # plateaus: equal distances
    keep, stack, scratch = np.empty(n, dtype=np.bool_), np.empty(2 * n + 4, dtype=np.int64), np.empty(n)
    estimate_kernel._rdp(x, z, epsilon, keep, stack, scratch)
    assert np.array_equal(np.nonzero(keep)[0], rdp_vertices(np.column_stack([x, z]), epsilon))
