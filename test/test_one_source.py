"""One estimator source: the kernels in core/compiled/ run compiled at run time and uncompiled
(PROFILE_POSE_KERNEL=python) for debugging, with the same decisions, reasons and numbers; its pieces hold
to the numpy baseline of the benchmark where that is the same algorithm."""
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from profile_pose_ros.core import estimate_pose, render_profile, sample_pose, true_corners
from profile_pose_ros.core.design.gauge_design import heightfield_gauge, random_gauge

UNCOMPILED = """
import pickle, sys
from profile_pose_ros.core import estimate_pose
from profile_pose_ros.core.compiled import loader
cases = pickle.load(sys.stdin.buffer)
results = [estimate_pose(points, gauge, **options) for points, gauge, options in cases]
pickle.dump((loader.kernel_name(), results), sys.stdout.buffer)
"""


def summary(estimate) -> tuple:
    return (estimate.ok, estimate.reason, estimate.R, estimate.t, estimate.covariance, estimate.corners,
            estimate.search_starts)


def failure_cases(gauge, rng) -> list:
    rotation, t = sample_pose(gauge, rng)
    clean = render_profile(gauge, rotation, t)
    cut = clean.copy()
    cut[cut[:, 0] > true_corners(gauge, rotation, t)[3, 0] + 1e-3, 1] = np.nan
    x = np.linspace(-0.12, 0.12, 3200)
    other = heightfield_gauge("other", 0.12, 0.10, [-0.045, -0.02, 0.003, 0.025, 0.046],
                              np.radians([-8.0, 6.0, 12.0, -4.0, -9.0]), [-0.7, 0.75, -0.7, 0.8, -0.75, 0.7])
    return [np.full((3200, 2), np.nan), cut, np.column_stack([x, 0.4 + rng.uniform(-0.02, 0.02, len(x))]),
            np.column_stack([x, 0.4 + 0.1 * x]), np.roll(clean, len(clean) // 2, axis=0),  # x neither increasing nor
            render_profile(other, *sample_pose(other, rng))]  # decreasing: a scrambled message


def test_compiled_and_uncompiled_runs_of_the_one_source_agree(gauge, rng):
    """Every path of estimate_pose (one call, n = 4 starts, the basin search, dense, each failure) run
    compiled here and uncompiled in a fresh process: same decisions and reasons, numbers to rounding."""
    cases = [(render_profile(gauge, *sample_pose(gauge, rng), noise_std=noise, spike_fraction=spikes, rng=rng),
              gauge, options)
             for noise, spikes in [(5e-6, 0.0), (20e-6, 0.0), (5e-6, 0.01)]
             for options in [{}, dict(refine_model="dense"), dict(refine_weighting="uniform"),
                             dict(refine=False, max_reprojection_error=2e-3)]]
    cases += [(points, gauge, {}) for points in failure_cases(gauge, rng)]
    for n in (4, 7):
        other = random_gauge(n, rng)
        cases += [(render_profile(other, *sample_pose(other, rng), noise_std=5e-6, rng=rng), other, {})
                  for _ in range(4)]
    run = subprocess.run([sys.executable, "-c", UNCOMPILED], input=pickle.dumps(cases), capture_output=True,
                         timeout=600, env={**os.environ, "PROFILE_POSE_KERNEL": "python"})
    assert run.returncode == 0, run.stderr.decode()
    kernel, uncompiled = pickle.loads(run.stdout)
    assert kernel == "uncompiled (python)"
    accepted = 0
    for (points, g, options), estimate in zip(cases, uncompiled):
        ours, theirs = summary(estimate_pose(points, g, **options)), summary(estimate)
        assert ours[:2] == theirs[:2] and ours[6] == theirs[6], (ours[:2], theirs[:2])
        if ours[0]:
            accepted += 1
            for a, b in zip(ours[2:6], theirs[2:6]):
                assert np.allclose(a, b, rtol=1e-9, atol=1e-13 * max(1.0, float(np.max(np.abs(a))))), (a, b)
    assert accepted >= len(cases) // 2


def test_refusals_say_why(gauge, rng):
    reasons = set()
    for points in failure_cases(gauge, rng):
        estimate = estimate_pose(points, gauge)
        assert not estimate.ok and not np.any(np.isfinite(estimate.t))
        reasons.add(estimate.reason.split(":")[0] if estimate.reason.startswith("corner") else estimate.reason)
    assert {"corner detection"} <= reasons and any("reprojection" in r or "noise explains" in r for r in reasons)
    bad_shape = estimate_pose(np.zeros((10, 3)), gauge)
    assert not bad_shape.ok and "(N, 2)" in bad_shape.reason


def test_the_core_runs_with_numpy_alone(gauge) -> None:
    """DESIGN.md: the core needs no more than numpy. Without numba the same source runs uncompiled."""
    code = ("import sys; sys.modules['numba'] = None\n"  # an import of numba now fails, as when not installed
            "import numpy as np\n"
            "from profile_pose_ros.core import Gauge, estimate_pose, render_profile, sample_pose\n"
            "from profile_pose_ros.core.compiled import loader\n"
            f"gauge = Gauge.from_yaml({str(gauge.source)!r})\n"
            "rotation, t = sample_pose(gauge, np.random.default_rng(1))\n"
            "e = estimate_pose(render_profile(gauge, rotation, t), gauge)\n"
            "print(loader.kernel_name(), '|', e.ok, float(np.max(np.abs(e.t - t))))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={k: v for k, v in os.environ.items() if k != "PROFILE_POSE_KERNEL"})
    assert run.returncode == 0, run.stderr
    name, verdict = run.stdout.strip().rsplit("|", 1)
    ok, error = verdict.split()
    assert name.strip() == "uncompiled (python)" and ok == "True" and float(error) < 1e-9


def test_an_unknown_kernel_choice_is_refused() -> None:
    run = subprocess.run([sys.executable, "-c", "from profile_pose_ros.core.compiled import loader; loader.kernels()"],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PROFILE_POSE_KERNEL": "fortran"})
    assert run.returncode != 0 and "PROFILE_POSE_KERNEL='fortran'" in run.stderr


def test_compiled_detection_equals_the_numpy_baseline_s(rng):
    """The compiled corner detection against the baseline's numpy one, the same algorithm written the plain
    way: same corners, face fits, covariance and failure reasons."""
    from profile_pose_ros.core.design.gauge_design import random_gauge
    from profile_pose_ros.core.estimation.corners import CornerOptions
    from profile_pose_ros.core.estimation.stages import detect_corners as detect_corners_compiled
    from profile_pose_ros.tools.numpy_baseline import detect_corners

    for n in (4, 5, 7, 10):
        gauge = random_gauge(n, rng)
        for options in (CornerOptions(), CornerOptions(robust_line_fit=False)):
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
    """estimate_kernel._rdp (vectorised passes, argmax by bit pattern) against the numpy baseline's
    rdp_vertices, ties included: a noiseless polyline has many equal distances, and both must split at
    the first."""
    from profile_pose_ros.core.compiled import estimate_kernel
    from profile_pose_ros.tools.numpy_baseline import rdp_vertices

    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(-0.05, 0.05, n)) + np.arange(n) * 1e-9  # strictly increasing, as detection needs
    knots = np.sort(rng.uniform(-0.05, 0.05, 4))
    z = np.interp(x, knots, rng.uniform(0.0, 0.02, 4)) + rng.normal(0.0, noise, n)
    if rng.random() < 0.3:
        z = np.round(z, 4)  # plateaus: equal distances
    keep, stack, scratch = np.empty(n, dtype=np.bool_), np.empty(2 * n + 4, dtype=np.int64), np.empty(n)
    estimate_kernel._rdp(x, z, epsilon, keep, stack, scratch)
    assert np.array_equal(np.nonzero(keep)[0], rdp_vertices(np.column_stack([x, z]), epsilon))
