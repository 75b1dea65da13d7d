"""What the estimator takes and returns: its options, its result, and the words of its refusals.

Below stages.py, hidden_face.py and estimator.py, which all build on it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from ..compiled import codes
from ..model.gauge import Gauge
from ..model.sym3 import largest_eigenvalue
from .corners import ROBUST_PASSES, CornerOptions
from .dense import DenseOptions
from .residuals import PoseSolution

WEIGHTINGS = ("corner_covariance", "uniform")
REFINE_MODELS = ("corners", "dense", "auto")


@dataclass(frozen=True)
class EstimatorOptions:
    corners: CornerOptions = CornerOptions()
    refine: bool = True
    refine_weighting: str = "corner_covariance"  # or "uniform": the paper's plain eq. (15)
    # "corners" (the paper's), "dense": then also fit every point's depth (core/estimation/dense.py), or "auto":
    # dense only where the corner pose's position std exceeds dense_above_sigma, the views whose corners
    # determine them too poorly (the corner model's refusals and wrong poses are all there, and its slow tail:
    # the basin search and the unscented covariance; docs/estimator.md). The default, as the node's: on a view
    # the corners determine well it is the corner model, to the bit
    refine_model: str = "auto"
    dense_above_sigma: float = 2e-4  # m
    noise_std: float = 0.0  # m; 0 = estimate the depth noise from each face fit
    max_reprojection_error: float = 1e-4  # m; reject poses whose corners miss their ridges by more
    # reject a pose whose corner residuals are more than this many times (rms, in their own standard deviations)
    # what the profile's noise explains: a profile that does not match the gauge, at any noise level. A correct
    # pose exceeds 4 with probability below 1e-7 (chi-square, 2n - 6 degrees of freedom); inf turns it off.
    max_residual_ratio: float = 4.0
    footprint_margin: float = 2e-3  # m; mapped corners must lie this close to the gauge's footprint
    max_iterations: int = 30
    basin_search: bool = True  # look for a lower minimum around a poorly determined pose (compiled/search_kernel.py)
    basin_search_min_sigma: float = 2.5e-4  # m; search when the refined position's largest std exceeds this
    # m; reject a pose whose position's largest std exceeds this. Its covariance would still be honest (NEES
    # about 5.4 up to 1 mm), but such a pose is more than 1 mm off a few times in a thousand: the gate trades
    # refused views against wrong poses, and 0.35 mm is where the two meet (docs/estimator.md, "The gate's
    # trade"; `profile_pose robustness --gates` measures it for any gauge). The shipped gauges are near
    # 0.02-0.2 mm at 5 um.
    max_position_sigma: float = 3.5e-4
    # when corner detection finds a corner too few beside a gap, solve the gauge without the face the gap hid
    hidden_faces: bool = True

    def __post_init__(self) -> None:
        if self.refine_weighting not in WEIGHTINGS:
            raise ValueError(f"refine_weighting must be one of {WEIGHTINGS}, got {self.refine_weighting!r}")
        if self.refine_model not in REFINE_MODELS:
            raise ValueError(f"refine_model must be one of {REFINE_MODELS}, got {self.refine_model!r}")

    @cached_property
    def kernel_vector(self) -> np.ndarray:
        """These options packed as the compiled estimator takes them (compiled/codes.py), once per options
        object: every profile needs them."""
        c = self.corners
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
        v[codes.O_NOISE] = self.noise_std
        v[codes.O_SIGFLOOR] = 1e-7  # same floor as CornerResult.covariance
        v[codes.O_WEIGHTED] = 1.0 if self.refine_weighting == "corner_covariance" else 0.0
        v[codes.O_REFINE] = 1.0 if self.refine else 0.0
        v[codes.O_MAXIT] = self.max_iterations
        v[codes.O_MAXREPROJ] = self.max_reprojection_error
        v[codes.O_MARGIN] = self.footprint_margin
        v[codes.O_PASSES] = ROBUST_PASSES
        v[codes.O_SPIKE] = c.spike_threshold
        v[codes.O_MAXRATIO] = self.max_residual_ratio
        v[codes.O_GAP] = np.nan if c.virtual_corner_gap is None else c.virtual_corner_gap
        v[codes.O_SEARCH] = 1.0 if self.basin_search and self.refine else 0.0
        # the thresholds are on the published (calibrated) std; the kernel compares its uncalibrated one
        calibrated = math.sqrt(codes.COVARIANCE_CALIBRATION)
        v[codes.O_SEARCHSIG] = self.basin_search_min_sigma / calibrated
        dense = DenseOptions()
        v[codes.O_DENSE] = ({"corners": codes.DENSE_NEVER, "dense": codes.DENSE_ALWAYS,
                             "auto": codes.DENSE_WHEN_POORLY_DETERMINED}[self.refine_model]
                            if self.refine else codes.DENSE_NEVER)
        v[codes.O_DENSESIG] = self.dense_above_sigma / calibrated
        v[codes.O_DMARGIN] = dense.ridge_margin
        v[codes.O_DTHR] = dense.outlier_threshold
        v[codes.O_DFLOOR] = dense.min_outlier_floor
        v[codes.O_DITER] = dense.iterations
        v.setflags(write=False)
        return v

    @cached_property
    def for_a_partial_view(self) -> "EstimatorOptions":
        """These options for a profile with faces hidden or out of view (hidden_face.py): `auto` fits every
        point to the real gauge there, whatever the corner pose's std. The corners seen then describe a
        reduced gauge, and its linearised covariance is not honest: on the designed gauge with face 1 under a
        gap, NEES mean 11.9 and 16 % beyond chi-square's 99 % point, against 5.9 and 1.2 % dense
        (docs/estimator.md). Made once per options object, which packs its kernel vector once."""
        return self.with_changes(dense_above_sigma=0.0) if self.refine_model == "auto" else self

    def with_changes(self, **changes) -> "EstimatorOptions":
        corner_keys = {k: changes.pop(k) for k in list(changes) if hasattr(CornerOptions, k)}
        return replace(self, corners=replace(self.corners, **corner_keys), **changes)


@dataclass
class PoseEstimate:
    """The pose of F in G (p_G = R p_F + t), or ok=False and why."""

    ok: bool
    reason: str = ""
    R: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    t: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    corners: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    reprojection_error: float = float("nan")  # m, mean |corner residual| (paper eq. 17 as a length)
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))  # ROS order, see docs
    closed_form: PoseSolution | None = None
    refined: bool = False
    iterations: int = 0
    fit_rms: float = float("nan")  # m, rms residual of the face line fits
    timings: dict = field(default_factory=dict)  # seconds per stage
    search_starts: int = 0  # starting poses tried by the basin search (0: the pose was well determined)
    position_sigma: float | None = None  # position_sigma(covariance[:3, :3]) when the compiled path computed it
    hidden_face: int | None = None  # the face a gap hid, or the one end face out of view (hidden_face.py)
    faces_hidden: int = 0  # how many adjacent faces from hidden_face the gap hid (1 or 2; 0: none)
    faces_in_view: tuple[int, int] | None = None  # first, last: when faces beyond the profile's ends were not seen
    background_cut: bool = False  # what the gauge stands on, seen beside it, left out (background.py)


def rejected(estimate: PoseEstimate, reason: str, **changes) -> PoseEstimate:
    """The estimate turned into a rejection: no pose, the corner results kept for diagnosis."""
    return replace(estimate, ok=False, reason=reason, R=np.full((3, 3), np.nan), t=np.full(3, np.nan),
                   covariance=np.full((6, 6), np.nan), position_sigma=None, **changes)


def ros_covariance(rotation: np.ndarray, local: np.ndarray) -> np.ndarray:
    """[delta_F, t] (right perturbation) -> ROS order [t, delta_G] with delta_G = R delta_F."""
    transform = np.zeros((6, 6))
    transform[:3, 3:] = np.eye(3)
    transform[3:, :3] = rotation
    return transform @ local @ transform.T


REASON_NOT_FINITE = "pose is not finite"


def reason_reprojection(error: float, gauge: Gauge, options: EstimatorOptions) -> str:
    return (f"reprojection error {error * 1e6:.1f} um exceeds {options.max_reprojection_error * 1e6:.1f} um "
            f"(profile does not match gauge '{gauge.name}')")


def reason_inconsistent(chi2: float, dof: int, gauge: Gauge, options: EstimatorOptions) -> str:
    return (f"corner residuals {math.sqrt(chi2 / dof):.1f}x what the profile's noise explains (chi-square "
            f"{chi2:.1f} on {dof} degrees of freedom; limit {options.max_residual_ratio:g}x): the profile does not "
            f"match gauge '{gauge.name}'")


def reason_ambiguous(apart: float, best_cost: float, rival_cost: float) -> str:
    return (f"pose ambiguous: two poses {apart * 1e3:.1f} mm apart fit the corners about equally well "
            f"(cost {best_cost:.1f} and {rival_cost:.1f})")


def reason_poorly_determined(sigma: float, options: EstimatorOptions) -> str:
    return (f"pose poorly determined: position std up to {sigma * 1e3:.2f} mm exceeds "
            f"{options.max_position_sigma * 1e3:.2f} mm (a near-degenerate view of the gauge)")


def reason_outside(i: int, x: float, y: float, gauge: Gauge) -> str:
    return (f"corner {i} maps to ({x * 1e3:.1f}, {y * 1e3:.1f}) mm, outside gauge "
            f"'{gauge.name}' ({gauge.width * 1e3:.0f} x {gauge.length * 1e3:.0f} mm)")


def position_sigma(position_covariance: np.ndarray) -> float:
    """Largest standard deviation (m) of a 3x3 position covariance (NaN if it is not finite); every
    estimate needs it (sym3.py: closed form, no LAPACK)."""
    (a, b, c), (_, d, e), (_, _, f) = position_covariance.tolist()
    if not all(map(math.isfinite, (a, b, c, d, e, f))):
        return float("nan")
    try:
        return math.sqrt(max(largest_eigenvalue(a, b, c, d, e, f), 0.0))
    except OverflowError:  # entries near the float limit (a received covariance): no precision at all
        return math.inf
