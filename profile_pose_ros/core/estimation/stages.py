"""The estimator's stages on the compiled kernels: corner detection, refinement from a start, dense
refinement, each with the options packed for the kernel and its status turned into a reason.

Which build of the kernels runs (prebuilt, JIT or uncompiled) is compiled/loader.py's choice.
"""
from __future__ import annotations

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
from .result import EstimatorOptions
from .solver import PoseSolution, Refinement

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
    v[codes.O_ROBUST] = 1.0 if c.robust_line_fit else 0.0
    v[codes.O_THR] = c.outlier_threshold
    v[codes.O_FLOOR] = c.min_outlier_floor
    v[codes.O_NOISE] = options.noise_std
    v[codes.O_SIGFLOOR] = 1e-7  # same floor as CornerResult.covariance
    v[codes.O_WEIGHTED] = 1.0 if options.refine_weighting == "corner_covariance" else 0.0
    v[codes.O_REFINE] = 1.0 if options.refine else 0.0
    v[codes.O_MAXIT] = options.max_iterations
    v[codes.O_MAXREPROJ] = options.max_reprojection_error
    v[codes.O_MARGIN] = options.footprint_margin
    v[codes.O_PASSES] = ROBUST_PASSES
    v.setflags(write=False)
    return v


def detection_reason(status: int, info: np.ndarray, n: int, options: CornerOptions) -> str | None:
    detection = {
        codes.TOO_FEW_POINTS: lambda: reason_too_few_points(int(info[0]), n, int(info[1])),
        codes.X_NOT_INCREASING: lambda: REASON_X_NOT_INCREASING,
        codes.STEEP_SEGMENT: lambda: reason_steep_segment(int(info[0]), info[1], options),
        codes.WRONG_CORNER_COUNT: lambda: reason_corner_count(int(info[1]), n),
        codes.CORNER_NOT_BETWEEN: lambda: reason_corner_not_between(int(info[0]), info[1], info[2], info[3]),
        codes.CORNERS_NOT_INCREASING: lambda: REASON_CORNERS_NOT_INCREASING,
    }
    return detection[status]() if status in detection else None


def detect_corners(points: np.ndarray, n_corners: int, options: CornerOptions = CornerOptions()) -> CornerResult:
    """The profile's n corners, their face fits and Jacobian, or why not (paper II-D; corners.py says how)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        return CornerResult(False, f"profile must be an (N, 2) array, got shape {points.shape}")
    corners, jac = np.empty((n_corners, 2)), np.empty((2 * n_corners, 2 * (n_corners + 1)))
    lines, info = np.empty((n_corners + 1, 10)), np.zeros(4)
    status, _, fit_rms = kernels().detect(points, n_corners, option_vector(_corner_only(options)), corners, jac,
                                          np.empty(2 * (n_corners + 1)), info, lines)
    if status != codes.OK:
        return CornerResult(False, detection_reason(status, info, n_corners, options))
    fits = [LineFit(int(row[0]), int(row[1]), row[2], row[3], row[4], row[5], int(row[6]), row[7], row[8], row[9])
            for row in lines]
    return CornerResult(True, "", corners, fits, jac, fit_rms)


def _corner_only(options: CornerOptions) -> EstimatorOptions:
    """Estimator options around corner options, one object per corner options (option_vector caches on it)."""
    return _cached_on(options, "_estimator_options", lambda: EstimatorOptions(corners=options))


def refine_pose(gauge: Gauge, corners: np.ndarray, start: PoseSolution, corner_covariance: np.ndarray,
                    weighted: bool = True, max_iterations: int = 30, polish: bool = True) -> Refinement:
    """Levenberg-Marquardt on SO(3) x R^3 from `start`, minimising the corner residuals (paper eq. 15):
    weighted by their covariance (maximum likelihood) or, weighted=False, the paper's plain sum of
    squares; then undamped Gauss-Newton steps to the minimiser (polish). The covariance returned is the
    sandwich form, honest when the weights are not the inverse covariance. Raises LinAlgError when the
    normal equations are singular."""
    if corner_covariance is None or not corner_covariance.size:
        raise ValueError("refine_pose needs the corners' covariance (CornerResult.covariance)")
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


def refine_dense(gauge: Gauge, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                          noise_std: float = 0.0, options: DenseOptions = DenseOptions()) -> DenseResult:
    """Gauss-Newton on every usable point's depth from (rotation, translation), re-selecting the points at each
    step (dense.py says which); noise_std 0 = estimate it from the residuals."""
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
