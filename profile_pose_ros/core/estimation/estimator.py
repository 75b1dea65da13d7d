"""estimate_pose: profile -> corners -> closed form -> refinement -> checks.

Every failure returns ok=False with a reason instead of raising: the node publishes nothing for a
rejected profile and reports the reason in diagnostics. A pose is only returned when the corners fit
the gauge (reprojection error under a bound, corners inside the gauge's footprint).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..model.gauge import Gauge
from ..model.rotation import rotation_angle, so3_log
from .compiled_path import estimate_fast, refine_dense_compiled
from .dense import refine_dense
from .plain import NUMPY, Stages, check_solution, estimate_plain
from .result import EstimatorOptions, PoseEstimate, position_sigma, reason_poorly_determined, ros_covariance
from .solver import PoseSolution, corner_residuals, solution_cost


def estimate_pose(points: np.ndarray, gauge: Gauge, options: EstimatorOptions | None = None, *,
                  backend: str = "fast", **overrides) -> PoseEstimate:
    """Estimate the profiler pose from one profile ((N, 2) [x, z] in metres, NaN = invalid).

    backend "fast" is the compiled path (core/compiled/estimate_kernel.py) used at run time; "numpy" is the readable
    reference it is tested against. Keyword overrides are any EstimatorOptions or CornerOptions
    field, e.g. refine=False.
    """
    options = options or EstimatorOptions()
    if overrides:
        options = options.with_changes(**overrides)
    if backend == "fast":
        estimate = estimate_fast(points, gauge, options)
    elif backend == "numpy":
        estimate = estimate_plain(points, gauge, options)
    else:
        raise ValueError(f"backend must be 'fast' or 'numpy', got {backend!r}")
    if estimate.ok and options.refine and options.refine_model == "dense":
        estimate = _refine_dense(points, gauge, options, estimate, compiled=backend == "fast")
    return _checked_precision(estimate, options)


def _checked_precision(estimate: PoseEstimate, options: EstimatorOptions) -> PoseEstimate:
    """The estimate, or a rejection when its position is too poorly determined to trust its covariance."""
    if not estimate.ok:
        return estimate
    sigma = estimate.position_sigma
    if sigma is None:
        sigma = position_sigma(estimate.covariance[:3, :3])  # NaN (kept) when the covariance is not finite
    if sigma > options.max_position_sigma:
        return _rejected(estimate, reason_poorly_determined(sigma, options))
    return estimate


def _rejected(estimate: PoseEstimate, reason: str, **changes) -> PoseEstimate:
    """The estimate turned into a rejection: no pose, the corner results kept for diagnosis."""
    return replace(estimate, ok=False, reason=reason, R=np.full((3, 3), np.nan), t=np.full(3, np.nan),
                   covariance=np.full((6, 6), np.nan), position_sigma=None, **changes)


def _refine_dense(points: np.ndarray, gauge: Gauge, options: EstimatorOptions, estimate: PoseEstimate,
                  compiled: bool) -> PoseEstimate:
    """Replace the corner solution by the dense one (same checks), keeping the corner results alongside."""
    start = time.perf_counter()
    try:
        dense_fit = refine_dense_compiled if compiled else refine_dense
        dense = dense_fit(gauge, points, estimate.R, estimate.t, options.noise_std)
    except (np.linalg.LinAlgError, ValueError) as exc:
        return _rejected(estimate, f"dense refinement: {exc}")
    solution = PoseSolution(dense.rotation, dense.translation,
                            corner_residuals(gauge, estimate.corners, dense.rotation, dense.translation))
    timings = dict(estimate.timings, dense_refinement=time.perf_counter() - start)
    reason = check_solution(gauge, solution, estimate.corners, options)
    if reason:
        return _rejected(estimate, f"dense refinement: {reason}", timings=timings)
    return replace(estimate, R=dense.rotation, t=dense.translation, reprojection_error=solution.reprojection_error,
                   covariance=ros_covariance(dense.rotation, dense.covariance_local), timings=timings,
                   position_sigma=None)


def pose_nees(estimate: PoseEstimate, rotation: np.ndarray, translation: np.ndarray) -> float:
    """Normalised estimation error squared of an estimate against its own covariance (6 on average if honest)."""
    d = np.concatenate([translation - estimate.t, so3_log(rotation @ estimate.R.T)])
    return float(d @ np.linalg.solve(estimate.covariance, d))


def is_wrong_minimum(points: np.ndarray, gauge: Gauge, estimate: PoseEstimate, rotation: np.ndarray,
                     translation: np.ndarray, stages: Stages = NUMPY, corner_cov: np.ndarray | None = None) -> bool:
    """True if an accepted estimate is a higher cost minimum than the one refined from the true pose and
    more than one standard deviation (Mahalanobis) from it: the search stopped in the wrong basin."""
    if corner_cov is None:
        corner_cov = stages.detect(points, gauge.n_ridges).covariance(None)
    at_truth = PoseSolution(rotation, translation, corner_residuals(gauge, estimate.corners, rotation, translation))
    truth = stages.refine(gauge, estimate.corners, at_truth, corner_cov)
    found = PoseSolution(estimate.R, estimate.t, corner_residuals(gauge, estimate.corners, estimate.R, estimate.t))
    d = np.concatenate([so3_log(estimate.R.T @ truth.solution.rotation), truth.solution.translation - estimate.t])
    higher = solution_cost(gauge, found, corner_cov, True) > solution_cost(gauge, truth.solution, corner_cov, True)
    return bool(higher and d @ np.linalg.solve(truth.covariance, d) > 1.0)


def pose_error(rotation: np.ndarray, translation: np.ndarray, true_rotation: np.ndarray,
               true_translation: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation error rad) between an estimate and the truth."""
    return float(np.linalg.norm(translation - true_translation)), rotation_angle(rotation, true_rotation)
