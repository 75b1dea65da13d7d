"""The dense refinement compiled (estimation/dense.py says what it fits): point selection, robust cut and
Gauss-Newton steps in one call. Steps are solved through the normal equations (Cholesky): no LAPACK in the
hot path.

On a face the predicted depth is linear in the point's x, and so is every column of the Jacobian, so
J^T J and J^T r follow from five sums per face (count, x, x^2, r, x r) instead of 27 products per point;
the points themselves are only classified (face, residual) and cut.
"""
from __future__ import annotations

import math

import numpy as np

from .codes import JIT, OK, SINGULAR
from .estimate_kernel import (CURVED_ABOVE, _add_curvature_term, _cholesky, _cholesky_solve, _matmul3, _moved_pose,
                              _so3_exp, _spd_inverse, _weakest_direction)
from .kernel import kernel

STEP_TOLERANCE = 1e-13  # stop once no step component exceeds it (m, rad): converged to rounding
# or once a step lowers chi-square by less than this: it moved the pose by a tenth of its own standard
# deviation (Mahalanobis), and Gauss-Newton's next step, quadratically smaller, would move it by far less; the
# normal equations formed before that step describe the final pose's uncertainty as well as any formed after
# it. A tighter bound buys one more pass over the points for a change no statistic of the pose can see
# (docs/estimator.md, Dense refinement).
STEP_CHI2 = 1e-2
# Between passes over the points, Gauss-Newton continues on the points the last pass kept, each step from their
# per-face sums (no pass): a step costs a microsecond where a pass costs tens. Converged this far, the next pass
# over the points usually finds the same points and a step under STEP_CHI2, and ends the refinement.
INNER_STEPS = 6
INNER_CHI2 = 1e-4
# columns of the per-face depth model (_face_models)
A, INV_B, C, ALPHA, TX, TY, TZ = range(7)


@kernel(**JIT)
def _face_models(normals, offsets, rot, t, model):
    """Per face, with its normal n and m = R^T n (the normal in F): a = m0, 1 / b = 1 / m2, c = offset - n . t,
    alpha = m1 / b and -n / b (the translation columns). A point x of the laser line meets the face at depth
    (c - x a) / b."""
    for f in range(normals.shape[0]):
        n0, n1, n2 = normals[f, 0], normals[f, 1], normals[f, 2]
        inv_b = 1.0 / (n0 * rot[0, 2] + n1 * rot[1, 2] + n2 * rot[2, 2])
        model[f, A] = n0 * rot[0, 0] + n1 * rot[1, 0] + n2 * rot[2, 0]
        model[f, INV_B] = inv_b
        model[f, C] = offsets[f] - (n0 * t[0] + n1 * t[1] + n2 * t[2])
        model[f, ALPHA] = (n0 * rot[0, 1] + n1 * rot[1, 1] + n2 * rot[2, 1]) * inv_b
        model[f, TX] = -n0 * inv_b
        model[f, TY] = -n1 * inv_b
        model[f, TZ] = -n2 * inv_b


@kernel(**JIT)
def _rank_bin(hist, rank):
    """The bin holding the rank-th smallest (0-based) of the counted values, and how many lie before it."""
    below = 0
    for b in range(hist.shape[0]):
        if below + hist[b] > rank:
            return b, below
        below += hist[b]
    return hist.shape[0] - 1, below


@kernel(**JIT)
def _median(values, count, hist, pool):
    """np.median(values[:count]) of non-negative values (count > 0), the same number, by radix selection:
    the bit patterns of non-negative floats order as the numbers do, so two histograms (the exponent, then
    the next 11 bits; hist holds 2048 counts) leave a handful of candidates to sort. Quickselect, which
    np.median uses, mispredicts its branches on fresh data (docs/estimator.md has the cost). pool is
    int64 scratch space of count. (A NaN sorts above inf here: an outlier, not a NaN median.)"""
    bits = values[:count].view(np.int64)
    lo, hi = (count - 1) // 2, count // 2
    pool[:count] = bits
    m, skip = count, 0
    for shift in (52, 41):
        hist[:] = 0
        for j in range(m):
            hist[(pool[j] >> shift) & 2047] += 1
        first, below = _rank_bin(hist, lo - skip)
        last, _ = _rank_bin(hist, hi - skip)
        if first != last:  # the two middle values straddle two bins: the largest of one, the smallest of the next
            low, high = 0, 0x7FFFFFFFFFFFFFFF
            for j in range(m):
                key = (pool[j] >> shift) & 2047
                if key == first:
                    low = max(low, pool[j])
                elif key == last:
                    high = min(high, pool[j])
            pool[0], pool[1] = low, high
            pair = pool[:2].view(np.float64)
            return 0.5 * (pair[0] + pair[1])
        kept = 0
        for j in range(m):  # branch-free compaction of the bin's members
            pool[kept] = pool[j]
            kept += ((pool[j] >> shift) & 2047) == first
        m, skip = kept, skip + below
    chosen = np.sort(pool[:m]).view(np.float64)
    return 0.5 * (chosen[lo - skip] + chosen[hi - skip])


