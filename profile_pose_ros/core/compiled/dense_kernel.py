"""The dense refinement compiled (estimation/dense.py says what it fits): point selection, robust cut and
Gauss-Newton steps in one call, fast enough for the loop beside the other nodes on two cores (written in
numpy it was not: docs/design_notes.md). Steps are solved through the normal equations (Cholesky):
no LAPACK in the hot path.
"""
from __future__ import annotations

import math

import numpy as np

from .codes import JIT, OK, SINGULAR
from .estimate_kernel import _cholesky, _cholesky_solve, _matmul3, _so3_exp, _spd_inverse
from .kernel import kernel

STEP_TOLERANCE = 1e-13  # as dense.refine_dense: stop once no step component exceeds it


@kernel(**JIT)
def _inliers(points, normals, offsets, ridge_q, ridge_u, width, length, rot, t, margin, threshold, floor,
             jac, residual):
    """Fill the first rows of jac (N, 6) and residual (N) with the usable, inlying points (dense.py's
    select_points, depth_model and robust cut); returns how many. What depends only on the face and the
    pose (the normal in F, the depth model's coefficients) is computed once per face, not per point."""
    n_ridges = ridge_u.shape[0]
    n_faces = n_ridges + 1
    # Per face, with the face's normal n and m = R^T n (the normal in F): a = m0, 1 / b = 1 / m2,
    # c = offset - n . t, m1 / b, then -n / b (the translation columns)
    coef = np.empty((n_faces, 7))
    for f in range(n_faces):
        n0, n1, n2 = normals[f, 0], normals[f, 1], normals[f, 2]
        inv_b = 1.0 / (n0 * rot[0, 2] + n1 * rot[1, 2] + n2 * rot[2, 2])
        coef[f, 0] = n0 * rot[0, 0] + n1 * rot[1, 0] + n2 * rot[2, 0]
        coef[f, 1] = inv_b
        coef[f, 2] = offsets[f] - (n0 * t[0] + n1 * t[1] + n2 * t[2])
        coef[f, 3] = (n0 * rot[0, 1] + n1 * rot[1, 1] + n2 * rot[2, 1]) * inv_b
        coef[f, 4] = -n0 * inv_b
        coef[f, 5] = -n1 * inv_b
        coef[f, 6] = -n2 * inv_b
    half_w = width / 2
    half_l = length / 2
    count = 0
    for i in range(points.shape[0]):
        x, z = points[i, 0], points[i, 1]
        mx = t[0] + x * rot[0, 0] + z * rot[0, 2]
        my = t[1] + x * rot[1, 0] + z * rot[1, 2]
        if not (abs(mx) < half_w and abs(my) < half_l):
            continue
        face = 0
        clearance = min(abs(mx + half_w), abs(half_w - mx))
        for k in range(n_ridges):
            ridge = ridge_q[k] + ridge_u[k] * my
            if ridge < mx:
                face += 1
            clearance = min(clearance, abs(ridge - mx))
        if not clearance > margin:
            continue
        a, inv_b, m1_b = coef[face, 0], coef[face, 1], coef[face, 3]
        predicted = (coef[face, 2] - x * a) * inv_b  # depth where the ray x meets the face: (c - x a) / b
        # d a / d delta = -(m x e1) = (0, -m2, m1); d b / d delta = -(m x e3) = (-m1, m0, 0), and
        # d predicted = (-x d a - predicted d b) / b
        jac[count, 0] = predicted * m1_b
        jac[count, 1] = x - predicted * inv_b * a
        jac[count, 2] = -x * m1_b
        jac[count, 3] = coef[face, 4]
        jac[count, 4] = coef[face, 5]
        jac[count, 5] = coef[face, 6]
        residual[count] = z - predicted
        count += 1
    if count == 0:
        return 0
    scale = 1.4826 * np.median(np.abs(residual[:count]))
    limit = max(threshold * scale, floor)
    kept = 0
    for i in range(count):
        if abs(residual[i]) <= limit:
            for a in range(6):  # element by element: a row slice per point cost more than the copy
                jac[kept, a] = jac[i, a]
            residual[kept] = residual[i]
            kept += 1
    return kept


