"""The estimator on the compiled kernels: options packing, status codes -> reasons, warm-up.

Which build of the kernels runs (prebuilt or JIT) is compiled/loader.py's choice.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from ..compiled import codes
from ..compiled.loader import kernels
from ..model.gauge import Gauge
from .corners import (REASON_CORNERS_NOT_INCREASING, ROBUST_PASSES, REASON_X_NOT_INCREASING, CornerOptions,
                      CornerResult, LineFit, reason_corner_count, reason_corner_not_between, reason_steep_segment,
                      reason_too_few_points)
from .dense import DenseOptions, DenseResult
from .plain import Stages, estimate_plain
from .result import REASON_NOT_FINITE, EstimatorOptions, PoseEstimate, reason_outside, reason_reprojection
from .solver import REASON_CF_DEGENERATE, PoseSolution, Refinement, reason_cf_rank, refine

T = TypeVar("T")


def _cached_on(owner, name: str, build: Callable[[], T]) -> T:
    """build() once per (immutable) owner, kept beside its fields (a frozen dataclass takes no attribute the
    usual way): per-options and per-gauge arrays the compiled calls need on every profile."""
    cached = owner.__dict__.get(name)
    if cached is None:
        cached = build()
        object.__setattr__(owner, name, cached)
    return cached


def option_vector(options: EstimatorOptions) -> np.ndarray:
    """The options packed for the compiled code, computed once per (immutable) options object."""
    return _cached_on(options, "_fast_vector", lambda: _packed_options(options))


def _packed_options(options: EstimatorOptions) -> np.ndarray:
    c = options.corners
    v = np.empty(codes.N_OPTIONS)
    v[codes.O_EPS] = c.rdp_epsilon
    v[codes.O_TRIM] = c.trim_fraction
    v[codes.O_MINSEG] = c.min_segment_points
    v[codes.O_MINANGLE] = c.min_corner_angle
    v[codes.O_MAXFACE] = c.max_face_angle
    v[codes.O_MAXOFF] = c.max_corner_offset
    v[codes.O_ROBUST] = 1.0 if c.robust else 0.0
    v[codes.O_THR] = c.outlier_threshold
    v[codes.O_FLOOR] = c.min_outlier_floor
    v[codes.O_NOISE] = options.noise_std
    v[codes.O_SIGFLOOR] = 1e-7  # same floor as CornerResult.covariance
    v[codes.O_WEIGHTED] = 1.0 if options.weighting == "corner_covariance" else 0.0
    v[codes.O_REFINE] = 1.0 if options.refine else 0.0
    v[codes.O_MAXIT] = options.max_iterations
    v[codes.O_MAXREPROJ] = options.max_reprojection_error
    v[codes.O_MARGIN] = options.footprint_margin
    v[codes.O_PASSES] = ROBUST_PASSES
    v.setflags(write=False)
    return v


def _detection_reason(status: int, info: np.ndarray, n: int, options: CornerOptions) -> str | None:
    detection = {
        codes.TOO_FEW_POINTS: lambda: reason_too_few_points(int(info[0]), n, int(info[1])),
        codes.X_NOT_INCREASING: lambda: REASON_X_NOT_INCREASING,
        codes.STEEP_SEGMENT: lambda: reason_steep_segment(int(info[0]), info[1], options),
        codes.WRONG_CORNER_COUNT: lambda: reason_corner_count(int(info[1]), n),
        codes.CORNER_NOT_BETWEEN: lambda: reason_corner_not_between(int(info[0]), info[1], info[2], info[3]),
        codes.CORNERS_NOT_INCREASING: lambda: REASON_CORNERS_NOT_INCREASING,
    }
    return detection[status]() if status in detection else None


def _reason(status: int, info: np.ndarray, gauge: Gauge, options: EstimatorOptions, error: float) -> str:
    n = gauge.n_ridges
    detection = _detection_reason(status, info, n, options.corners)
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
    if status == codes.REPROJECTION:
        return reason_reprojection(error, gauge, options)
    if status == codes.OUTSIDE_FOOTPRINT:
        return reason_outside(int(info[0]), info[1], info[2], gauge)
    return f"internal status {status}"


def detect_corners_compiled(points: np.ndarray, n_corners: int, options: CornerOptions = CornerOptions()
                            ) -> CornerResult:
    """corners.detect_corners() through the compiled kernel: the same corners, face fits and reasons."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        return CornerResult(False, f"profile must be an (N, 2) array, got shape {points.shape}")
    corners, jac = np.empty((n_corners, 2)), np.empty((2 * n_corners, 2 * (n_corners + 1)))
    lines, info = np.empty((n_corners + 1, 10)), np.zeros(4)
    status, _, fit_rms = kernels().detect(points, n_corners, option_vector(_corner_only(options)), corners, jac,
                                          np.empty(2 * (n_corners + 1)), info, lines)
    if status != codes.OK:
        return CornerResult(False, _detection_reason(status, info, n_corners, options))
    fits = [LineFit(int(row[0]), int(row[1]), row[2], row[3], row[4], row[5], int(row[6]), row[7], row[8], row[9])
            for row in lines]
    return CornerResult(True, "", corners, fits, jac, fit_rms)


