"""Corner detection on a profile (paper II-D), made robust enough to run next to a moving robot.

RDP proposes breakpoints; each segment between breakpoints loses `trim_fraction` of its points at both
ends (edge noise of triangulation) and gets a line fit of z on x (maximum likelihood for depth noise),
optionally with outlier rejection; adjacent lines intersect in the corners. Spurious breakpoints (from
spikes or noise) are removed by merging nearly collinear neighbours, and near-vertical segments at the
ends (the gauge's side walls) are dropped. If the result is not exactly the gauge's n corners in order,
detection fails with a reason: a guessed correspondence would yield a confidently wrong pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .rdp import rdp_vertices

ROBUST_PASSES = 4  # fit, reject outliers, refit: converges in 2-3 passes on spiky profiles


@dataclass(frozen=True)
class CornerOptions:
    rdp_epsilon: float = 3e-4  # m; breakpoint tolerance, far above sensor noise, far below face relief
    trim_fraction: float = 0.10  # paper II-D: discard 10 % of each segment at both ends
    min_segment_points: int = 20  # shorter segments are spikes or edge debris, not faces
    min_corner_angle: float = math.radians(5.0)  # rad; neighbours closer in direction are one face
    max_face_angle: float = math.radians(70.0)  # rad from F's x axis; steeper end segments are walls
    max_corner_offset: float = 1e-3  # m; a corner must lie between the two faces it joins (+- this)
    robust: bool = True  # reject outliers in each line fit (spikes)
    outlier_threshold: float = 4.0  # in robust standard deviations
    min_outlier_floor: float = 1e-6  # m; never reject residuals below this (noise-free profiles)


@dataclass
class LineFit:
    """z = slope * (x - x_mean) + z_mean over the points used; sigma from the fit's residuals."""

    first: int  # index range (into the valid points) the segment spans, inclusive
    last: int
    slope: float = 0.0
    x_mean: float = 0.0
    z_mean: float = 0.0
    sxx: float = 0.0
    n_used: int = 0
    sigma: float = 0.0
    x_min: float = 0.0
    x_max: float = 0.0

    @property
    def angle(self) -> float:
        return math.atan(self.slope)


@dataclass
class CornerResult:
    ok: bool
    reason: str = ""
    corners: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (n, 2) [x, z] in F
    lines: list[LineFit] = field(default_factory=list)  # the n+1 face fits
    jacobian: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # d corners / d line params
    fit_rms: float = float("nan")  # m, rms residual of the face fits

    def covariance(self, noise_std: float | None = None, floor: float = 1e-7) -> np.ndarray:
        """(2n, 2n) covariance of the stacked corners [x0, z0, x1, z1, ...].

        Adjacent corners share a face fit, so the matrix is block-tridiagonal, not diagonal. Each
        line's parameters (slope, z_mean) have variance sigma^2 (1/Sxx, 1/N); sigma is the configured
        depth noise, or else that line's own residual scatter (never below `floor`).
        """
        variance = []
        for line in self.lines:
            sigma = noise_std if noise_std else max(line.sigma, floor)
            variance += [sigma ** 2 / line.sxx, sigma ** 2 / line.n_used]
        return self.jacobian @ np.diag(variance) @ self.jacobian.T


# Failure reasons, shared with the compiled path (compiled/estimate_kernel.py) so both say exactly the same.
REASON_X_NOT_INCREASING = "profile x values are not strictly increasing"
REASON_CORNERS_NOT_INCREASING = "corners are not in increasing x order"


def reason_too_few_points(n_valid: int, n_corners: int, needed: int) -> str:
    return f"only {n_valid} valid points; {n_corners + 1} faces need at least {needed}"


def reason_steep_segment(k: int, x_mean: float, options: "CornerOptions") -> str:
    return (f"segment {k} at x = {x_mean * 1e3:.1f} mm is steeper than "
            f"{math.degrees(options.max_face_angle):.0f} deg between faces")


def reason_corner_count(n_faces: int, n_corners: int) -> str:
    return f"found {max(n_faces - 1, 0)} corners ({n_faces} faces); the gauge has {n_corners}"


def reason_corner_not_between(i: int, x: float, left_end: float, right_start: float) -> str:
    return (f"corner {i} at x = {x * 1e3:.2f} mm is not between its faces "
            f"({left_end * 1e3:.2f}..{right_start * 1e3:.2f} mm)")


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
    passes = ROBUST_PASSES if options.robust else 1
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


def detect_corners(points: np.ndarray, n_corners: int, options: CornerOptions = CornerOptions()) -> CornerResult:
    """Find exactly n_corners corners, in order of increasing x, or say why not."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2:
        return CornerResult(False, f"profile must be an (N, 2) array, got shape {points.shape}")
    valid = np.isfinite(points).all(axis=1)
    pts = points[valid]
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
