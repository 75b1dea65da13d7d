"""The method written the straightforward way, for the benchmark only (never on the runtime path):
numpy RDP and line fits (core.corners), numpy SVD closed form (core.solver.closed_form), and the
refinement of paper eq. (15) with scipy.optimize.least_squares over a unit quaternion and t, with the
residuals whitened by their covariance so it solves the same problem as the runtime path."""
from __future__ import annotations

import time

import numpy as np
from scipy.linalg import cholesky, solve_triangular
from scipy.optimize import least_squares

from ..core.estimation.corners import detect_corners
from ..core.estimation.result import EstimatorOptions
from ..core.model.gauge import Gauge
from ..core.model.rotation import quaternion_xyzw, rotation_from_quaternion_xyzw
from ..core.estimation.solver import closed_form, corner_residuals, residual_covariance


def estimate_reference(points: np.ndarray, gauge: Gauge, options: EstimatorOptions = EstimatorOptions()):
    """(R, t, timings) or (None, None, timings) when detection or the closed form fails."""
    timings = {}
    start = time.perf_counter()
    found = detect_corners(points, gauge.n_ridges, options.corners)
    timings["corner_detection"] = time.perf_counter() - start
    if not found.ok:
        return None, None, timings
    start = time.perf_counter()
    initial = closed_form(gauge, found.corners)
    timings["closed_form"] = time.perf_counter() - start
    start = time.perf_counter()
    sigma_r = residual_covariance(gauge, initial.rotation, found.covariance(options.noise_std or None))
    lower = cholesky(sigma_r, lower=True)

    def whitened(x: np.ndarray) -> np.ndarray:
        rotation = rotation_from_quaternion_xyzw(x[:4])
        return solve_triangular(lower, corner_residuals(gauge, found.corners, rotation, x[4:]).ravel(), lower=True)

    x0 = np.concatenate([quaternion_xyzw(initial.rotation), initial.translation])
    result = least_squares(whitened, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    timings["refinement"] = time.perf_counter() - start
    return rotation_from_quaternion_xyzw(result.x[:4]), result.x[4:], timings