def _corner_only(options: CornerOptions) -> EstimatorOptions:
    """Estimator options around corner options, one object per corner options (option_vector caches on it)."""
    return _cached_on(options, "_estimator_options", lambda: EstimatorOptions(corners=options))


def refine_compiled(gauge: Gauge, corners: np.ndarray, start: PoseSolution, corner_covariance: np.ndarray | None,
                    weighted: bool = True, max_iterations: int = 30, polish: bool = True) -> Refinement:
    """solver.refine() through the compiled kernel (same algorithm, same contract, within 1e-12): the basin
    search and the four-ridge starts run it dozens of times per profile. Without a corner covariance it is
    solver.refine() itself."""
    if corner_covariance is None or not corner_covariance.size:
        return refine(gauge, corners, start, corner_covariance, weighted, max_iterations, polish)
    n2 = 2 * len(corners)
    rotation, translation, residuals, covariance = np.empty((3, 3)), np.empty(3), np.empty(n2), np.empty((6, 6))
    status, iterations = kernels().refine_pose(
        gauge.q, gauge.u, gauge.w, np.ascontiguousarray(corners, dtype=np.float64),
        np.ascontiguousarray(start.rotation, dtype=np.float64),
        np.ascontiguousarray(start.translation, dtype=np.float64),
        np.ascontiguousarray(corner_covariance, dtype=np.float64), bool(weighted), int(max_iterations), bool(polish),
        rotation, translation, residuals, covariance)
    if status != codes.OK:
        raise np.linalg.LinAlgError("Singular matrix")
    return Refinement(PoseSolution(rotation, translation, residuals.reshape(-1, 2)), covariance, int(iterations))


def refine_dense_compiled(gauge: Gauge, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                          noise_std: float = 0.0, options: DenseOptions = DenseOptions()) -> DenseResult:
    """dense.refine_dense() through the compiled kernel (same steps, solved by Cholesky; within 1e-9)."""
    normals, offsets, ridge_q, ridge_u = _dense_gauge(gauge)
    rot_out, t_out, cov_out = np.empty((3, 3)), np.empty(3), np.empty((6, 6))
    status, used, sigma = kernels().refine_dense(
        np.ascontiguousarray(points, dtype=np.float64), normals, offsets, ridge_q, ridge_u, gauge.width, gauge.length,
        np.array(rotation, dtype=np.float64), np.array(translation, dtype=np.float64), float(noise_std),
        options.ridge_margin, options.outlier_threshold, options.min_outlier_floor, options.iterations, rot_out, t_out,
        cov_out)
    if status != codes.OK:
        raise np.linalg.LinAlgError("Singular matrix")
    return DenseResult(rot_out, t_out, cov_out, int(used), float(sigma))