@kernel(**JIT)
def _ridges_ordered(ridge_q, ridge_u, half_l):
    """Whether the ridges lie in increasing x all along the footprint (a validated gauge's do; a gauge made
    without some faces may not): the x of a ridge is linear in y, so checking both ends is enough."""
    for k in range(ridge_u.shape[0] - 1):
        for y in (-half_l, half_l):
            if not ridge_q[k] + ridge_u[k] * y < ridge_q[k + 1] + ridge_u[k + 1] * y:
                return False
    return True


@kernel(**JIT)
def _classify(points, ridge_q, ridge_u, width, length, rot, t, margin, threshold, floor, model, face_of, residual,
              spread, hist, pool, sums):
    """Each point's face and depth residual, face_of -1 where the point is unusable (off the footprint, within
    `margin` of a ridge or an edge) or beyond the robust cut (threshold robust standard deviations, at least
    `floor`), and each face's sums over its kept points (_face_normal_equations' columns); returns (points
    kept, the sum of their squared residuals). spread, hist and pool are scratch space for the median.

    A point's face is the number of ridges left of it. With the ridges in order that is found by walking from
    the previous point's face (the profile crosses the faces in turn, so the walk is a step or none), and the
    nearest ridges are the face's two: the same face and clearance as testing every ridge, at a fixed cost
    per point instead of one that grows with the ridges.

    The sums are taken over every usable point as it is classified and the few beyond the cut taken out once
    the cut is known: one pass over the points instead of a second one to sum the kept (a third of a dense
    pass's time). The face being crossed keeps its sums in locals, stored when the walk leaves it: the same
    additions in the same order as _add_to_sums makes, without a store and a load per point."""
    n_ridges = ridge_u.shape[0]
    half_w = width / 2
    half_l = length / 2
    ordered = _ridges_ordered(ridge_q, ridge_u, half_l)
    sums[:, :] = 0.0
    squares = 0.0
    face = 0
    usable = 0
    run = -1  # the face whose sums are in s0..s4 and x0
    s0 = s1 = s2 = s3 = s4 = x0 = 0.0
    for i in range(points.shape[0]):
        face_of[i] = -1
        x, z = points[i, 0], points[i, 1]
        mx = t[0] + x * rot[0, 0] + z * rot[0, 2]
        my = t[1] + x * rot[1, 0] + z * rot[1, 2]
        if not (abs(mx) < half_w and abs(my) < half_l):
            continue
        clearance = min(abs(mx + half_w), abs(half_w - mx))
        if ordered:
            while face < n_ridges and ridge_q[face] + ridge_u[face] * my < mx:
                face += 1
            while face > 0 and not ridge_q[face - 1] + ridge_u[face - 1] * my < mx:
                face -= 1
            if face > 0:
                clearance = min(clearance, abs(ridge_q[face - 1] + ridge_u[face - 1] * my - mx))
            if face < n_ridges:
                clearance = min(clearance, abs(ridge_q[face] + ridge_u[face] * my - mx))
        else:
            face = 0
            for k in range(n_ridges):
                ridge = ridge_q[k] + ridge_u[k] * my
                if ridge < mx:
                    face += 1
                clearance = min(clearance, abs(ridge - mx))
        if not clearance > margin:
            continue
        r = z - (model[face, C] - x * model[face, A]) * model[face, INV_B]
        face_of[i] = face
        residual[i] = r
        spread[usable] = abs(r)
        usable += 1
        if face != run:
            if run >= 0:
                _store_sums(sums, run, s0, s1, s2, s3, s4, x0)
            run = face
            s0, s1, s2, s3, s4, x0 = (sums[face, 0], sums[face, 1], sums[face, 2], sums[face, 3], sums[face, 4],
                                      sums[face, 5])
        if s0 == 0.0:
            x0 = x
        u = x - x0
        s0 += 1.0
        s1 += u
        s2 += u * u
        s3 += r
        s4 += u * r
        squares += r * r
    if run >= 0:
        _store_sums(sums, run, s0, s1, s2, s3, s4, x0)
    if usable == 0:
        return 0, 0.0
    limit = max(threshold * 1.4826 * _median(spread, usable, hist, pool), floor)
    kept = 0
    for i in range(points.shape[0]):
        if face_of[i] >= 0:
            if abs(residual[i]) <= limit:
                kept += 1
            else:
                squares -= _add_to_sums(sums, face_of[i], points[i, 0], residual[i], -1.0)
                face_of[i] = -1
    return kept, squares


