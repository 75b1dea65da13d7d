"""The basin search, compiled: when a refined pose is poorly determined its cost is a long curved valley
along the weak mode (tilt of the laser plane with a shift along the ridges), and a local method can stop
in a neighbouring basin several standard deviations from the truth. The search tries more starts and
keeps the lowest minimum: the four-ridge subsets' closed-form candidates (a well-spread subset of four
lands in the right basin where all n nearly parallel ridges blend into the wrong one), then hops of 3, 8
and 20 standard deviations both ways along the two weakest modes of the best so far, again while that
improves. Every start gets a few LM steps (triage); the two lowest, if not far above the best, are refined
fully. One compiled call, so a poorly determined pose costs about what a well-determined one does.
"""
from __future__ import annotations

import math

import numpy as np

from .codes import JIT, OK
from .estimate_kernel import (_matmul3, _pose_from_x, _quadratic, _refine, _residual_covariance, _residuals,
                              _so3_exp, _spd_inverse, _system)
from .kernel import kernel

SEARCH_SCALES = (3.0, 8.0, 20.0)  # hop lengths along a weak mode, in its standard deviations
SEARCH_MODES = 2  # the weakest directions of the pose
SEARCH_ROUNDS = 3  # hop again from an improved minimum
MAX_SUBSETS = 5  # four-ridge subsets tried (consecutive ridges, each starting one further on)
TRIAGE_ITERATIONS = 4  # a few LM steps tell which basin a start is in
TRIAGE_KEEP = 2  # starts refined fully per round
TRIAGE_MARGIN = 1.5  # a triaged start this much above the best is not refined further
ROOT_IMAG_TOLERANCE = 1e-9  # a complex root pair this close to the real axis is a (double) real root


@kernel(**JIT)
def _cost(q, u, w, corners, rot, t, corner_cov, weighted):
    """The cost the refinement minimises at (rot, t): the residuals' squared length, weighted by the
    covariance the corners induce (inf if that is singular) or plain."""
    n2 = 2 * corners.shape[0]
    r = np.empty(n2)
    _residuals(q, u, w, corners, rot, t, r)
    if not weighted:
        return _quadratic(r, np.eye(n2))
    sigma_r = np.empty((n2, n2))
    information = np.empty((n2, n2))
    _residual_covariance(u, w, rot, corner_cov, sigma_r)
    if not _spd_inverse(sigma_r, information):
        return np.inf
    return _quadratic(r, information)


@kernel(**JIT)
def _cubic_real_roots(c3, c2, c1, c0, roots):
    """Real roots of c3 x^3 + c2 x^2 + c1 x + c0 into roots; returns how many. A complex pair whose
    imaginary part is below ROOT_IMAG_TOLERANCE (relative) counts as a real root (a near-double root is a
    start too)."""
    zeros = 0
    while c0 == 0.0 and (c3 != 0.0 or c2 != 0.0 or c1 != 0.0):  # a root at zero, exactly (as numpy.roots)
        c0, c1, c2, c3 = c1, c2, c3, 0.0
        roots[zeros] = 0.0
        zeros += 1
    return zeros + _nonzero_roots(c3, c2, c1, c0, roots[zeros:])


@kernel(**JIT)
def _quadratic_roots(c2, c1, c0, roots):
    """Real roots of c2 x^2 + c1 x + c0 (c0 != 0), without cancellation; a near-real complex pair as one."""
    if c2 == 0.0:
        if c1 == 0.0:
            return 0
        roots[0] = -c0 / c1
        return 1
    disc = c1 * c1 - 4.0 * c2 * c0
    if disc < 0.0:
        re, im = -c1 / (2.0 * c2), math.sqrt(-disc) / abs(2.0 * c2)
        if im < ROOT_IMAG_TOLERANCE * (1.0 + abs(re)):
            roots[0] = re
            return 1
        return 0
    half = -0.5 * (c1 + math.copysign(math.sqrt(disc), c1))
    roots[0] = half / c2
    roots[1] = c0 / half  # c0 != 0, so half != 0
    return 2


@kernel(**JIT)
def _newton(c3, c2, c1, c0, x):
    """x polished by a few Newton steps on the cubic."""
    for _ in range(4):
        f = ((c3 * x + c2) * x + c1) * x + c0
        df = (3.0 * c3 * x + 2.0 * c2) * x + c1
        if df == 0.0:
            break
        x -= f / df
    return x