@kernel(**JIT)
def _normal(jac, residual, count, hessian, gradient):
    """hessian = J^T J and gradient = J^T r over the first `count` rows. The 27 sums live in locals (in
    registers): accumulated in the output arrays, each was a chain through memory at every point."""
    h00 = h01 = h02 = h03 = h04 = h05 = h11 = h12 = h13 = h14 = h15 = 0.0
    h22 = h23 = h24 = h25 = h33 = h34 = h35 = h44 = h45 = h55 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    for i in range(count):
        j0, j1, j2, j3, j4, j5 = jac[i, 0], jac[i, 1], jac[i, 2], jac[i, 3], jac[i, 4], jac[i, 5]
        r = residual[i]
        h00 += j0 * j0; h01 += j0 * j1; h02 += j0 * j2; h03 += j0 * j3; h04 += j0 * j4; h05 += j0 * j5
        h11 += j1 * j1; h12 += j1 * j2; h13 += j1 * j3; h14 += j1 * j4; h15 += j1 * j5
        h22 += j2 * j2; h23 += j2 * j3; h24 += j2 * j4; h25 += j2 * j5
        h33 += j3 * j3; h34 += j3 * j4; h35 += j3 * j5
        h44 += j4 * j4; h45 += j4 * j5
        h55 += j5 * j5
        g0 += j0 * r; g1 += j1 * r; g2 += j2 * r; g3 += j3 * r; g4 += j4 * r; g5 += j5 * r
    sums = (h00, h01, h02, h03, h04, h05, h11, h12, h13, h14, h15, h22, h23, h24, h25, h33, h34, h35, h44, h45, h55)
    k = 0
    for a in range(6):
        for b in range(a, 6):
            hessian[a, b] = sums[k]
            hessian[b, a] = sums[k]
            k += 1
    gradient[0], gradient[1], gradient[2], gradient[3], gradient[4], gradient[5] = g0, g1, g2, g3, g4, g5


@kernel(**JIT)
def refine_dense(points, normals, offsets, ridge_q, ridge_u, width, length, rot, t, noise_std, margin, threshold,
                 floor, iterations, rot_out, t_out, cov_out):
    """dense.refine_dense: returns (status, points used, sigma); rot_out, t_out, cov_out (over [delta_F, t])."""
    finite = 0
    for i in range(points.shape[0]):
        if math.isfinite(points[i, 0]) and math.isfinite(points[i, 1]):
            finite += 1
    pts = np.empty((finite, 2))
    k = 0
    for i in range(points.shape[0]):
        if math.isfinite(points[i, 0]) and math.isfinite(points[i, 1]):
            pts[k, 0], pts[k, 1] = points[i, 0], points[i, 1]
            k += 1
    jac, residual = np.empty((finite, 6)), np.empty(finite)
    hessian, gradient, low, step = np.empty((6, 6)), np.empty(6), np.empty((6, 6)), np.empty(6)
    turn, rotated = np.empty((3, 3)), np.empty((3, 3))
    rot_out[:, :] = rot
    t_out[:] = t
    for _ in range(iterations):
        count = _inliers(pts, normals, offsets, ridge_q, ridge_u, width, length, rot_out, t_out, margin, threshold,
                         floor, jac, residual)
        _normal(jac, residual, count, hessian, gradient)
        if count < 6 or not _cholesky(hessian, low):
            return SINGULAR, count, 0.0
        _cholesky_solve(low, gradient, step)
        _so3_exp(step[:3], turn)
        _matmul3(rot_out, turn, rotated)
        rot_out[:, :] = rotated
        for a in range(3):
            t_out[a] += step[3 + a]
        largest = 0.0
        for a in range(6):
            largest = max(largest, abs(step[a]))
        if largest < STEP_TOLERANCE:
            break
    count = _inliers(pts, normals, offsets, ridge_q, ridge_u, width, length, rot_out, t_out, margin, threshold,
                     floor, jac, residual)
    _normal(jac, residual, count, hessian, gradient)
    sigma = noise_std
    if sigma == 0.0:
        sigma = math.sqrt(np.sum(residual[:count] ** 2) / max(1, count - 6))
    if count < 6 or not _spd_inverse(hessian, cov_out):
        return SINGULAR, count, sigma
    for a in range(6):
        for b in range(6):
            cov_out[a, b] *= sigma * sigma
    return OK, count, sigma
