"""The renderer is the ground truth for everything else, so it is checked against hand computations."""
import numpy as np
import pytest

from profile_pose_ros.core import DEFAULT_PROFILER, ProfilerModel, render_profile, true_corners
from profile_pose_ros.core.design.gauge_design import heightfield_gauge
from profile_pose_ros.core.model.poses import LOOKING_DOWN
from profile_pose_ros.core.model.render import shadow_mask
from profile_pose_ros.core.model.rotation import so3_exp


def to_gauge(profile, rotation, translation):
    return translation + profile[:, :1] * rotation[:, 0] + profile[:, 1:] * rotation[:, 2]


def test_straight_down_depth_is_standoff_minus_height(gauge):
    t = np.array([0.0, 0.004, 0.45])
    profile = render_profile(gauge, LOOKING_DOWN, t)
    x, z = profile[:, 0], profile[:, 1]
    inside = np.abs(x) <= gauge.width / 2
    assert np.all(np.isfinite(z[inside]))
    assert np.all(np.isnan(z[~inside]))  # nothing outside the footprint
    # F's x is G's x and the laser plane is G y = 0.004: z_F = 0.45 - h(x, 0.004)
    expected = 0.45 - gauge.surface_z(x[inside], np.full(inside.sum(), 0.004))
    assert np.max(np.abs(z[inside] - expected)) < 1e-15
    assert profile.shape == (3200, 2)
    assert x[1] - x[0] == pytest.approx(75e-6)


def test_points_lie_on_the_gauge_surface_or_walls(gauge):
    rotation = so3_exp(np.array([0.0, np.radians(8.0), 0.0])) @ LOOKING_DOWN  # rolled: one side wall shows
    t = np.array([0.0, 0.0, 0.03]) - 0.4 * rotation[:, 2]
    profile = render_profile(gauge, rotation, t)
    valid = np.isfinite(profile[:, 1])
    p = to_gauge(profile[valid], rotation, t)
    on_top = np.abs(p[:, 2] - gauge.surface_z(p[:, 0], p[:, 1])) < 1e-12
    on_wall = np.isclose(np.abs(p[:, 0]), gauge.width / 2, atol=1e-12) & (p[:, 2] >= gauge.base_z)
    assert np.all(on_top | on_wall)
    assert on_wall.sum() > 10  # the tilt exposes one side wall
    assert np.all(np.abs(p[:, 1]) <= gauge.length / 2 + 1e-12)


def test_measurement_range_blanks_points(gauge):
    far = render_profile(gauge, LOOKING_DOWN, np.array([0.0, 0.0, 0.70]))
    assert np.all(np.isnan(far[:, 1]))  # everything beyond 600 mm
    narrow = ProfilerModel(width_near=0.08, width_far=0.08 * 320 / 163)
    t = np.array([0.0, 0.0, 0.33])
    profile = render_profile(gauge, LOOKING_DOWN, t, profiler=narrow)
    valid = np.isfinite(profile[:, 1])
    assert np.all(np.abs(profile[valid, 0]) <= narrow.half_width(profile[valid, 1]) + 1e-15)
    assert valid.sum() < np.sum(np.abs(profile[:, 0]) <= gauge.width / 2)


def test_shadow_mask_hand_case():
    emitter_z = -0.042
    x = np.array([0.01, 0.02, 0.03])
    # angles from the emitter: atan2(x, z + 0.042)
    lit = shadow_mask(x, np.array([0.30, 0.25, 0.35]), emitter_z)  # 0.0292, 0.0684, 0.0763: increasing
    assert not lit.any()
    hidden = shadow_mask(x, np.array([0.30, 0.20, 0.35]), emitter_z)  # 0.0292, 0.0824, 0.0763: third hidden
    assert hidden.tolist() == [False, False, True]
    mirrored = shadow_mask(-x[::-1], np.array([0.35, 0.20, 0.30]), emitter_z)
    assert mirrored.tolist() == [True, False, False]


def test_steep_view_self_occludes():
    steep = heightfield_gauge("steep", 0.12, 0.10, [-0.038, -0.019, 0.0, 0.019, 0.038], np.radians([0, 5, 0, 5, 0]),
                              [1.2, -1.2, 1.2, -1.2, 1.2, -1.2])  # faces at 50 deg: beta = 40 deg
    rotation = so3_exp(np.array([0.0, np.radians(40.0), 0.0])) @ LOOKING_DOWN
    t = np.array([0.03, 0.0, 0.03]) - 0.40 * rotation[:, 2]
    with_shadow = render_profile(steep, rotation, t)
    without = render_profile(steep, rotation, t, profiler=ProfilerModel(occlusion=False))
    shadowed = np.isnan(with_shadow[:, 1]) & np.isfinite(without[:, 1])
    assert shadowed.sum() > 20  # alpha = 40 deg plus the fan angle exceeds beta: faces hide each other


