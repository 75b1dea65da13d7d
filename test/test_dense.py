"""Dense refinement: exact on clean profiles, closer to the dense Cramér-Rao bound than the corner solution,
robust to spikes, with an honest covariance; and available through the node's parameter."""
import numpy as np
import pytest

from profile_pose_ros.core import estimate_pose, pose_error, render_profile, sample_pose
from profile_pose_ros.core.design.crlb import dense_crlb, position_rotation_rms
from profile_pose_ros.core.model.rotation import so3_log


def test_dense_is_exact_on_clean_profiles(gauge, rng):
    for _ in range(10):
        rotation, t = sample_pose(gauge, rng)
        estimate = estimate_pose(render_profile(gauge, rotation, t), gauge, refine_model="dense")
        assert estimate.ok, estimate.reason
        position, angle = pose_error(estimate.R, estimate.t, rotation, t)
        assert position < 1e-9 and angle < 1e-9
        assert "dense_refinement" in estimate.timings


@pytest.mark.parametrize("spikes", [0.0, 0.01])
def test_dense_beats_corners_and_approaches_its_bound(gauge, spikes):
    rng = np.random.default_rng(5)
    rotation, t = sample_pose(gauge, rng)
    corner_err, dense_err, nees = [], [], []
    for _ in range(120):
        points = render_profile(gauge, rotation, t, noise_std=5e-6, spike_fraction=spikes, rng=rng)
        corners = estimate_pose(points, gauge)
        dense = estimate_pose(points, gauge, refine_model="dense")
        assert corners.ok and dense.ok
        corner_err.append(np.linalg.norm(t - corners.t))
        d = np.concatenate([t - dense.t, so3_log(rotation @ dense.R.T)])
        dense_err.append(np.linalg.norm(d[:3]))
        nees.append(d @ np.linalg.solve(dense.covariance, d))
    rms_corner, rms_dense = (np.sqrt(np.mean(np.square(e))) for e in (corner_err, dense_err))
    bound, _ = position_rotation_rms(dense_crlb(gauge, rotation, t, 5e-6))
    assert rms_dense < rms_corner / 1.2
    assert rms_dense < 1.15 * bound  # 1.1-1.2x with a 0.5 mm ridge margin; ~1.0x with 0.05 mm
    assert 4.0 < np.mean(nees) < 9.0


def test_refine_model_is_validated():
    with pytest.raises(ValueError, match="refine_model"):
        estimate_pose(np.zeros((10, 2)), None, refine_model="magic")


def test_compiled_dense_refinement_is_the_numpy_one(gauge, rng):
    """The node's compiled dense refinement against dense.py: same points kept, same minimiser (the steps
    are solved by Cholesky there, by SVD least squares here)."""
    from profile_pose_ros.core.estimation.dense import refine_dense
    from profile_pose_ros.core.estimation.compiled_path import refine_dense_compiled
    from profile_pose_ros.core.model.rotation import rotation_angle

    for _ in range(15):
        rotation, translation = sample_pose(gauge, rng)
        points = render_profile(gauge, rotation, translation, noise_std=5e-6, rng=rng)
        start = estimate_pose(points, gauge)
        assert start.ok
        for noise_std in (0.0, 5e-6):
            plain = refine_dense(gauge, points, start.R, start.t, noise_std)
            compiled = refine_dense_compiled(gauge, points, start.R, start.t, noise_std)
            assert compiled.points_used == plain.points_used
            assert np.abs(compiled.translation - plain.translation).max() < 1e-9
            assert rotation_angle(compiled.rotation, plain.rotation) < 1e-9
            assert compiled.sigma == pytest.approx(plain.sigma, rel=1e-6)
            assert np.allclose(compiled.covariance_local, plain.covariance_local, rtol=1e-6, atol=0)
        fast = estimate_pose(points, gauge, refine_model="dense")
        reference = estimate_pose(points, gauge, refine_model="dense", backend="numpy")
        assert fast.ok and reference.ok
        assert np.abs(fast.t - reference.t).max() < 1e-9
    with pytest.raises(np.linalg.LinAlgError):  # nothing usable: no pose, as dense.py
        refine_dense_compiled(gauge, np.full((50, 2), np.nan), start.R, start.t)