@kernel(**JIT)
def _store_sums(sums, face, s0, s1, s2, s3, s4, x0):
    sums[face, 0], sums[face, 1], sums[face, 2], sums[face, 3], sums[face, 4], sums[face, 5] = s0, s1, s2, s3, s4, x0


@kernel(**JIT)
def _add_to_sums(sums, face, x, r, sign):
    """Add (sign 1) or take out (-1) one point of `face` in its sums; returns r^2. The sums are over u = x - x0,
    x0 the face's first point (sums[face, 5]), so that they do not cancel."""
    if sums[face, 0] == 0.0:
        sums[face, 5] = x
    u = x - sums[face, 5]
    sums[face, 0] += sign
    sums[face, 1] += sign * u
    sums[face, 2] += sign * u * u
    sums[face, 3] += sign * r
    sums[face, 4] += sign * u * r
    return r * r


@kernel(**JIT)
def _face_normal_equations(model, sums, hessian, gradient):
    """hessian = J^T J and gradient = J^T r from the per-face sums (columns S0, S1, S2, R0, R1, x0: the count,
    u, u^2, r and u r summed over the face's points, u = x - x0). Per face the Jacobian row is B [1, u], hence
    J^T J = sum over faces of B [[S0, S1], [S1, S2]] B^T and J^T r = B [R0, R1]."""
    n_faces = model.shape[0]
    hessian[:, :] = 0.0
    gradient[:] = 0.0
    b0, b1 = np.empty(6), np.empty(6)
    for f in range(n_faces):
        s0 = sums[f, 0]
        if s0 == 0.0:
            continue
        x0 = sums[f, 5]
        a, inv_b, alpha = model[f, A], model[f, INV_B], model[f, ALPHA]
        depth0 = (model[f, C] - x0 * a) * inv_b  # predicted depth at x0; it changes by slope per unit u
        slope = -a * inv_b
        beta = a * inv_b
        # the derivatives of the predicted depth (estimate_kernel's rotation-then-translation order):
        # d/d delta = (P m1 / b, x - P a / b, -x m1 / b), d/d t = -n / b, each as b0 + b1 u
        b0[0], b1[0] = alpha * depth0, alpha * slope
        b0[1], b1[1] = x0 - beta * depth0, 1.0 - beta * slope
        b0[2], b1[2] = -alpha * x0, -alpha
        b0[3], b1[3] = model[f, TX], 0.0
        b0[4], b1[4] = model[f, TY], 0.0
        b0[5], b1[5] = model[f, TZ], 0.0
        s1, s2, r0, r1 = sums[f, 1], sums[f, 2], sums[f, 3], sums[f, 4]
        for k in range(6):
            gradient[k] += b0[k] * r0 + b1[k] * r1
            for j in range(k, 6):
                hessian[k, j] += b0[k] * b0[j] * s0 + (b0[k] * b1[j] + b1[k] * b0[j]) * s1 + b1[k] * b1[j] * s2
    for k in range(6):
        for j in range(k):
            hessian[k, j] = hessian[j, k]


