"""Python side of the compiled estimator: kernel choice, options packing, status codes -> reasons, warm-up.

The kernel is the prebuilt extension (aot.py) when it can be built on this machine, else numba's JIT of
the same source (fast.py). PROFILE_POSE_KERNEL=aot|jit|auto (default auto) forces a choice.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from types import SimpleNamespace
from typing import TypeVar

import numpy as np

from . import aot
from . import fast_codes as fast
from .corners import (REASON_CORNERS_NOT_INCREASING, ROBUST_PASSES, REASON_X_NOT_INCREASING, CornerOptions,
                      CornerResult, LineFit, reason_corner_count, reason_corner_not_between, reason_steep_segment,
                      reason_too_few_points)
from .estimator import (REASON_NOT_FINITE, EstimatorOptions, PoseEstimate, Stages, estimate_plain,
                        reason_outside, reason_reprojection)
from .dense import DenseOptions, DenseResult
from .gauge import Gauge
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
    v = np.empty(fast.N_OPTIONS)
    v[fast.O_EPS] = c.rdp_epsilon
    v[fast.O_TRIM] = c.trim_fraction
    v[fast.O_MINSEG] = c.min_segment_points
    v[fast.O_MINANGLE] = c.min_corner_angle
    v[fast.O_MAXFACE] = c.max_face_angle
    v[fast.O_MAXOFF] = c.max_corner_offset
    v[fast.O_ROBUST] = 1.0 if c.robust else 0.0
    v[fast.O_THR] = c.outlier_threshold
    v[fast.O_FLOOR] = c.min_outlier_floor
    v[fast.O_NOISE] = options.noise_std
    v[fast.O_SIGFLOOR] = 1e-7  # same floor as CornerResult.covariance
    v[fast.O_WEIGHTED] = 1.0 if options.weighting == "corner_covariance" else 0.0
    v[fast.O_REFINE] = 1.0 if options.refine else 0.0
    v[fast.O_MAXIT] = options.max_iterations
    v[fast.O_MAXREPROJ] = options.max_reprojection_error
    v[fast.O_MARGIN] = options.footprint_margin
    v[fast.O_PASSES] = ROBUST_PASSES
    v.setflags(write=False)
    return v


def _detection_reason(status: int, info: np.ndarray, n: int, options: CornerOptions) -> str | None:
    detection = {
        fast.TOO_FEW_POINTS: lambda: reason_too_few_points(int(info[0]), n, int(info[1])),
        fast.X_NOT_INCREASING: lambda: REASON_X_NOT_INCREASING,
        fast.STEEP_SEGMENT: lambda: reason_steep_segment(int(info[0]), info[1], options),
        fast.WRONG_CORNER_COUNT: lambda: reason_corner_count(int(info[1]), n),
        fast.CORNER_NOT_BETWEEN: lambda: reason_corner_not_between(int(info[0]), info[1], info[2], info[3]),
        fast.CORNERS_NOT_INCREASING: lambda: REASON_CORNERS_NOT_INCREASING,
    }
    return detection[status]() if status in detection else None


def _reason(status: int, info: np.ndarray, gauge: Gauge, options: EstimatorOptions, error: float) -> str:
    n = gauge.n_ridges
    detection = _detection_reason(status, info, n, options.corners)
    if detection is not None:
        return f"corner detection: {detection}"
    if status == fast.CF_RANK:
        return f"closed form: {reason_cf_rank(n, int(info[0]))}"
    if status == fast.CF_DEGENERATE:
        return f"closed form: {REASON_CF_DEGENERATE}"
    if status == fast.SINGULAR:
        return "refinement: Singular matrix"
    if status == fast.NOT_FINITE:
        return REASON_NOT_FINITE
    if status == fast.REPROJECTION:
        return reason_reprojection(error, gauge, options)
    if status == fast.OUTSIDE_FOOTPRINT:
        return reason_outside(int(info[0]), info[1], info[2], gauge)
    return f"internal status {status}"


_kernels = None
kernel_name = ""


def _loaded():
    """The compiled functions in use (estimate, detect, refine_pose, decode_xz, refine_dense): loaded (and,
    the first time on a machine, built) on first need."""
    global _kernels, kernel_name
    if _kernels is None:
        choice = os.environ.get("PROFILE_POSE_KERNEL", "auto")
        module = aot.load() if choice in ("auto", "aot") else None
        if module is not None:
            _kernels, kernel_name = module, "prebuilt (aot)"
        elif choice == "aot":
            raise RuntimeError("PROFILE_POSE_KERNEL=aot but the prebuilt estimator could not be built here")
        else:
            from . import fast as jit
            from .fast_dense import refine_dense as dense
            from .fast_profile import decode_xz

            _kernels = SimpleNamespace(estimate=jit.estimate, detect=jit.detect, refine_pose=jit.refine_pose,
                                       decode_xz=decode_xz, refine_dense=dense)
            kernel_name = "numba jit"
    return _kernels


def will_compile() -> bool:
    """Whether the kernels' first use in a process will compile them (a minute or more): the prebuilt
    kernel is wanted and this machine has no build of these sources yet."""
    return os.environ.get("PROFILE_POSE_KERNEL", "auto") != "jit" and not aot.is_current()


def kernel():
    """The compiled estimate() in use."""
    return _loaded().estimate


def decode_xz(table: np.ndarray, x_col: int, y_col: int, z_col: int, out: np.ndarray) -> tuple[int, int]:
    """fast_profile.decode_xz through the kernel in use (profile_cloud.decode_profile calls it)."""
    return _loaded().decode_xz(table, x_col, y_col, z_col, out)


def detect_corners_compiled(points: np.ndarray, n_corners: int, options: CornerOptions = CornerOptions()
                            ) -> CornerResult:
    """corners.detect_corners() through the compiled kernel: the same corners, face fits and reasons."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        return CornerResult(False, f"profile must be an (N, 2) array, got shape {points.shape}")
    corners, jac = np.empty((n_corners, 2)), np.empty((2 * n_corners, 2 * (n_corners + 1)))
    lines, info = np.empty((n_corners + 1, 10)), np.zeros(4)
    status, _, fit_rms = _loaded().detect(points, n_corners, option_vector(_corner_only(options)), corners, jac,
                                          np.empty(2 * (n_corners + 1)), info, lines)
    if status != fast.OK:
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
    status, iterations = _loaded().refine_pose(
        gauge.q, gauge.u, gauge.w, np.ascontiguousarray(corners, dtype=np.float64),
        np.ascontiguousarray(start.rotation, dtype=np.float64),
        np.ascontiguousarray(start.translation, dtype=np.float64),
        np.ascontiguousarray(corner_covariance, dtype=np.float64), bool(weighted), int(max_iterations), bool(polish),
        rotation, translation, residuals, covariance)
    if status != fast.OK:
        raise np.linalg.LinAlgError("Singular matrix")
    return Refinement(PoseSolution(rotation, translation, residuals.reshape(-1, 2)), covariance, int(iterations))


