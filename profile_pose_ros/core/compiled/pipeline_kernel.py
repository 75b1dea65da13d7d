"""The estimate of a whole gauge from its detected corners (profile_kernel.estimate detects them): closed form
(a four-ridge gauge's several starting poses, each refined, the lowest minimum kept unless a rival fits about as
well), refinement, the basin search when the pose is poorly determined or its checks refuse it, the checks, and
for a poorly determined pose its covariance by the unscented transform; or, with the dense model (or auto, for
a poorly determined corner pose), the dense refinement from that pose and the same checks of its solution.
"""
from __future__ import annotations

import math

import numpy as np

from ..model.sym3 import largest_eigenvalue
from .codes import (AMBIGUOUS, AMBIGUOUS_COST, AMBIGUOUS_DISTANCE, COVARIANCE_CALIBRATION, DENSE_ALWAYS,
                    DENSE_STAGE, DENSE_WHEN_POORLY_DETERMINED, INCONSISTENT, JIT, NO_CONVERGED, NO_START, NOT_FINITE,
                    O_DENSE, O_DENSESIG, O_DFLOOR, O_DITER, O_DMARGIN, O_DTHR, O_MARGIN, O_MAXIT, O_MAXRATIO,
                    O_MAXREPROJ, O_NOISE, O_REFINE, O_SEARCH, O_SEARCHSIG, O_WEIGHTED, OK, OUTSIDE_FOOTPRINT,
                    REPROJECTION, REWEIGHT_ROUNDS)
from .dense_kernel import refine_dense
from .estimate_kernel import (CURVED_ABOVE, _add_corner_valley_curvature, _cholesky, _closed_form, _quadratic, _refine,
                              _residuals, _spd_inverse, _unstack_residuals)
from .kernel import kernel
from .search_kernel import _cost, four_ridge_starts, search_minima

_largest_eigenvalue = kernel(**JIT)(largest_eigenvalue)


@kernel(**JIT)
def _position_sigma(cov):
    """estimator.position_sigma of cov[:3, :3], compiled: every accepted pose is checked against it."""
    a, b, c, d, e, f = cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2]
    for v in (a, b, c, d, e, f):
        if not math.isfinite(v):
            return np.nan
    return math.sqrt(max(_largest_eigenvalue(a, b, c, d, e, f), 0.0))


@kernel(**JIT)
def _check(corners, rot, t, r, chi2, refined, width, length, opt, info, res_out):
    """Why (rot, t) is no pose, as a status (OK if it is one): not finite; (refined only: the closed form's
    residuals are far larger) residuals inconsistent with the corners' covariance; corners off their ridges
    by more than the bound; corners mapped off the footprint. Returns (status, reprojection error)."""
    n = corners.shape[0]
    err = _unstack_residuals(r, res_out)
    for v in rot.ravel():
        if not math.isfinite(v):
            return NOT_FINITE, err
    for v in t:
        if not math.isfinite(v):
            return NOT_FINITE, err
    dof = 2 * n - 6
    if refined and dof > 0 and not chi2 <= opt[O_MAXRATIO] * opt[O_MAXRATIO] * dof:
        info[0] = chi2
        info[1] = dof
        return INCONSISTENT, err
    if not err <= opt[O_MAXREPROJ]:
        return REPROJECTION, err
    half_w = width / 2 + opt[O_MARGIN]
    half_l = length / 2 + opt[O_MARGIN]
    for i in range(n):
        mx = corners[i, 0] * rot[0, 0] + corners[i, 1] * rot[0, 2] + t[0]
        my = corners[i, 0] * rot[1, 0] + corners[i, 1] * rot[1, 2] + t[1]
        if abs(mx) > half_w or abs(my) > half_l:
            info[0] = i
            info[1] = mx
            info[2] = my
            return OUTSIDE_FOOTPRINT, err
    return OK, err