def _dense_gauge(gauge: Gauge) -> tuple[np.ndarray, ...]:
    """The gauge's faces and ridge lines as the dense kernel takes them, once per gauge."""
    return _cached_on(gauge, "_dense_arrays", lambda: tuple(
        np.array(a, dtype=np.float64) for a in (gauge.normals, gauge.offsets, gauge.q[:, 0], gauge.u)))


COMPILED = Stages(detect_corners_compiled, refine_compiled)  # estimate_plain()'s stages on the compiled kernels


def estimate_fast(points: np.ndarray, gauge: Gauge, options: EstimatorOptions) -> PoseEstimate:
    if gauge.n_ridges == 4:  # several starting poses (solver.four_ridge_candidates): the numpy path
        return estimate_plain(points, gauge, options, COMPILED)
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        return PoseEstimate(False, f"corner detection: profile must be an (N, 2) array, got shape {points.shape}")
    n = gauge.n_ridges
    corners = np.empty((n, 2))
    rot, t, cov = np.empty((3, 3)), np.empty(3), np.empty((6, 6))  # NaN-filled by the kernel unless ok
    cf_rot, cf_t, cf_res, res = np.empty((3, 3)), np.empty(3), np.empty((n, 2)), np.empty((n, 2))
    info = np.zeros(4)
    start = time.perf_counter()
    try:
        status, iterations, fit_rms, error, cf_error, sigma = kernels().estimate(
            points, gauge.q, gauge.u, gauge.w, gauge.width, gauge.length, option_vector(options), corners, rot, t,
            cov, cf_rot, cf_t, cf_res, res, info)
    except np.linalg.LinAlgError as exc:
        return PoseEstimate(False, f"refinement: {exc}", timings={"total": time.perf_counter() - start})
    timings = {"total": time.perf_counter() - start}
    if status in (codes.TOO_FEW_POINTS, codes.X_NOT_INCREASING, codes.STEEP_SEGMENT, codes.WRONG_CORNER_COUNT,
                  codes.CORNER_NOT_BETWEEN, codes.CORNERS_NOT_INCREASING):
        return PoseEstimate(False, _reason(status, info, gauge, options, error), timings=timings)
    if status in (codes.CF_RANK, codes.CF_DEGENERATE):
        return PoseEstimate(False, _reason(status, info, gauge, options, error), corners=corners, timings=timings)
    ok = status == codes.OK
    if options.search and options.refine and (status in (codes.REPROJECTION, codes.OUTSIDE_FOOTPRINT) or (
            ok and sigma > options.search_min_sigma)):
        # poorly determined, or perhaps in a wrong basin: the numpy path, whose basin search decides
        return estimate_plain(points, gauge, options, COMPILED)
    return PoseEstimate(ok=ok, reason="" if ok else _reason(status, info, gauge, options, error), R=rot, t=t,
                        corners=corners, reprojection_error=error, covariance=cov,
                        closed_form=PoseSolution(cf_rot, cf_t, cf_res), refined=options.refine,
                        iterations=iterations, fit_rms=fit_rms, timings=timings,
                        position_sigma=sigma if ok else None)


def warm_up(gauge: Gauge, options: EstimatorOptions | None = None) -> float:
    """Compile (or load from cache) every path before the first real profile; returns seconds taken."""
    from ..model.poses import sample_pose
    from ..model.render import render_profile

    start = time.perf_counter()
    options = options or EstimatorOptions()
    rotation, translation = sample_pose(gauge, np.random.default_rng(0))
    profile = render_profile(gauge, rotation, translation)
    estimate_fast(profile, gauge, options)
    estimate_fast(np.full((10, 2), np.nan), gauge, options)  # a failure path too
    estimate_plain(profile, gauge, options, COMPILED)  # the kernels of the n = 4 starts and the basin search
    return time.perf_counter() - start