def refine_dense_compiled(gauge: Gauge, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                          noise_std: float = 0.0, options: DenseOptions = DenseOptions()) -> DenseResult:
    """dense.refine_dense() through the compiled kernel (same steps, solved by Cholesky; within 1e-9)."""
    normals, offsets, ridge_q, ridge_u = _dense_gauge(gauge)
    rot_out, t_out, cov_out = np.empty((3, 3)), np.empty(3), np.empty((6, 6))
    status, used, sigma = _loaded().refine_dense(
        np.ascontiguousarray(points, dtype=np.float64), normals, offsets, ridge_q, ridge_u, gauge.width, gauge.length,
        np.array(rotation, dtype=np.float64), np.array(translation, dtype=np.float64), float(noise_std),
        options.ridge_margin, options.outlier_threshold, options.min_outlier_floor, options.iterations, rot_out, t_out,
        cov_out)
    if status != fast.OK:
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
        status, iterations, fit_rms, error, cf_error, sigma = kernel()(
            points, gauge.q, gauge.u, gauge.w, gauge.width, gauge.length, option_vector(options), corners, rot, t,
            cov, cf_rot, cf_t, cf_res, res, info)
    except np.linalg.LinAlgError as exc:
        return PoseEstimate(False, f"refinement: {exc}", timings={"total": time.perf_counter() - start})
    timings = {"total": time.perf_counter() - start}
    if status in (fast.TOO_FEW_POINTS, fast.X_NOT_INCREASING, fast.STEEP_SEGMENT, fast.WRONG_CORNER_COUNT,
                  fast.CORNER_NOT_BETWEEN, fast.CORNERS_NOT_INCREASING):
        return PoseEstimate(False, _reason(status, info, gauge, options, error), timings=timings)
    if status in (fast.CF_RANK, fast.CF_DEGENERATE):
        return PoseEstimate(False, _reason(status, info, gauge, options, error), corners=corners, timings=timings)
    ok = status == fast.OK
    if options.search and options.refine and (status in (fast.REPROJECTION, fast.OUTSIDE_FOOTPRINT) or (
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
    from .poses import sample_pose
    from .render import render_profile

    start = time.perf_counter()
    options = options or EstimatorOptions()
    rotation, translation = sample_pose(gauge, np.random.default_rng(0))
    profile = render_profile(gauge, rotation, translation)
    estimate_fast(profile, gauge, options)
    estimate_fast(np.full((10, 2), np.nan), gauge, options)  # a failure path too
    estimate_plain(profile, gauge, options, COMPILED)  # the kernels of the n = 4 starts and the basin search
    return time.perf_counter() - start