@kernel(**JIT)
def _start_outputs(q, u, w, corners, rot, t, cf_rot, cf_t, cf_res):
    """The starting pose as the closed-form outputs; returns its reprojection error."""
    cf_rot[:, :] = rot
    cf_t[:] = t
    r = np.empty(2 * corners.shape[0])
    _residuals(q, u, w, corners, rot, t, r)
    return _unstack_residuals(r, cf_res)


@kernel(**JIT)
def _rotation_between(a, b, out):
    """delta with b = a exp([delta]x) (angle < pi): model.rotation.so3_log of a^T b."""
    m = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            m[i, j] = a[0, i] * b[0, j] + a[1, i] * b[1, j] + a[2, i] * b[2, j]
    cos_angle = min(max((m[0, 0] + m[1, 1] + m[2, 2] - 1.0) / 2.0, -1.0), 1.0)
    angle = math.acos(cos_angle)
    scale = 0.5 if angle < 1e-7 else angle / (2.0 * math.sin(angle))
    out[0] = scale * (m[2, 1] - m[1, 2])
    out[1] = scale * (m[0, 2] - m[2, 0])
    out[2] = scale * (m[1, 0] - m[0, 1])


@kernel(**JIT)
def _rival(rots, ts, costs, count, best, cov):
    """The first minimum that fits about as well as the best (costs within AMBIGUOUS_COST) but lies far from
    it (beyond AMBIGUOUS_DISTANCE of its standard deviations): with four ridges (two redundant equations)
    the corners can fit two poses centimetres apart, and the lower cost is then a coin toss (seen in the
    study: 54 mm off, cost 1.6 against 4.4 at the true pose). Returns its index, or -1."""
    information = np.empty((6, 6))
    if not _spd_inverse(cov, information):
        return -1
    d = np.empty(6)
    for k in range(count):
        if not costs[k] - costs[best] < AMBIGUOUS_COST:  # a start that did not converge has an infinite cost
            continue
        _rotation_between(rots[best], rots[k], d[:3])
        for i in range(3):
            d[3 + i] = ts[k, i] - ts[best, i]
        if _quadratic(d, information) > AMBIGUOUS_DISTANCE * AMBIGUOUS_DISTANCE:
            return k
    return -1


@kernel(**JIT)
def _unscented_covariance(q, u, w, corners, rot, t, corner_cov, weighted, max_iterations, cov):
    """A poorly determined pose's covariance (over [delta_F, t]) by the unscented transform: the corners moved
    to the 2m sigma points of their covariance (m = 2n; +-sqrt(m) times each column of its Cholesky factor),
    the pose refined again from each, and the second moment of those poses about the estimate. Along the
    long curved valley of such a pose the corners -> pose map is far from linear, and the linearised
    covariance understates the error (docs/estimator.md, Covariance, has the measurements). cov is left as
    it is if any sigma point's refinement fails."""
    n = corners.shape[0]
    m = 2 * n
    low = np.empty((m, m))
    if not _cholesky(corner_cov, low):
        return
    moved = np.empty((n, 2))
    d = np.empty(6)
    second = np.zeros((6, 6))
    no_cov = np.empty((0, 0))
    spread = math.sqrt(m)
    for j in range(m):
        for sign in (1.0, -1.0):
            for i in range(n):
                moved[i, 0] = corners[i, 0] + sign * spread * low[2 * i, j]
                moved[i, 1] = corners[i, 1] + sign * spread * low[2 * i + 1, j]
            status, rot2, t2, r2, its, chi2 = _refine(q, u, w, moved, rot, t, corner_cov, weighted, max_iterations,
                                                      True, no_cov, 1)  # converged: a short run spreads too little
            if status != OK:
                return
            _rotation_between(rot, rot2, d[:3])  # R2 = R exp([delta_F]x)
            for a in range(3):
                d[3 + a] = t2[a] - t[a]
            for a in range(6):
                for b in range(6):
                    second[a, b] += d[a] * d[b]
    for a in range(6):
        for b in range(6):
            cov[a, b] = second[a, b] / (2.0 * m)


