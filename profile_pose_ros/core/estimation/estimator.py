"""estimate_pose: profile -> corners -> closed form -> refinement -> checks.

Every failure returns ok=False with a reason instead of raising: the node publishes nothing for a
rejected profile and reports the reason in diagnostics. A pose is only returned when the corners fit
the gauge (reprojection error under a bound, corners inside the gauge's footprint). One source runs
every stage: the kernels in compiled/, compiled ahead, JIT-compiled or, for debugging, uncompiled
(compiled/loader.py).
"""
from __future__ import annotations

import time
from functools import lru_cache
from typing import Callable

import numpy as np

from ..compiled import codes
from ..compiled.loader import kernels
from ..model.gauge import Gauge
from ..model.rotation import rotation_angle, so3_log
from .background import without_background
from .hidden_face import make_partial_gauges, partial_view_estimate, partial_view_inputs
from .result import (REASON_NOT_FINITE, EstimatorOptions, PoseEstimate, reason_ambiguous, reason_inconsistent,
                     reason_outside, reason_poorly_determined, reason_reprojection)
from .residuals import REASON_CF_DEGENERATE, PoseSolution, corner_residuals, reason_cf_rank, solution_cost
from .stages import detect_corners, detection_reason, refine_pose

REASON_NO_START = "no real starting pose for the 4-ridge gauge"


def estimate_pose(points: np.ndarray, gauge: Gauge, options: EstimatorOptions | None = None,
                  **overrides) -> PoseEstimate:
    """Estimate the profiler pose from one profile ((N, 2) [x, z] in metres, NaN = invalid).

    Keyword overrides are any EstimatorOptions or CornerOptions field, e.g. refine=False.
    """
    options = options or _DEFAULT_OPTIONS
    if overrides:
        options = _cached(_options_with, options, tuple(sorted(overrides.items())))
    return _estimate_in_one_call(points, gauge, _cached(_first_of_equal, options))


# An options object packs its kernel vector and the partial views' inputs (kept per gauge) once. A call without
# options, with overrides, or with options made anew but equal to earlier ones therefore runs on one shared
# object: made on every call, they cost more than the shipped gauge's whole estimate (docs/performance.md,
# "Called plainly").
_DEFAULT_OPTIONS = EstimatorOptions()


@lru_cache(maxsize=16)
def _options_with(options: EstimatorOptions, overrides: tuple) -> EstimatorOptions:
    return options.with_changes(**dict(overrides))


@lru_cache(maxsize=16)
def _first_of_equal(options: EstimatorOptions) -> EstimatorOptions:
    return options


def _cached(function, *args):
    """function(*args) through its cache; uncached when an argument cannot be hashed (a value with_changes then
    refuses, or options a caller built with one)."""
    try:
        return function(*args)
    except TypeError:
        return function.__wrapped__(*args)


def _reason(status: int, info: np.ndarray, gauge: Gauge, options: EstimatorOptions, error: float) -> str:
    if status >= codes.DENSE_STAGE:
        if status - codes.DENSE_STAGE == codes.SINGULAR:
            return "dense refinement: Singular matrix"
        return f"dense refinement: {_reason(status - codes.DENSE_STAGE, info, gauge, options, error)}"
    n = gauge.n_ridges
    detection = detection_reason(status, info, n, options.corners)
    if detection is not None:
        return f"corner detection: {detection}"
    if status == codes.CF_RANK:
        return f"closed form: {reason_cf_rank(n, int(info[0]))}"
    if status == codes.CF_DEGENERATE:
        return f"closed form: {REASON_CF_DEGENERATE}"
    if status == codes.SINGULAR:
        return "refinement: Singular matrix"
    if status == codes.NOT_FINITE:
        return REASON_NOT_FINITE
    if status == codes.INCONSISTENT:
        return reason_inconsistent(info[0], int(info[1]), gauge, options)
    if status == codes.REPROJECTION:
        return reason_reprojection(error, gauge, options)
    if status == codes.OUTSIDE_FOOTPRINT:
        return reason_outside(int(info[0]), info[1], info[2], gauge)
    if status == codes.AMBIGUOUS:
        return reason_ambiguous(info[0], info[1], info[2])
    if status == codes.NO_START:
        return f"closed form: {REASON_NO_START}"
    if status == codes.NO_CONVERGED:
        return "refinement: no starting pose converged"
    return f"internal status {status}"


