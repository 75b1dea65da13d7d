"""Cramér-Rao lower bounds of the pose for Gaussian depth noise, at a true pose.

Two measurement models:
- corner model: the estimator's own — the n corners from the face line fits, with their propagated
  covariance; the bound is (Jᵀ Σ_r⁻¹ J)⁻¹ with J the corner residuals' Jacobian at the truth;
- dense model: every lit profile point's depth z_i(θ), i.i.d. noise σ; the bound is σ² (Gᵀ G)⁻¹ with
  G = dz/dθ. This is what any estimator using the whole profile could at best reach.
Both are returned in the ROS order of PoseEstimate.covariance: [t (3), rotation in G (3)].
Gauge design should aim at these bounds, not at the reprojection error (docs/estimator.md).
"""
from __future__ import annotations

import numpy as np

from ..estimation.corners import CornerOptions, detect_corners
from ..estimation.result import ros_covariance
from ..model.gauge import Gauge
from ..model.render import DEFAULT_PROFILER, ProfilerModel, render_profile, shadow_mask, trace_depth
from ..model.rotation import so3_exp
from ..estimation.solver import residual_covariance, residual_jacobian


def corner_crlb(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, noise_std: float,
                profiler: ProfilerModel = DEFAULT_PROFILER, options: CornerOptions = CornerOptions(),
                trace=None, detect=detect_corners) -> np.ndarray:
    """6x6 bound for the corner model at the true pose (raises ValueError if the corners are not all seen).
    `trace` and `detect`: the ray trace and the corner detection to use (the compiled ones for studies)."""
    found = detect(render_profile(gauge, rotation, translation, profiler=profiler, trace=trace),
                   gauge.n_ridges, options)
    if not found.ok:
        raise ValueError(f"corners not detectable at this pose: {found.reason}")
    corner_cov = found.covariance(noise_std)
    jac = residual_jacobian(gauge, found.corners, rotation)
    information = jac.T @ np.linalg.solve(residual_covariance(gauge, rotation, corner_cov), jac)
    return ros_covariance(rotation, np.linalg.inv(information))


def depth_jacobian(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray,
                   profiler: ProfilerModel = DEFAULT_PROFILER, step: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """(G, lit): dz_i/d[δ_F, t] for the lit points (central differences), and which points are lit.

    Points whose face changes within ±step (at a corner or an edge) are left out: there the depth is
    not differentiable.
    """
    x = profiler.x
    z0 = trace_depth(gauge, rotation, translation, x)
    lit = np.isfinite(z0) & profiler.in_range(x, z0)
    if profiler.occlusion:
        lit &= ~shadow_mask(x, np.where(lit, z0, np.nan), profiler.emitter_z)
    columns = []
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = step
        plus = trace_depth(gauge, rotation @ so3_exp(delta[:3]), translation + delta[3:], x)
        minus = trace_depth(gauge, rotation @ so3_exp(-delta[:3]), translation - delta[3:], x)
        forward, backward = (plus - z0) / step, (z0 - minus) / step
        smooth = np.abs(forward - backward) <= 1e-3 * (1.0 + np.abs(forward))
        lit &= smooth & np.isfinite(plus) & np.isfinite(minus)
        columns.append((plus - minus) / (2 * step))
    return np.column_stack(columns)[lit], lit


def dense_crlb(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, noise_std: float,
               profiler: ProfilerModel = DEFAULT_PROFILER, trace=None) -> np.ndarray:
    """6x6 bound for an estimator using every lit top-face point's depth (i.i.d. Gaussian noise on z).

    Uses the analytic depth Jacobian of dense.py (one render); depth_jacobian() is the finite-difference
    check of it, which also counts side-wall points.
    """
    from ..estimation.dense import DenseOptions, depth_model, select_points

    points = render_profile(gauge, rotation, translation, profiler=profiler, trace=trace)
    points = points[np.isfinite(points).all(axis=1)]
    index, face = select_points(gauge, points, rotation, translation, DenseOptions(ridge_margin=1e-6))
    _, g = depth_model(gauge, points[index, 0], face, rotation, translation)
    return ros_covariance(rotation, noise_std ** 2 * np.linalg.inv(g.T @ g))


def position_rotation_rms(covariance: np.ndarray) -> tuple[float, float]:
    """(rms position error m, rms rotation error rad) implied by a 6x6 ROS-order covariance."""
    return float(np.sqrt(np.trace(covariance[:3, :3]))), float(np.sqrt(np.trace(covariance[3:, 3:])))
