"""The numpy baseline that Table III compares the runtime path against (profile_pose benchmark), never on
the runtime path: the method written the straightforward way. numpy RDP and line fits, numpy SVD closed
form (closed_form; paper_closed_form is the paper's as printed, for Table I), and the refinement of paper
eq. (15) with scipy.optimize.least_squares over a unit quaternion and t, with the residuals whitened by
their covariance so it solves the same problem as the runtime path. Its corner detection is the algorithm
of the compiled one (compiled/estimate_kernel.py: _detect), step for step; the tests hold the two to the
same corners."""
from __future__ import annotations

import math
import time

import numpy as np
from scipy.linalg import cholesky, solve_triangular
from scipy.optimize import least_squares

from ..core.estimation.corners import (REASON_CORNERS_NOT_INCREASING, REASON_X_NOT_INCREASING, ROBUST_PASSES,
                                       CornerOptions, CornerResult, LineFit, reason_corner_count,
                                       reason_corner_not_between, reason_steep_segment, reason_too_few_points)
from ..core.compiled.codes import MAX_GLINT_RUN
from ..core.estimation.result import EstimatorOptions
from ..core.estimation.residuals import (REASON_CF_DEGENERATE, PoseSolution, corner_residuals, reason_cf_rank,
                                         residual_covariance)
from ..core.model.gauge import Gauge
from ..core.model.rotation import nearest_rotation, quaternion_xyzw, rotation_from_quaternion_xyzw


class ClosedFormError(ArithmeticError):
    """The corners do not determine a pose (degenerate geometry)."""


def rdp_vertices(points: np.ndarray, epsilon: float) -> np.ndarray:
    """Sorted indices of the vertices RDP keeps (always the first and the last point).

    Iterative with an explicit stack, so a noisy 3,200-point profile cannot hit the recursion limit.
    """
    n = len(points)
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        first, last = stack.pop()
        if last - first < 2:
            continue
        a = points[first]
        chord = points[last] - a
        length = np.hypot(chord[0], chord[1])
        rel = points[first + 1:last] - a
        if length > 0:
            dist = np.abs(chord[0] * rel[:, 1] - chord[1] * rel[:, 0]) / length
        else:
            dist = np.hypot(rel[:, 0], rel[:, 1])
        i = int(np.argmax(dist))
        if dist[i] > epsilon:
            split = first + 1 + i
            keep[split] = True
            stack.append((first, split))
            stack.append((split, last))
    return np.nonzero(keep)[0]


def fit_line(points: np.ndarray, first: int, last: int, options: CornerOptions) -> LineFit:
    """Least-squares line over points[first..last] after trimming, with optional outlier rejection."""
    count = last - first + 1
    trim = int(options.trim_fraction * count)
    seg = points[first + trim:last - trim + 1]
    if len(seg) < 2:
        seg = points[first:last + 1]
    x, z = seg[:, 0], seg[:, 1]
    keep = np.ones(len(seg), dtype=bool)
    fit = LineFit(first, last)
    passes = ROBUST_PASSES if options.robust_line_fit else 1
    for iteration in range(passes):
        xs, zs = x[keep], z[keep]
        x_mean = xs.mean()
        dx = xs - x_mean
        sxx = float(dx @ dx)
        if sxx <= 0:
            break
        z_mean = zs.mean()
        slope = float(dx @ (zs - z_mean)) / sxx
        fit = LineFit(first, last, slope, float(x_mean), float(z_mean), sxx, int(keep.sum()),
                      x_min=float(points[first, 0]), x_max=float(points[last, 0]))
        if iteration == passes - 1:
            break
        residual = z - (slope * (x - x_mean) + z_mean)
        scale = 1.4826 * np.median(np.abs(residual[keep]))
        new_keep = np.abs(residual) <= max(options.outlier_threshold * scale, options.min_outlier_floor)
        if np.array_equal(new_keep, keep) or new_keep.sum() < 2:
            break
        keep = new_keep
    if fit.n_used > 2:
        residual = z[keep] - (fit.slope * (x[keep] - fit.x_mean) + fit.z_mean)
        fit.sigma = float(np.sqrt(residual @ residual / (fit.n_used - 2)))
    return fit