@kernel(**JIT)
def _dense_stage(points, q, u, w, faces, width, length, opt, corners, rot, t, cov, info, res_out):
    """rot, t, cov replaced by the dense refinement's from (rot, t) if its solution passes the checks the
    corner solution passed (the corners' residual test aside: the dense pose does not minimise them).
    Returns (status, reprojection error). faces: Gauge.kernel_faces, writable copies (numba's code for the
    dense loops is slower on the gauge's read-only arrays)."""
    normals, offsets, ridge_q, ridge_u = faces
    rot_d, t_d, cov_d = np.empty((3, 3)), np.empty(3), np.empty((6, 6))
    status, used, sigma = refine_dense(points, normals, offsets, ridge_q, ridge_u, width, length, rot, t,
                                       opt[O_NOISE], opt[O_DMARGIN], opt[O_DTHR], opt[O_DFLOOR], int(opt[O_DITER]),
                                       rot_d, t_d, cov_d)
    if status != OK:
        return status, np.nan
    r = np.empty(2 * corners.shape[0])
    _residuals(q, u, w, corners, rot_d, t_d, r)
    status, err = _check(corners, rot_d, t_d, r, 0.0, False, width, length, opt, info, res_out)
    if status == OK:
        rot[:, :] = rot_d
        t[:] = t_d
        cov[:, :] = cov_d
    return status, err


@kernel(**JIT)
def _starting_poses(q, u, w, corners, start_rots, start_ts, info):
    """The starting poses of the refinement into start_rots (3, 3, 3) and start_ts (3, 3): the closed form, or a
    four-ridge gauge's candidates (its system leaves a free direction). Returns (status, how many): NO_START or
    the closed form's refusal (info holds its numbers) with none."""
    if corners.shape[0] == 4:
        count = four_ridge_starts(q, u, w, corners, start_rots, start_ts)
        return (OK if count > 0 else NO_START), count
    status, rot, t = _closed_form(q, u, w, corners, info)
    if status != OK:
        return status, 0
    start_rots[0] = rot
    start_ts[0] = t
    return OK, 1


@kernel(**JIT)
def _from_the_real_corners(q, u, w, corners, corner_cov, weighted, max_iterations, virtual):
    """The lowest minimum of all the corners refined from the starting poses of the real ones alone (every corner
    but `virtual`; none from three). Returns (found, rot, t, residuals, covariance, chi2, iterations)."""
    n = corners.shape[0]
    m = n - 1
    sub_q, sub_u, sub_w, sub_corners = np.empty((m, 3)), np.empty(m), np.empty(m), np.empty((m, 2))
    k = 0
    for i in range(n):
        if i != virtual:
            sub_q[k], sub_u[k], sub_w[k], sub_corners[k] = q[i], u[i], w[i], corners[i]
            k += 1
    start_rots, start_ts = np.empty((3, 3, 3)), np.empty((3, 3))
    count = 0
    if m >= 4:
        _, count = _starting_poses(sub_q, sub_u, sub_w, sub_corners, start_rots, start_ts, np.zeros(4))
    best_rot, best_t, best_r, best_cov = np.empty((3, 3)), np.empty(3), np.empty(2 * n), np.empty((6, 6))
    best_cost, best_chi2, best_its = np.inf, np.inf, 0
    cov = np.empty((6, 6))
    for k in range(count):
        status, rot, t, r, iterations, chi2 = _refine(q, u, w, corners, start_rots[k], start_ts[k], corner_cov,
                                                      weighted, max_iterations, True, cov, REWEIGHT_ROUNDS)
        cost = chi2 if weighted else _quadratic(r, np.eye(2 * n))
        if status == OK and cost < best_cost:
            best_rot[:, :], best_t[:], best_r[:], best_cov[:, :] = rot, t, r, cov
            best_cost, best_chi2, best_its = cost, chi2, iterations
    return math.isfinite(best_cost), best_rot, best_t, best_r, best_cov, best_chi2, best_its


@kernel(**JIT)
def _unset(rot_out, t_out, cov_out):
    """The outputs NaN: they stay so unless a pose is accepted."""
    rot_out[:, :] = np.nan
    t_out[:] = np.nan
    cov_out[:, :] = np.nan


