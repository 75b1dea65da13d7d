"""estimate_pose: profile -> corners -> closed form -> refinement -> checks.

Every failure returns ok=False with a reason instead of raising: the node publishes nothing for a
rejected profile and reports the reason in diagnostics. A pose is only returned when the corners fit
the gauge (reprojection error under a bound, corners inside the gauge's footprint).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from functools import lru_cache
from dataclasses import dataclass, field, replace

import numpy as np

from .corners import CornerOptions, detect_corners
from .gauge import Gauge
from .rotation import rotation_angle, so3_log
from .sym3 import largest_eigenvalue
from .solver import (PoseSolution, Refinement, SolverError, closed_form, corner_residuals, four_ridge_candidates,
                     refine, search_minima, solution_cost)

WEIGHTINGS = ("corner_covariance", "uniform")
REFINE_MODELS = ("corners", "dense")


@dataclass(frozen=True)
class EstimatorOptions:
    corners: CornerOptions = CornerOptions()
    refine: bool = True
    weighting: str = "corner_covariance"  # or "uniform": the paper's plain eq. (15)
    refine_model: str = "corners"  # or "dense": then also fit every point's depth (core/dense.py)
    noise_std: float = 0.0  # m; 0 = estimate the depth noise from each face fit
    max_reprojection_error: float = 1e-4  # m; reject poses whose corners miss their ridges by more
    footprint_margin: float = 2e-3  # m; mapped corners must lie this close to the gauge's footprint
    max_iterations: int = 30
    search: bool = True  # look for a lower minimum around a poorly determined pose (solver.search_minima)
    search_min_sigma: float = 2.5e-4  # m; search when the refined position's largest std exceeds this
    # m; reject a pose whose position's largest std exceeds this: the profile determines it so poorly that its
    # linearised covariance understates the error (docs/estimator.md, "Covariance"), so nothing downstream
    # could weight it right. The shipped gauges are near 0.02-0.2 mm at 5 um noise.
    max_position_sigma: float = 5e-4

    def __post_init__(self) -> None:
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        if self.refine_model not in REFINE_MODELS:
            raise ValueError(f"refine_model must be one of {REFINE_MODELS}, got {self.refine_model!r}")

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


def reason_poorly_determined(sigma: float, options: EstimatorOptions) -> str:
    return (f"pose poorly determined: position std up to {sigma * 1e3:.2f} mm exceeds "
            f"{options.max_position_sigma * 1e3:.2f} mm (a near-degenerate view of the gauge)")


def reason_outside(i: int, x: float, y: float, gauge: Gauge) -> str:
    return (f"corner {i} maps to ({x * 1e3:.1f}, {y * 1e3:.1f}) mm, outside gauge "
            f"'{gauge.name}' ({gauge.width * 1e3:.0f} x {gauge.length * 1e3:.0f} mm)")


def _check(gauge: Gauge, solution: PoseSolution, corners: np.ndarray, options: EstimatorOptions) -> str:
    if not (np.all(np.isfinite(solution.rotation)) and np.all(np.isfinite(solution.translation))):
        return REASON_NOT_FINITE
    error = solution.reprojection_error
    if not error <= options.max_reprojection_error:
        return reason_reprojection(error, gauge, options)
    mapped = corners[:, :1] * solution.rotation[:, 0] + corners[:, 1:] * solution.rotation[:, 2] + solution.translation
    half = np.array([gauge.width, gauge.length]) / 2 + options.footprint_margin
    outside = np.nonzero(np.any(np.abs(mapped[:, :2]) > half, axis=1))[0]
    if len(outside):
        i = int(outside[0])
        return reason_outside(i, mapped[i, 0], mapped[i, 1], gauge)
    return ""


def estimate_pose(points: np.ndarray, gauge: Gauge, options: EstimatorOptions | None = None, *,
                  backend: str = "fast", **overrides) -> PoseEstimate:
    """Estimate the profiler pose from one profile ((N, 2) [x, z] in metres, NaN = invalid).

    backend "fast" is the compiled path (core/fast.py) used at run time; "numpy" is the readable
    reference it is tested against. Keyword overrides are any EstimatorOptions or CornerOptions
    field, e.g. refine=False.
    """
    options = options or EstimatorOptions()
    if overrides:
        options = options.with_changes(**overrides)
    if backend == "fast":
        from .fast_wrapper import estimate_fast

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
    if compiled:
        from .fast_wrapper import refine_dense_compiled as refine_dense
    else:
        from .dense import refine_dense

    start = time.perf_counter()
    try:
        dense = refine_dense(gauge, points, estimate.R, estimate.t, options.noise_std)
    except (np.linalg.LinAlgError, ValueError) as exc:
        return _rejected(estimate, f"dense refinement: {exc}")
    solution = PoseSolution(dense.rotation, dense.translation,
                            corner_residuals(gauge, estimate.corners, dense.rotation, dense.translation))
    timings = dict(estimate.timings, dense_refinement=time.perf_counter() - start)
    reason = _check(gauge, solution, estimate.corners, options)
    if reason:
        return _rejected(estimate, f"dense refinement: {reason}", timings=timings)
    return replace(estimate, R=dense.rotation, t=dense.translation, reprojection_error=solution.reprojection_error,
                   covariance=ros_covariance(dense.rotation, dense.covariance_local), timings=timings,
                   position_sigma=None)


def position_sigma(position_covariance: np.ndarray) -> float:
    """Largest standard deviation (m) of a 3x3 position covariance (NaN if it is not finite); every
    estimate needs it (sym3.py: closed form, no LAPACK)."""
    (a, b, c), (_, d, e), (_, _, f) = position_covariance.tolist()
    if not all(map(math.isfinite, (a, b, c, d, e, f))):
        return float("nan")
    return math.sqrt(max(largest_eigenvalue(a, b, c, d, e, f), 0.0))


def needs_search(result: Refinement, cost: float, n_corners: int, weighted: bool, options: EstimatorOptions) -> bool:
    """Search when the pose is poorly determined, or (weighted) when its cost is implausible for the noise."""
    if not (options.search and options.refine):
        return False
    if position_sigma(result.covariance[3:, 3:]) > options.search_min_sigma:
        return True
    return weighted and cost > _implausible_cost(max(2 * n_corners - 6, 1))


@lru_cache(maxsize=None)
def _implausible_cost(dof: int) -> float:
    """The chi-square value a correct minimum exceeds with probability 1e-4."""
    from scipy.special import gammainccinv

    return float(2.0 * gammainccinv(dof / 2.0, 1e-4))


@dataclass(frozen=True)
class Stages:
    """The corner detection and refinement estimate_plain() runs: numpy (the reference) by default; the
    compiled path hands its n = 4 and basin-search cases over with its kernels (fast_wrapper.COMPILED)."""

    detect: Callable = detect_corners
    refine: Callable = refine


NUMPY = Stages()


def estimate_plain(points: np.ndarray, gauge: Gauge, options: EstimatorOptions, stages: Stages = NUMPY
                   ) -> PoseEstimate:
    """The numpy reference implementation, stage by stage, with per-stage timings."""
    timings = {}
    start = time.perf_counter()
    found = stages.detect(points, gauge.n_ridges, options.corners)
    timings["corner_detection"] = time.perf_counter() - start
    if not found.ok:
        return PoseEstimate(False, f"corner detection: {found.reason}", timings=timings)
    corners = found.corners
    start = time.perf_counter()
    try:
        starts = four_ridge_candidates(gauge, corners) if gauge.n_ridges == 4 else [closed_form(gauge, corners)]
    except (SolverError, np.linalg.LinAlgError) as exc:
        return PoseEstimate(False, f"closed form: {exc}", corners=corners, timings=timings)
    timings["closed_form"] = time.perf_counter() - start

    corner_cov = found.covariance(options.noise_std or None)
    weighted = options.weighting == "corner_covariance"
    start = time.perf_counter()
    minima = []
    for candidate in starts:
        try:
            attempt = stages.refine(gauge, corners, candidate, corner_cov, weighted,
                                    options.max_iterations if options.refine or len(starts) > 1 else 0)
        except np.linalg.LinAlgError as exc:
            if len(starts) == 1:
                return PoseEstimate(False, f"refinement: {exc}", corners=corners, closed_form=candidate,
                                    timings=timings)
            continue
        minima.append((solution_cost(gauge, attempt.solution, corner_cov, weighted), candidate, attempt))
    if not minima:
        return PoseEstimate(False, "refinement: no starting pose converged", corners=corners, timings=timings)
    cost, initial, result = min(minima, key=lambda m: m[0])
    rival = _rival_minimum(minima, result, cost) if weighted and options.refine and len(minima) > 1 else None
    if rival is not None:
        return PoseEstimate(False, reason_ambiguous(rival, result, cost), corners=corners, closed_form=initial,
                            timings=timings)
    search_starts = 0
    if needs_search(result, cost, len(corners), weighted, options):
        search_start = time.perf_counter()
        result, search_starts = search_minima(gauge, corners, result, corner_cov, weighted, options.max_iterations,
                                              stages.refine)
        timings["search"] = time.perf_counter() - search_start
    solution, refined, iterations = initial, False, 0
    if options.refine:
        solution, refined, iterations = result.solution, True, result.iterations
        timings["refinement"] = time.perf_counter() - start
    reason = _check(gauge, solution, corners, options)
    estimate = PoseEstimate(
        ok=not reason, reason=reason, corners=corners, reprojection_error=solution.reprojection_error,
        closed_form=initial, refined=refined, iterations=iterations, fit_rms=found.fit_rms, timings=timings,
        search_starts=search_starts,
    )
    if not reason:
        estimate.R, estimate.t = solution.rotation, solution.translation
        estimate.covariance = ros_covariance(solution.rotation, result.covariance)
    return estimate


AMBIGUOUS_COST = 9.0  # a rival minimum this close in cost (chi-square) is as plausible as the best
AMBIGUOUS_DISTANCE = 5.0  # standard deviations (Mahalanobis, the best minimum's covariance) apart


def _rival_minimum(minima: list, best: Refinement, best_cost: float) -> tuple[float, Refinement] | None:
    """Another minimum that fits the corners about as well as the best one but lies far from it: with four
    ridges (two redundant equations) the corners can fit two poses centimetres apart, and the lower cost is
    then a coin toss (seen in the study: 54 mm off, cost 1.6 against 4.4 at the true pose)."""
    information = np.linalg.inv(best.covariance)
    for cost, _, other in minima:
        d = np.concatenate([so3_log(best.solution.rotation.T @ other.solution.rotation),
                            other.solution.translation - best.solution.translation])
        if cost - best_cost < AMBIGUOUS_COST and d @ information @ d > AMBIGUOUS_DISTANCE ** 2:
            return cost, other
    return None


def reason_ambiguous(rival: tuple[float, Refinement], best: Refinement, best_cost: float) -> str:
    cost, other = rival
    apart = np.linalg.norm(other.solution.translation - best.solution.translation)
    return (f"pose ambiguous: two poses {apart * 1e3:.1f} mm apart fit the corners about equally well "
            f"(cost {best_cost:.1f} and {cost:.1f})")


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