@kernel(**JIT)
def _moved_sums(model, moved_model, sums, moved):
    """The per-face sums at another pose (moved_model's) of the same points: a point's predicted depth is
    depth0 + slope u on its face at any pose, so its residual changes by the change of those two, and the sums
    of r and u r by the counts and u sums times them."""
    for f in range(model.shape[0]):
        x0 = sums[f, 5]
        depth_change = ((model[f, C] - x0 * model[f, A]) * model[f, INV_B] -
                        (moved_model[f, C] - x0 * moved_model[f, A]) * moved_model[f, INV_B])
        slope_change = moved_model[f, A] * moved_model[f, INV_B] - model[f, A] * model[f, INV_B]
        moved[f, 0], moved[f, 1], moved[f, 2], moved[f, 5] = sums[f, 0], sums[f, 1], sums[f, 2], x0
        moved[f, 3] = sums[f, 3] + sums[f, 0] * depth_change + sums[f, 1] * slope_change
        moved[f, 4] = sums[f, 4] + sums[f, 1] * depth_change + sums[f, 2] * slope_change


@kernel(**JIT)
def _step(low, gradient, step, turn, rotated, rot, t):
    """Solve (L L^T) step = gradient and move the pose (rot, t) by it; returns the chi-square the step removes
    (step^T J^T J step), or -1 once no component exceeds STEP_TOLERANCE (converged to rounding, even where the
    residuals are all zero)."""
    _cholesky_solve(low, gradient, step)
    _so3_exp(step[:3], turn)
    _matmul3(rot, turn, rotated)
    rot[:, :] = rotated
    for a in range(3):
        t[a] += step[3 + a]
    largest, decrease = 0.0, 0.0
    for a in range(6):
        largest = max(largest, abs(step[a]))
        decrease += step[a] * gradient[a]
    return -1.0 if largest < STEP_TOLERANCE else decrease


@kernel(**JIT)
def _linearise(pts, normals, offsets, ridge_q, ridge_u, width, length, rot, t, margin, threshold, floor, model, face_of,
               residual, spread, hist, pool, sums, hessian, gradient):
    """One pass over the points at (rot, t): faces, residuals, the robust cut and the normal equations.
    Returns (points kept, the sum of their squared residuals); the rest are scratch and outputs."""
    _face_models(normals, offsets, rot, t, model)
    count, squares = _classify(pts, ridge_q, ridge_u, width, length, rot, t, margin, threshold, floor, model, face_of,
                               residual, spread, hist, pool, sums)
    _face_normal_equations(model, sums, hessian, gradient)
    return count, squares


@kernel(**JIT)
def _add_valley_curvature(normals, offsets, rot, t, sums, cov):
    """_add_curvature_term (estimate_kernel) for the dense pose: p'' from the predicted depths at +-s v, each
    point on the face it was on in the last linearisation (whose per-face sums `sums` holds). On a face the
    predicted depth is linear in x at every pose, so p'' is too: its J^T p'' follows from the face's sums, with
    no pass over the points."""
    v = np.empty(6)
    variance = _weakest_direction(cov, v)
    s = math.sqrt(variance)
    n_faces = normals.shape[0]
    model, moved_model = np.empty((n_faces, 7)), np.empty((n_faces, 7))
    curved_sums = sums.copy()
    _face_models(normals, offsets, rot, t, model)
    intercept, slope = np.zeros(n_faces), np.zeros(n_faces)  # p'' = intercept + slope x on each face
    moved, shifted = np.empty((3, 3)), np.empty(3)
    for sign in (1.0, -1.0):
        _moved_pose(rot, t, v, sign * s, moved, shifted)
        _face_models(normals, offsets, moved, shifted, moved_model)
        for f in range(n_faces):
            intercept[f] += (moved_model[f, C] * moved_model[f, INV_B] - model[f, C] * model[f, INV_B]) / variance
            slope[f] -= (moved_model[f, A] * moved_model[f, INV_B] - model[f, A] * model[f, INV_B]) / variance
    for f in range(n_faces):
        at_x0 = intercept[f] + slope[f] * sums[f, 5]  # r = at_x0 + slope u, u = x - x0
        curved_sums[f, 3] = at_x0 * sums[f, 0] + slope[f] * sums[f, 1]
        curved_sums[f, 4] = at_x0 * sums[f, 1] + slope[f] * sums[f, 2]
    hessian, curved = np.empty((6, 6)), np.empty(6)
    _face_normal_equations(model, curved_sums, hessian, curved)
    _add_curvature_term(cov, hessian, curved, v, variance)