@kernel(**JIT)
def estimate_detected(points, q, u, w, normals, offsets, ridge_q, ridge_u, width, length, opt, corners, jac, line_var,
                      fit_rms, virtual, rot_out, t_out, cov_out, cf_rot, cf_t, cf_res, res_out, info):
    """The estimate from a detection already made (corners, jac, line_var and fit_rms as estimate_kernel.detect
    returns them, with this opt): a partial view tries several gauges on one detection (partial_kernel.py). Returns
    (status, iterations, fit_rms, reprojection_error, cf_reprojection_error, position_sigma, search_starts);
    position_sigma is NaN unless a pose is accepted, search_starts 0 unless the basin search ran. virtual: the
    index of a corner two faces' fits make across a gap (partial_kernel.py), or -1."""
    n = u.shape[0]
    _unset(rot_out, t_out, cov_out)
    corner_cov = np.empty((2 * n, 2 * n))
    for a in range(2 * n):
        for b in range(2 * n):
            acc = 0.0
            for k in range(2 * n + 2):
                acc += jac[a, k] * line_var[k] * jac[b, k]
            corner_cov[a, b] = acc
    start_rots = np.empty((3, 3, 3))
    start_ts = np.empty((3, 3))
    status, count = _starting_poses(q, u, w, corners, start_rots, start_ts, info)
    if status != OK:
        return status, 0, fit_rms, np.nan, np.nan, np.nan, 0
    cf_err = _start_outputs(q, u, w, corners, start_rots[0], start_ts[0], cf_rot, cf_t, cf_res)
    refined = opt[O_REFINE] > 0
    weighted = opt[O_WEIGHTED] > 0
    max_it = int(opt[O_MAXIT]) if refined or count > 1 else 0  # several starts are told apart by their minima
    rots = np.empty((count, 3, 3))
    ts = np.empty((count, 3))
    rs = np.empty((count, 2 * n))
    covs = np.empty((count, 6, 6))
    costs = np.full(count, np.inf)
    chi2s = np.empty(count)
    its = np.zeros(count, dtype=np.int64)
    best = -1
    for k in range(count):
        status, rot2, t2, r2, iterations, chi2 = _refine(q, u, w, corners, start_rots[k], start_ts[k], corner_cov,
                                                         weighted, max_it, True, covs[k], REWEIGHT_ROUNDS)
        if status != OK:
            if count == 1:
                return status, iterations, fit_rms, np.nan, cf_err, np.nan, 0
            continue
        rots[k] = rot2
        ts[k] = t2
        rs[k] = r2
        chi2s[k] = chi2
        its[k] = iterations
        costs[k] = chi2 if weighted else _quadratic(r2, np.eye(2 * n))
        if best < 0 or costs[k] < costs[best]:
            best = k
    if best < 0:
        return NO_CONVERGED, 0, fit_rms, np.nan, cf_err, np.nan, 0
    if best != 0:
        cf_err = _start_outputs(q, u, w, corners, start_rots[best], start_ts[best], cf_rot, cf_t, cf_res)
    if weighted and refined and count > 1:
        k = _rival(rots, ts, costs, count, best, covs[best])
        if k >= 0:
            d = ts[k] - ts[best]
            info[0] = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
            info[1] = costs[best]
            info[2] = costs[k]
            return AMBIGUOUS, its[best], fit_rms, np.nan, cf_err, np.nan, 0
    cov = covs[best].copy()
    chi2 = chi2s[best]
    if refined:
        rot, t, r, iterations = rots[best].copy(), ts[best].copy(), rs[best].copy(), its[best]
    else:
        rot, t, r, iterations = start_rots[best].copy(), start_ts[best].copy(), np.empty(2 * n), 0
        _residuals(q, u, w, corners, rot, t, r)
    status, err = _check(corners, rot, t, r, chi2, refined, width, length, opt, info, res_out)
    tried = 0
    # auto (DENSE_WHEN_POORLY_DETERMINED): the dense refinement where the corners determine the pose poorly
    auto = opt[O_DENSE] == DENSE_WHEN_POORLY_DETERMINED and refined
    dense = opt[O_DENSE] == DENSE_ALWAYS or auto and not _position_sigma(cov[3:, 3:]) <= opt[O_DENSESIG]
    if opt[O_SEARCH] > 0 and refined and status != OK and virtual >= 0:
        # a virtual corner, extrapolated far along nearly parallel faces, can skew the closed form into a wrong
        # basin (corner residuals hundreds of times the noise); the real corners alone start in the right one
        # far more often, at a fraction of the basin search's cost
        found, rot2, t2, r2, cov2, chi2_2, its2 = _from_the_real_corners(q, u, w, corners, corner_cov, weighted,
                                                                         max_it, virtual)
        if found:  # checked aside: a refusal keeps the numbers of its own pose's check
            res2 = np.empty_like(res_out)
            status2, err2 = _check(corners, rot2, t2, r2, chi2_2, refined, width, length, opt, np.zeros(4), res2)
            if status2 == OK:
                rot, t, r, iterations, chi2, status, err = rot2, t2, r2, its2, chi2_2, status2, err2
                cov[:, :] = cov2
                res_out[:, :] = res2
    # A corner pose that is poorly determined, or refused: perhaps a neighbouring basin holds the right minimum.
    # Not for a poorly determined one the dense refinement takes over: fitting every point, it finds its basin
    # from the corner pose as well as from the searched one (docs/estimator.md, Unclean profiles)
    if opt[O_SEARCH] > 0 and refined and (status != OK or not dense and not _position_sigma(cov[3:, 3:]) <=
                                          opt[O_SEARCHSIG]):
        best_rot, best_t, best_r, best_cov = np.empty((3, 3)), np.empty(3), np.empty(2 * n), np.empty((6, 6))
        improved, tried, its = search_minima(q, u, w, corners, corner_cov, weighted, max_it, rot, t, cov, best_rot,
                                             best_t, best_r, best_cov)
        if improved:
            rot, t, r, iterations = best_rot, best_t, best_r, its
            cov[:, :] = best_cov
            chi2 = _cost(q, u, w, corners, rot, t, corner_cov, True)
            status, err = _check(corners, rot, t, r, chi2, refined, width, length, opt, info, res_out)
            if auto:
                dense = not _position_sigma(cov[3:, 3:]) <= opt[O_DENSESIG]
    if status != OK:
        return status, iterations, fit_rms, err, cf_err, np.nan, tried
    if dense:
        status, dense_err = _dense_stage(points, q, u, w, (normals, offsets, ridge_q, ridge_u), width, length, opt,
                                         corners, rot, t, cov, info, res_out)
        if status != OK:
            return status + DENSE_STAGE, iterations, fit_rms, err, cf_err, np.nan, tried
        err = dense_err
    elif refined and not _position_sigma(cov[3:, 3:]) <= opt[O_SEARCHSIG]:
        _unscented_covariance(q, u, w, corners, rot, t, corner_cov, weighted, max_it, cov)
    elif refined and weighted and cov[3, 3] + cov[4, 4] + cov[5, 5] > CURVED_ABOVE:
        _add_corner_valley_curvature(q, u, w, corners, rot, t, corner_cov, cov)
    rot_out[:, :] = rot
    t_out[:] = t
    # [delta_F, t] -> ROS [t, delta_G = R delta_F]: cov_ros = T cov T^T, T = [[0, I], [R, 0]], calibrated
    rr = np.zeros((6, 6))
    for k in range(3):
        rr[k, 3 + k] = 1.0
        for j in range(3):
            rr[3 + k, j] = rot[k, j]
    for a in range(6):
        for b in range(6):
            acc = 0.0
            for i in range(6):
                if rr[a, i] == 0.0:
                    continue
                for j in range(6):
                    acc += rr[a, i] * cov[i, j] * rr[b, j]
            cov_out[a, b] = acc * COVARIANCE_CALIBRATION
    return OK, iterations, fit_rms, err, cf_err, _position_sigma(cov_out), tried
