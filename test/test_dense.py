"""Dense refinement: exact on clean profiles, closer to the dense Cramér-Rao bound than the corner solution,
robust to spikes, with an honest covariance; and available through the node's parameter."""
import numpy as np
import pytest

from profile_pose_ros.core import estimate_pose, pose_error, render_profile, sample_pose
from profile_pose_ros.core.crlb import dense_crlb, position_rotation_rms
from profile_pose_ros.core.rotation import so3_log


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