@kernel(**JIT)
def _noise_variance(noise_std, squares, count):
    """The depth noise's variance: the configured one, or (noise_std 0) the kept residuals'."""
    return noise_std * noise_std if noise_std > 0.0 else squares / max(1, count - 6)


@kernel(**JIT)
def _lit_span(points):
    """The rows from the first point with a finite x and z to just past the last (empty if none)."""
    n = points.shape[0]
    first = 0
    while first < n and not (math.isfinite(points[first, 0]) and math.isfinite(points[first, 1])):
        first += 1
    last = n
    while last > first and not (math.isfinite(points[last - 1, 0]) and math.isfinite(points[last - 1, 1])):
        last -= 1
    return first, last


@kernel(**JIT)
def refine_dense(points, normals, offsets, ridge_q, ridge_u, width, length, rot, t, noise_std, margin, threshold,
                 floor, iterations, rot_out, t_out, cov_out):
    """dense.refine_dense: returns (status, points used, sigma); rot_out, t_out, cov_out (over [delta_F, t]).
    Every pass runs over the lit span only: the profiler's field is often twice the gauge's, and its unlit ends
    (NaN) cost a pass as much as the points. A NaN inside the span (a gap, a dropout) is passed over where
    _classify maps each point onto the footprint (it lands on no face), not copied out first."""
    first, last = _lit_span(points)
    pts = points[first:last]
    n_points = pts.shape[0]
    n_faces = normals.shape[0]
    face_of, residual, spread = np.empty(n_points, np.int64), np.empty(n_points), np.empty(n_points)
    hist, pool = np.empty(2048, np.int64), np.empty(n_points, np.int64)
    model, sums = np.empty((n_faces, 7)), np.empty((n_faces, 6))
    hessian, gradient, low, step = np.empty((6, 6)), np.empty(6), np.empty((6, 6)), np.empty(6)
    turn, rotated = np.empty((3, 3)), np.empty((3, 3))
    rot_out[:, :] = rot
    t_out[:] = t
    moved_model, moved_sums = np.empty((n_faces, 7)), np.empty((n_faces, 6))
    inner_hessian, inner_gradient = np.empty((6, 6)), np.empty(6)
    converged = False
    count, squares = 0, 0.0
    for _ in range(iterations):
        count, squares = _linearise(pts, normals, offsets, ridge_q, ridge_u, width, length, rot_out, t_out, margin,
                                    threshold, floor, model, face_of, residual, spread, hist, pool, sums, hessian,
                                    gradient)
        if count < 6 or not _cholesky(hessian, low):
            return SINGULAR, count, 0.0
        variance = _noise_variance(noise_std, squares, count)
        if _step(low, gradient, step, turn, rotated, rot_out, t_out) < STEP_CHI2 * variance:
            # the normal equations just formed are those of the final pose, to well within its uncertainty
            converged = True
            break
        # Gauss-Newton on the points this pass kept, from their sums alone (_moved_sums), to convergence: the next
        # pass then starts where these points put the pose, and usually keeps the same points and ends there
        for _ in range(INNER_STEPS):
            _face_models(normals, offsets, rot_out, t_out, moved_model)
            _moved_sums(model, moved_model, sums, moved_sums)
            _face_normal_equations(moved_model, moved_sums, inner_hessian, inner_gradient)
            if not _cholesky(inner_hessian, low):
                break
            if _step(low, inner_gradient, step, turn, rotated, rot_out, t_out) < INNER_CHI2 * variance:
                break
    if not converged:
        count, squares = _linearise(pts, normals, offsets, ridge_q, ridge_u, width, length, rot_out, t_out, margin,
                                    threshold, floor, model, face_of, residual, spread, hist, pool, sums, hessian,
                                    gradient)
    sigma = noise_std if noise_std > 0.0 else math.sqrt(_noise_variance(noise_std, squares, count))
    if count < 6 or not _spd_inverse(hessian, cov_out):
        return SINGULAR, count, sigma
    for a in range(6):
        for b in range(6):
            cov_out[a, b] *= sigma * sigma
    if cov_out[3, 3] + cov_out[4, 4] + cov_out[5, 5] > CURVED_ABOVE:
        _add_valley_curvature(normals, offsets, rot_out, t_out, sums, cov_out)
    return OK, count, sigma