def test_noise_and_spikes_are_seedable_and_sized(gauge):
    t = np.array([0.0, 0.0, 0.45])
    clean = render_profile(gauge, LOOKING_DOWN, t)
    a = render_profile(gauge, LOOKING_DOWN, t, noise_std=5e-6, rng=np.random.default_rng(7))
    b = render_profile(gauge, LOOKING_DOWN, t, noise_std=5e-6, rng=np.random.default_rng(7))
    assert np.array_equal(a, b, equal_nan=True)
    valid = np.isfinite(clean[:, 1])
    assert np.std(a[valid, 1] - clean[valid, 1]) == pytest.approx(5e-6, rel=0.1)
    spiky = render_profile(gauge, LOOKING_DOWN, t, spike_fraction=0.01, rng=np.random.default_rng(1))
    jump = np.abs(spiky[valid, 1] - clean[valid, 1])
    assert np.sum(jump > 0) == round(0.01 * valid.sum())
    assert np.all((jump == 0) | ((jump >= 2e-4 - 1e-12) & (jump <= 2e-3 + 1e-12)))


def test_true_corners_lie_on_both_faces(gauge):
    rotation = so3_exp(np.array([0.05, -0.08, 0.1])) @ LOOKING_DOWN
    t = np.array([0.003, -0.006, 0.03]) - 0.42 * rotation[:, 2]
    corners = true_corners(gauge, rotation, t)
    p = to_gauge(corners, rotation, t)
    for i in range(gauge.n_ridges):
        assert gauge.normals[i] @ p[i] == pytest.approx(gauge.offsets[i], abs=1e-14)
        assert gauge.normals[i + 1] @ p[i] == pytest.approx(gauge.offsets[i + 1], abs=1e-14)
    assert np.all(np.diff(corners[:, 0]) > 0)
    assert DEFAULT_PROFILER.in_range(corners[:, 0], corners[:, 1]).all()


def test_compiled_trace_equals_the_reference(gauge) -> None:
    """sim_cell renders with render_kernel's compiled trace; it must see exactly what the reference sees,
    side walls and misses included (poses far off the gauge, tilted, and random gauges)."""
    from profile_pose_ros.core.design.gauge_design import random_gauge
    from profile_pose_ros.core.model.render import trace_depth
    from profile_pose_ros.core.compiled.render_kernel import trace_depth_fast

    rng = np.random.default_rng(11)
    gauges = [gauge] + [random_gauge(n, rng) for n in (4, 7)]
    x = DEFAULT_PROFILER.x
    for g in gauges:
        for _ in range(20):
            rotation = so3_exp(rng.normal(0, 0.4, 3)) @ np.diag([1.0, -1.0, -1.0])
            translation = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.08, 0.08), 0.45])
            reference = trace_depth(g, rotation, translation, x)
            np.testing.assert_array_equal(np.isnan(trace_depth_fast(g, rotation, translation, x)),
                                          np.isnan(reference))
            np.testing.assert_allclose(trace_depth_fast(g, rotation, translation, x), reference, rtol=0, atol=1e-12)


def test_compiled_shadow_and_range_equal_the_reference(gauge) -> None:
    """sim_cell's one compiled pass (trace, emitter shadow, measurement range) hides exactly the points
    the reference hides; the poses are tilted enough that some are shadowed, and a narrow profiler
    model clips the range."""
    from profile_pose_ros.core.design.gauge_design import random_gauge
    from profile_pose_ros.core.model.render import visible_depth
    from profile_pose_ros.core.compiled.render_kernel import trace_depth_fast, visible_depth_fast

    rng = np.random.default_rng(12)
    models = [DEFAULT_PROFILER, ProfilerModel(z_near=0.40, z_far=0.47, width_near=0.05, width_far=0.09),
              ProfilerModel(occlusion=False)]
    shadowed = clipped = 0
    for g in [gauge] + [random_gauge(n, rng) for n in (4, 7)]:
        for _ in range(30):
            rotation = so3_exp(rng.normal(0, 0.5, 3)) @ np.diag([1.0, -1.0, -1.0])
            translation = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.45])
            traced = trace_depth_fast(g, rotation, translation, DEFAULT_PROFILER.x)
            for model in models:
                reference = visible_depth(g, rotation, translation, model, trace=trace_depth_fast)
                np.testing.assert_array_equal(visible_depth_fast(g, rotation, translation, model), reference)
            shadowed += shadow_mask(DEFAULT_PROFILER.x, traced, DEFAULT_PROFILER.emitter_z).any()
            clipped += (np.isfinite(traced) & ~models[1].in_range(DEFAULT_PROFILER.x, traced)).any()
    assert shadowed >= 5 and clipped >= 5