def intersect(a: LineFit, b: LineFit) -> tuple[np.ndarray, np.ndarray]:
    """Intersection of two fitted lines and its Jacobian w.r.t. (slope_a, z_mean_a, slope_b, z_mean_b)."""
    dm = a.slope - b.slope
    ba = a.z_mean - a.slope * a.x_mean
    bb = b.z_mean - b.slope * b.x_mean
    x = (bb - ba) / dm
    z = a.slope * (x - a.x_mean) + a.z_mean
    dx = np.array([(a.x_mean - x) / dm, -1.0 / dm, (x - b.x_mean) / dm, 1.0 / dm])
    dz = a.slope * dx + np.array([x - a.x_mean, 1.0, 0.0, 0.0])
    return np.array([x, z]), np.vstack([dx, dz])


def _segments(points: np.ndarray, vertices: np.ndarray, options: CornerOptions) -> list[LineFit]:
    lines = []
    for first, last in zip(vertices[:-1], vertices[1:]):
        if last - first + 1 >= options.min_segment_points:
            lines.append(fit_line(points, int(first), int(last), options))
    return lines


def _merge_collinear(points: np.ndarray, lines: list[LineFit], options: CornerOptions) -> list[LineFit]:
    merged = True
    while merged and len(lines) > 1:
        merged = False
        gaps = [abs(math.atan((a.slope - b.slope) / (1.0 + a.slope * b.slope))) for a, b in zip(lines, lines[1:])]
        j = int(np.argmin(gaps))
        if gaps[j] < options.min_corner_angle:
            lines[j:j + 2] = [fit_line(points, lines[j].first, lines[j + 1].last, options)]
            merged = True
    return lines


def _without_spikes(pts: np.ndarray, threshold: float) -> np.ndarray:
    """pts without the glints: the points off the median depth of their five neighbours by more than threshold,
    and the runs of up to MAX_GLINT_RUN points side by side that step off their face by more than threshold
    (compiled/estimate_kernel.py: _drop_spikes says why; the same decisions, written the plain way)."""
    if threshold <= 0 or len(pts) < 5:
        return pts
    x, z = pts[:, 0], pts[:, 1]
    inner = z[2:-2]
    off_line = np.abs(inner - 0.5 * (z[1:-3] + z[3:-1])) > 0.5 * threshold
    if not off_line.any():
        return pts
    off_median = np.abs(inner - np.median(np.lib.stride_tricks.sliding_window_view(z, 5), axis=1)) > threshold
    spike = np.zeros(len(pts), dtype=bool)
    spike[2:-2] = off_line & off_median
    outer, anchor = 0, 1  # the last two points kept
    for i in range(2, len(z) - 2):
        if spike[i]:
            continue
        if abs(z[i] - z[anchor]) > threshold:
            end = _glint_run_end(x, z, outer, anchor, i, threshold)
            if end > i:
                spike[i:end] = True
                continue
        outer, anchor = anchor, i
    return pts[~spike]


def _glint_run_end(x: np.ndarray, z: np.ndarray, outer: int, anchor: int, i: int, threshold: float) -> int:
    """The first j after the run from i whose line from the anchor leaves every run point more than threshold
    off and the two points beyond within it; -1 if none (estimate_kernel._displaced_run_end)."""
    for j in range(max(i + 1, anchor + 3), min(i + MAX_GLINT_RUN, len(z) - 2) + 1):
        if not x[j] > x[anchor]:
            return -1
        slope = (z[j] - z[anchor]) / (x[j] - x[anchor])
        line = lambda k: z[anchor] + slope * (x[k] - x[anchor])  # noqa: E731
        if abs(z[outer] - line(outer)) <= threshold and abs(z[j + 1] - line(j + 1)) <= threshold and all(
                abs(z[m] - line(m)) > threshold for m in range(i, j)):
            return j
    return -1