@kernel(**JIT)
def _nonzero_roots(c3, c2, c1, c0, roots):
    """_cubic_real_roots when c0 != 0: the real root of largest size (trigonometric form when there are
    three, else Cardano's), polished, then the two of the quadratic left when it is divided out (from the
    constant term up: stable for the largest root); the closed forms' other roots lose their digits to
    cancellation on badly scaled cubics."""
    if c3 == 0.0:
        return _quadratic_roots(c2, c1, c0, roots)
    a, b, c = c2 / c3, c1 / c3, c0 / c3
    p = b - a * a / 3.0
    qq = 2.0 * a * a * a / 27.0 - a * b / 3.0 + c
    disc = 0.25 * qq * qq + p * p * p / 27.0
    shift = -a / 3.0
    if disc <= 0.0 and p < 0.0:
        radius = 2.0 * math.sqrt(-p / 3.0)
        angle = math.acos(max(-1.0, min(1.0, 3.0 * qq / (p * radius))))
        x0 = shift
        for k in range(3):
            x = radius * math.cos((angle - 2.0 * math.pi * k) / 3.0) + shift
            if abs(x) > abs(x0):
                x0 = x
    else:
        s = math.sqrt(max(disc, 0.0))
        m = math.copysign(abs(-0.5 * qq + s) ** (1.0 / 3.0), -0.5 * qq + s)
        n = math.copysign(abs(-0.5 * qq - s) ** (1.0 / 3.0), -0.5 * qq - s)
        x0 = m + n + shift
    x0 = _newton(c3, c2, c1, c0, x0)
    roots[0] = x0
    # c3 x^2 + b1 x + b0 = the cubic / (x - x0), from the constant term up (stable for the largest root)
    b0 = -c0 / x0
    b1 = (b0 - c1) / x0
    if b0 == 0.0:  # underflow: x0 dwarfs the other roots, which are then below anything measurable
        return 1
    return 1 + _quadratic_roots(c3, b1, b0, roots[1:])


@kernel(**JIT)
def _quadratic_in_alpha(x0, v, ia, ib, out):
    """Coefficients (alpha^2, alpha, 1) of (x0 + alpha v)[ia] . (x0 + alpha v)[ib], ia and ib three indices."""
    out[0] = 0.0
    out[1] = 0.0
    out[2] = 0.0
    for k in range(3):
        out[0] += v[ia + 3 * k] * v[ib + 3 * k]
        out[1] += x0[ia + 3 * k] * v[ib + 3 * k] + v[ia + 3 * k] * x0[ib + 3 * k]
        out[2] += x0[ia + 3 * k] * x0[ib + 3 * k]


@kernel(**JIT)
def four_ridge_starts(q, u, w, corners, rots, ts):
    """Starting poses from four ridges, whose system A x = b (8 x 9) leaves one free direction: x = x0 +
    alpha v. The rotation constraints |r1| = |r3| = 1, r1 . r3 = 0 violated squared make a quartic in
    alpha; each real root of its derivative is a candidate (the caller refines each and keeps the best).
    Fills rots (3, 3, 3) and ts (3, 3); returns how many."""
    a = np.empty((8, 9))
    b = np.empty(8)
    _system(q, u, w, corners, a, b)
    uu, s, vt = np.linalg.svd(a)
    if not s[7] > s[0] * 1e-12:
        return 0  # rank below 8: more than one free direction
    x0 = np.zeros(9)  # the minimum-norm least-squares solution, as lstsq gives it
    for i in range(8):
        coefficient = 0.0
        for k in range(8):
            coefficient += uu[k, i] * b[k]
        coefficient /= s[i]
        for j in range(9):
            x0[j] += coefficient * vt[i, j]
    v = vt[8].copy()
    quartic = np.zeros(5)
    term = np.empty(3)
    for ia, ib, unit in ((0, 0, 1.0), (1, 1, 1.0), (0, 1, 0.0)):  # r1 is x[0::3], r3 is x[1::3]
        _quadratic_in_alpha(x0, v, ia, ib, term)
        term[2] -= unit
        for i in range(3):
            for j in range(3):
                quartic[i + j] += term[i] * term[j]
    roots = np.empty(3)
    count = _cubic_real_roots(4.0 * quartic[0], 3.0 * quartic[1], 2.0 * quartic[2], quartic[3], roots)
    found = 0
    x = np.empty(9)
    for k in range(count):
        for j in range(9):
            x[j] = x0[j] + roots[k] * v[j]
        if _pose_from_x(x, rots[found], ts[found]) == OK:
            found += 1
    return found


