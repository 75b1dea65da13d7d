"""Corner detection on a profile (paper II-D): its options, its result and the words of its refusals.

The detection itself is compiled (compiled/estimate_kernel.py: _detect); estimation/stages.py calls it.
Points far off the median of their neighbours (glints) are dropped first. RDP proposes breakpoints; each
segment between breakpoints loses `trim_fraction` of its points at both ends (edge noise of triangulation)
and gets a line fit of z on x (maximum likelihood for depth noise), optionally with outlier rejection;
adjacent lines intersect in the corners. Spurious breakpoints (from spikes or noise) are removed by
merging nearly collinear neighbours, and near-vertical segments at the ends (the gauge's side walls) are
dropped. If the result is not exactly the gauge's n corners in order, detection fails with a reason: a
guessed correspondence would yield a confidently wrong pose (a face a gap hides entirely: hidden_face.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


ROBUST_PASSES = 4  # fit, reject outliers, refit: converges in 2-3 passes on spiky profiles


@dataclass(frozen=True)
class CornerOptions:
    rdp_epsilon: float = 3e-4  # m; breakpoint tolerance, far above sensor noise, far below face relief
    trim_fraction: float = 0.10  # paper II-D: discard 10 % of each segment at both ends
    min_segment_points: int = 20  # shorter segments are spikes or edge debris, not faces
    min_corner_angle: float = math.radians(5.0)  # rad; neighbours closer in direction are one face
    max_face_angle: float = math.radians(70.0)  # rad from F's x axis; steeper end segments are walls
    max_corner_offset: float = 1e-3  # m; a corner must lie between the two faces it joins (+- this)
    robust_line_fit: bool = True  # reject outliers in each line fit (spikes)
    outlier_threshold: float = 4.0  # in robust standard deviations
    min_outlier_floor: float = 1e-6  # m; never reject residuals below this (noise-free profiles)
    # m; drop points this far off the median of their five neighbours before RDP (glints); 0 keeps every point.
    # Half of rdp_epsilon: a smaller glint cannot make RDP break a face, a larger one is far beyond the noise.
    spike_threshold: float = 1.5e-4
    # m; an x inside a gap that hides a face (hidden_face.py): the corner between the faces either side of it is
    # where their planes cross, exempt from the between and order checks. None: every corner is real.
    virtual_corner_gap: float | None = None


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
    faces_found: int = 0  # when refused for the number of corners: how many faces were found

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


# Failure reasons: the compiled detection's status codes, in words (stages.py).
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