def detect_corners(points: np.ndarray, n_corners: int, options: CornerOptions = CornerOptions()) -> CornerResult:
    """Find exactly n_corners corners, in order of increasing x, or say why not."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2:
        return CornerResult(False, f"profile must be an (N, 2) array, got shape {points.shape}")
    valid = np.isfinite(points).all(axis=1)
    pts = _without_spikes(points[valid], options.spike_threshold)
    needed = (n_corners + 1) * options.min_segment_points
    if len(pts) < needed:
        return CornerResult(False, reason_too_few_points(len(pts), n_corners, needed))
    if np.any(np.diff(pts[:, 0]) <= 0):
        return CornerResult(False, REASON_X_NOT_INCREASING)

    vertices = rdp_vertices(pts, options.rdp_epsilon)
    lines = _merge_collinear(pts, _segments(pts, vertices, options), options)
    while lines and abs(lines[0].angle) > options.max_face_angle:
        lines.pop(0)
    while lines and abs(lines[-1].angle) > options.max_face_angle:
        lines.pop()
    for k, line in enumerate(lines):
        if abs(line.angle) > options.max_face_angle:
            return CornerResult(False, reason_steep_segment(k, line.x_mean, options))
    if len(lines) != n_corners + 1:
        return CornerResult(False, reason_corner_count(len(lines), n_corners))

    corners = np.empty((n_corners, 2))
    jacobian = np.zeros((2 * n_corners, 2 * (n_corners + 1)))
    for i, (a, b) in enumerate(zip(lines[:-1], lines[1:])):
        corners[i], jacobian[2 * i:2 * i + 2, 2 * i:2 * i + 4] = intersect(a, b)
        low, high = a.x_max - options.max_corner_offset, b.x_min + options.max_corner_offset
        if not low <= corners[i, 0] <= high or not np.isfinite(corners[i]).all():
            return CornerResult(False, reason_corner_not_between(i, corners[i, 0], a.x_max, b.x_min))
    if np.any(np.diff(corners[:, 0]) <= 0):
        return CornerResult(False, REASON_CORNERS_NOT_INCREASING)

    used = sum(line.n_used - 2 for line in lines)
    rms = math.sqrt(sum(line.sigma ** 2 * (line.n_used - 2) for line in lines) / max(1, used))
    return CornerResult(True, "", corners, lines, jacobian, rms)


def closed_form(gauge: Gauge, corners: np.ndarray) -> PoseSolution:
    """Paper eqs. (9)-(14): solve the stacked 2n x 9 system by SVD, then project onto SE(3). Raises
    ClosedFormError when the corners do not determine a pose."""
    a, b = _system(gauge, corners)
    x, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < 9:
        raise ClosedFormError(reason_cf_rank(len(corners), rank))
    return _pose_from_m(gauge, corners, x)


def _system(gauge: Gauge, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stacked 2n x 9 system A x = b of eqs. (9)-(10)."""
    n = len(corners)
    p = np.column_stack([corners[:, 0], corners[:, 1], np.ones(n)])  # [px, pz, 1]
    a = np.zeros((2 * n, 9))
    a[0::2, 0:3] = p
    a[0::2, 3:6] = -gauge.u[:, None] * p
    a[1::2, 3:6] = -gauge.w[:, None] * p
    a[1::2, 6:9] = p
    b = np.empty(2 * n)
    b[0::2] = gauge.q[:, 0]
    b[1::2] = gauge.q[:, 2]
    return a, b


def _pose_from_m(gauge: Gauge, corners: np.ndarray, x: np.ndarray) -> PoseSolution:
    """Eqs. (12)-(14): rows of M = [r1 r3 t] -> nearest rotation, rescaled translation."""
    m = x.reshape(3, 3)
    r1, r3, t_hat = m[:, 0], m[:, 1], m[:, 2]
    r_hat = np.column_stack([r1, np.cross(r3, r1), r3])
    norm_hat = np.linalg.norm(r_hat)
    if not np.isfinite(norm_hat) or norm_hat == 0:
        raise ClosedFormError(REASON_CF_DEGENERATE)
    rotation = nearest_rotation(r_hat)
    translation = np.linalg.norm(rotation) / norm_hat * t_hat
    return PoseSolution(rotation, translation, corner_residuals(gauge, corners, rotation, translation))


def paper_closed_form(gauge: Gauge, corners: np.ndarray) -> PoseSolution:
    """Eqs. (9)-(14) exactly as printed, also when the system is rank-deficient (n = 4): the SVD then
    returns the minimum-norm solution, which is what the paper's Table I reports as failing for n = 4."""
    a, b = _system(gauge, corners)
    return _pose_from_m(gauge, corners, np.linalg.lstsq(a, b, rcond=None)[0])


def estimate_baseline(points: np.ndarray, gauge: Gauge, options: EstimatorOptions = EstimatorOptions()):
    """(R, t, timings) or (None, None, timings) when detection or the closed form fails."""
    timings = {}
    start = time.perf_counter()
    found = detect_corners(points, gauge.n_ridges, options.corners)
    timings["corner_detection"] = time.perf_counter() - start
    if not found.ok:
        return None, None, timings
    start = time.perf_counter()
    try:
        initial = closed_form(gauge, found.corners)
    except ClosedFormError:
        return None, None, timings
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