@kernel(**JIT)
def search_minima(q, u, w, corners, corner_cov, weighted, max_iterations, rot, t, cov, rot_out, t_out, r_out,
                  cov_out):
    """The lowest minimum found around the refined pose (rot, t) with covariance cov (over [delta_F, t]).
    Returns (improved, starts tried, iterations of the refinement that found it); when improved the pose,
    its stacked residuals and covariance are in the *_out arrays."""
    n = corners.shape[0]
    best_rot = rot.copy()
    best_t = t.copy()
    best_cov = cov.copy()
    best_cost = _cost(q, u, w, corners, rot, t, corner_cov, weighted)
    improved = False
    iterations = 0
    tried = 0
    capacity = 3 * MAX_SUBSETS + 2 * SEARCH_MODES * len(SEARCH_SCALES)
    start_rots = np.empty((capacity, 3, 3))
    start_ts = np.empty((capacity, 3))
    no_cov = np.empty((0, 0))
    full_cov = np.empty((6, 6))
    costs = np.empty(capacity)
    short_rots = np.empty((capacity, 3, 3))
    short_ts = np.empty((capacity, 3))
    sub_q = np.empty((4, 3))
    sub_u = np.empty(4)
    sub_w = np.empty(4)
    sub_corners = np.empty((4, 2))
    hop = np.empty(6)
    step = np.empty((3, 3))
    starts = 0
    if n >= 5:
        for first in range(min(n, MAX_SUBSETS)):
            for j in range(4):
                i = (first + j) % n
                sub_q[j] = q[i]
                sub_u[j] = u[i]
                sub_w[j] = w[i]
                sub_corners[j] = corners[i]
            starts += four_ridge_starts(sub_q, sub_u, sub_w, sub_corners, start_rots[starts:], start_ts[starts:])
    for round_ in range(SEARCH_ROUNDS + 1):
        if round_ > 0:  # hops along the weak modes of the best so far
            values, vectors = np.linalg.eigh(best_cov)
            starts = 0
            for mode in range(1, SEARCH_MODES + 1):
                size = math.sqrt(max(values[6 - mode], 0.0))
                for scale in SEARCH_SCALES:
                    for sign in (1.0, -1.0):
                        for k in range(6):
                            hop[k] = sign * scale * size * vectors[k, 6 - mode]
                        _so3_exp(hop[:3], step)
                        _matmul3(best_rot, step, start_rots[starts])
                        for k in range(3):
                            start_ts[starts, k] = best_t[k] + hop[3 + k]
                        starts += 1
        tried += starts
        for k in range(starts):  # triage: a few steps from each start
            status, rot2, t2, r2, its, chi2 = _refine(q, u, w, corners, start_rots[k], start_ts[k], corner_cov,
                                                       weighted, TRIAGE_ITERATIONS, False, no_cov, 1)
            short_rots[k] = rot2
            short_ts[k] = t2
            cost = chi2 if weighted else _quadratic(r2, np.eye(2 * n))
            costs[k] = cost if status == OK and math.isfinite(cost) else np.inf
        improved_now = False
        for _ in range(min(TRIAGE_KEEP, starts)):  # the lowest ones (first of equals), refined fully
            k = int(np.argmin(costs[:starts]))
            if not costs[k] < best_cost * TRIAGE_MARGIN:
                break
            costs[k] = np.inf
            status, rot2, t2, r2, its, chi2 = _refine(q, u, w, corners, short_rots[k], short_ts[k], corner_cov,
                                                       weighted, max_iterations, True, full_cov, 1)
            if status != OK:
                continue
            cost = chi2 if weighted else _quadratic(r2, np.eye(2 * n))
            if cost < best_cost * (1.0 - 1e-6):
                best_rot[:, :] = rot2
                best_t[:] = t2
                best_cov[:, :] = full_cov
                r_out[:] = r2
                best_cost, iterations, improved, improved_now = cost, its, True, True
        if round_ > 0 and not improved_now:
            break
    rot_out[:, :] = best_rot
    t_out[:] = best_t
    cov_out[:, :] = best_cov
    return improved, tried, iterations
