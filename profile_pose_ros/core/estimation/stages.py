"""The estimator's stages on the compiled kernels: corner detection, refinement from a start, dense
refinement, each with the options packed for the kernel and its status turned into a reason.

Which build of the kernels runs (prebuilt, JIT or uncompiled) is compiled/loader.py's choice.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..compiled import codes
from ..compiled.loader import kernels
from ..model.gauge import Gauge
from .corners import (REASON_CORNERS_NOT_INCREASING, REASON_X_NOT_INCREASING, CornerOptions, CornerResult,
                      LineFit, reason_corner_count, reason_corner_not_between, reason_steep_segment,
                      reason_too_few_points)
from .dense import DenseOptions, DenseResult
from .result import EstimatorOptions
from .residuals import PoseSolution, Refinement


def detection_reason(status: int, info: np.ndarray, n: int, options: CornerOptions) -> str | None:
    """A corner-detection status code of the kernel in words (None for the codes of later stages)."""
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
    lines, line_var, info = np.empty((n_corners + 1, 10)), np.empty(2 * (n_corners + 1)), np.zeros(4)
    status, _, fit_rms = kernels().detect(points, n_corners, _corner_kernel_vector(options), corners, jac, line_var,
                                          info, lines)
    if status != codes.OK:
        return CornerResult(False, detection_reason(status, info, n_corners, options),
                            faces_found=int(info[1]) if status == codes.WRONG_CORNER_COUNT else 0)
    fits = [LineFit(int(first), int(last), slope, x_mean, z_mean, sxx, int(used), sigma, x_min, x_max)
            for first, last, slope, x_mean, z_mean, sxx, used, sigma, x_min, x_max in lines.tolist()]
    return CornerResult(True, "", corners, fits, jac, fit_rms)


@lru_cache(maxsize=16)
def _corner_kernel_vector(options: CornerOptions) -> np.ndarray:
    """The kernel's option vector for corner detection alone (the search detects with the same few)."""
    return EstimatorOptions(corners=options).kernel_vector


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
    normals, offsets, ridge_q, ridge_u = gauge.kernel_faces
    rot_out, t_out, cov_out = np.empty((3, 3)), np.empty(3), np.empty((6, 6))
    status, used, sigma = kernels().refine_dense(
        np.ascontiguousarray(points, dtype=np.float64), normals, offsets, ridge_q, ridge_u, gauge.width, gauge.length,
        np.array(rotation, dtype=np.float64), np.array(translation, dtype=np.float64), float(noise_std),
        options.ridge_margin, options.outlier_threshold, options.min_outlier_floor, options.iterations, rot_out, t_out,
        cov_out)
    if status != codes.OK:
        raise np.linalg.LinAlgError("Singular matrix")
    return DenseResult(rot_out, t_out, cov_out, int(used), float(sigma))