def _estimate_in_one_call(points: np.ndarray, gauge: Gauge, options: EstimatorOptions,
                          background_cut: bool = False) -> PoseEstimate:
    """The whole estimate in a single compiled call (corners, closed form or four-ridge starts, refinement,
    basin search, checks) and, when corner detection refuses the profile, the partial view's (hidden_face.py):
    perhaps a gap hides a whole face. Its corners then see the gauge without that face, but the profile's points
    still lie on the real gauge: the dense refinement fits them to all its faces (with the reduced gauge it cut
    the points of a face narrowly in view after all and settled far off: docs/estimator.md)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        return PoseEstimate(False, f"corner detection: profile must be an (N, 2) array, got shape {points.shape}")
    n = gauge.n_ridges
    # corners, rotation, t, covariance (NaN-filled by the kernel unless ok), closed form's, residuals, info
    outputs = (np.empty((n, 2)), np.empty((3, 3)), np.empty(3), np.empty((6, 6)), np.empty((3, 3)), np.empty(3),
               np.empty((n, 2)), np.empty((n, 2)), np.zeros(4))
    where = np.empty(6)  # a partial view's numbers for its reason
    start = time.perf_counter()
    try:
        result = kernels().estimate(points, gauge.q, gauge.u, gauge.w, *gauge.kernel_faces, gauge.width, gauge.length,
                                    options.kernel_vector, *partial_view_inputs(gauge, options), *outputs, where)
    except np.linalg.LinAlgError as exc:
        return PoseEstimate(False, f"refinement: {exc}", timings={"total": time.perf_counter() - start})
    timings = {"total": time.perf_counter() - start}
    outcome, m, which = result[:7], result[7], result[8:]
    if outcome[0] == codes.X_NOT_INCREASING and _x_decreasing(points):
        return _estimate_in_one_call(points[::-1], gauge, options, background_cut)
    if not background_cut and _too_many_faces(outcome[0], outputs[8], n):
        kept = without_background(points, options.corners.max_face_angle)
        if kept is not None:  # what the gauge stands on, seen beside it: its segments are no faces of the gauge
            again = _estimate_in_one_call(kept, gauge, options, background_cut=True)
            if again.ok or len(again.corners):  # its corners found: its pose, or why that pose is refused
                again.timings["total"] = time.perf_counter() - start
                again.background_cut = True  # again is this call's own
                return again
    if which[0] == codes.PARTIAL_NONE:
        return _described(outcome, outputs, lambda: gauge, options, timings)
    outputs = (outputs[0][:m], *outputs[1:6], outputs[6][:m], outputs[7][:m], outputs[8])
    return partial_view_estimate(outcome, outputs, which, where, gauge, options, _described, timings)


def _too_many_faces(status: int, info: np.ndarray, n: int) -> bool:
    """Whether corner detection refused a profile for more faces than the gauge has, or a steep segment between
    faces: what a table or a fixture beside the gauge makes (background.py)."""
    return status == codes.STEEP_SEGMENT or status == codes.WRONG_CORNER_COUNT and info[1] > n + 1


def _x_decreasing(points: np.ndarray) -> bool:
    """Whether the valid points' x strictly decrease: a profiler (or a driver) that reports the laser line from
    +x to -x gives the same profile as one reporting it from -x to +x, and is estimated in that order; any other
    order is refused, as a fold-over or a scrambled message says something is wrong."""
    x = points[np.isfinite(points).all(axis=1), 0]
    return x.size > 1 and bool(np.all(np.diff(x) < 0))


def _described(outcome: tuple, outputs: tuple, seen: Callable[[], Gauge], options: EstimatorOptions,
               timings: dict) -> PoseEstimate:
    """The PoseEstimate of a compiled estimate's outcome (its returned tuple) and outputs (the arrays it filled,
    in _estimate_in_one_call's order, this call's own) for the gauge its corners saw, which `seen` makes only
    for a refusal's words: the whole gauge, or a partial view's (hidden_face.py). A pose whose position is too
    poorly determined to trust its covariance is refused here, its numbers blanked in place and the corner
    results kept for diagnosis (as `rejected` makes it, without copying the estimate: most profiles of a noisy
    or near-degenerate view end here)."""
    status, iterations, fit_rms, error, cf_error, sigma, search_starts = outcome
    corners, rot, t, cov, cf_rot, cf_t, cf_res, _, info = outputs
    if status in (codes.TOO_FEW_POINTS, codes.X_NOT_INCREASING, codes.STEEP_SEGMENT, codes.WRONG_CORNER_COUNT,
                  codes.CORNER_NOT_BETWEEN, codes.CORNERS_NOT_INCREASING):
        return PoseEstimate(False, _reason(status, info, seen(), options, error), timings=timings)
    if status in (codes.CF_RANK, codes.CF_DEGENERATE, codes.NO_START):
        return PoseEstimate(False, _reason(status, info, seen(), options, error), corners=corners, timings=timings)
    ok = status == codes.OK
    reason = "" if ok else _reason(status, info, seen(), options, error)
    if ok and sigma > options.max_position_sigma:
        ok, reason = False, reason_poorly_determined(sigma, options)
        for published in (rot, t, cov):
            published.fill(np.nan)
    return PoseEstimate(ok=ok, reason=reason, R=rot, t=t, corners=corners, reprojection_error=error, covariance=cov,
                        closed_form=PoseSolution(cf_rot, cf_t, cf_res), refined=options.refine,
                        iterations=iterations, fit_rms=fit_rms, timings=timings,
                        position_sigma=sigma if ok else None, search_starts=int(search_starts))


def warm_up(gauge: Gauge, options: EstimatorOptions | None = None) -> float:
    """Compile (or load from cache) every path, and make the gauges of partial views, before the first real
    profile; returns seconds taken."""
    from ..model.poses import sample_pose
    from ..model.render import render_profile

    start = time.perf_counter()
    options = _cached(_first_of_equal, options or _DEFAULT_OPTIONS)  # the object estimate_pose will run on
    rotation, translation = sample_pose(gauge, np.random.default_rng(0))
    profile = render_profile(gauge, rotation, translation)
    _estimate_in_one_call(profile, gauge, options)  # also makes the partial views' ridge tables
    _estimate_in_one_call(np.full((10, 2), np.nan), gauge, options)  # a failure path too
    make_partial_gauges(gauge)
    return time.perf_counter() - start


def pose_nees(estimate: PoseEstimate, rotation: np.ndarray, translation: np.ndarray) -> float:
    """Normalised estimation error squared of an estimate against its own covariance (6 on average if honest)."""
    d = np.concatenate([translation - estimate.t, so3_log(rotation @ estimate.R.T)])
    return float(d @ np.linalg.solve(estimate.covariance, d))


def is_wrong_minimum(points: np.ndarray, gauge: Gauge, estimate: PoseEstimate, rotation: np.ndarray,
                     translation: np.ndarray, corner_cov: np.ndarray | None = None) -> bool:
    """True if an accepted estimate is a higher cost minimum than the one refined from the true pose and
    more than one standard deviation (Mahalanobis) from it: the search stopped in the wrong basin."""
    if corner_cov is None:
        corner_cov = detect_corners(points, gauge.n_ridges).covariance(None)
    at_truth = PoseSolution(rotation, translation, corner_residuals(gauge, estimate.corners, rotation, translation))
    truth = refine_pose(gauge, estimate.corners, at_truth, corner_cov)
    found = PoseSolution(estimate.R, estimate.t, corner_residuals(gauge, estimate.corners, estimate.R, estimate.t))
    d = np.concatenate([so3_log(estimate.R.T @ truth.solution.rotation), truth.solution.translation - estimate.t])
    higher = solution_cost(gauge, found, corner_cov, True) > solution_cost(gauge, truth.solution, corner_cov, True)
    return bool(higher and d @ np.linalg.solve(truth.covariance, d) > 1.0)


def pose_error(rotation: np.ndarray, translation: np.ndarray, true_rotation: np.ndarray,
               true_translation: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation error rad) between an estimate and the truth."""
    return float(np.linalg.norm(translation - true_translation)), rotation_angle(rotation, true_rotation)
