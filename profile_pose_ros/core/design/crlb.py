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

from ..estimation.corners import CornerOptions
from ..estimation.result import ros_covariance
from ..estimation.residuals import residual_covariance, residual_jacobian
from ..estimation.stages import detect_corners
from ..model.gauge import Gauge
from ..model.render import DEFAULT_PROFILER, ProfilerModel, render_profile, shadow_mask, trace_depth
from ..model.rotation import so3_exp

E1 = np.array([1.0, 0.0, 0.0])
E3 = np.array([0.0, 0.0, 1.0])


def select_points(gauge: Gauge, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                  ridge_margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the points the dense model can use and their faces, from where they land in G (the
    selection compiled/dense_kernel.py makes at every step, here once at the true pose)."""
    mapped = translation + points[:, :1] * rotation[:, 0] + points[:, 1:] * rotation[:, 2]
    ridges = gauge.ridge_x(mapped[:, 1])
    face = np.sum(ridges < mapped[:, :1], axis=1)
    edges = np.column_stack([np.full(len(mapped), -gauge.width / 2), ridges, np.full(len(mapped), gauge.width / 2)])
    clearance = np.min(np.abs(edges - mapped[:, :1]), axis=1)
    inside = (np.abs(mapped[:, 0]) < gauge.width / 2) & (np.abs(mapped[:, 1]) < gauge.length / 2)
    usable = inside & (clearance > ridge_margin)
    return np.nonzero(usable)[0], face[usable]


def depth_model(gauge: Gauge, x: np.ndarray, face: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """Predicted depths and their Jacobian w.r.t. [delta_F (right perturbation), t]."""
    n = gauge.normals[face]
    d = gauge.offsets[face]
    a = n @ rotation[:, 0]
    b = n @ rotation[:, 2]
    c = d - n @ translation
    z = (c - x * a) / b
    m = n @ rotation  # normals in F (rows)
    da = -np.cross(m, E1)  # d(n . R e1)/d delta = -(m x e1)
    db = -np.cross(m, E3)
    jac = np.empty((len(x), 6))
    jac[:, :3] = (-x[:, None] * da) / b[:, None] - (z / b)[:, None] * db
    jac[:, 3:] = -n / b[:, None]
    return z, jac


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

    points = render_profile(gauge, rotation, translation, profiler=profiler, trace=trace)
    return dense_crlb_of_points(gauge, points, rotation, translation, noise_std)


def dense_crlb_of_points(gauge: Gauge, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                         noise_std: float) -> np.ndarray:
    """The dense bound for the points a profile actually has (NaN rows: none there, as in a gap): how well
    any estimator could place a view some of whose points are missing."""
    points = points[np.isfinite(points).all(axis=1)]
    index, face = select_points(gauge, points, rotation, translation, ridge_margin=1e-6)
    _, g = depth_model(gauge, points[index, 0], face, rotation, translation)
    return ros_covariance(rotation, noise_std ** 2 * np.linalg.inv(g.T @ g))


def position_rotation_rms(covariance: np.ndarray) -> tuple[float, float]:
    """(rms position error m, rms rotation error rad) implied by a 6x6 ROS-order covariance."""
    return float(np.sqrt(np.trace(covariance[:3, :3]))), float(np.sqrt(np.trace(covariance[3:, 3:])))
