"""A partial view, inside the profile's one compiled call (profile_kernel.py): the hypotheses of
estimation/hidden_face.py (its docstring says what they are and why), tried in its order, with the checks that
refuse them. Every hypothesis is a detection and an estimate of a few tens of microseconds; run from Python, the
calls between them cost as much again.

The reduced gauges' ridges come in as tables the Python side makes once per gauge (hidden_face.partial_tables),
from the Gauge objects themselves: table[.., :m] holds the m ridges' [q, u, w], NaN where that gauge does not
exist (faces either side of a gap that never meet).
"""
from __future__ import annotations

import math

import numpy as np

from .codes import (GAP_PITCHES, JIT, MAX_HIDDEN_IN_A_GAP, MIN_RIDGES, O_GAP, O_MINSEG, OK, PARTIAL_AMBIGUOUS,
                    PARTIAL_HIDDEN, PARTIAL_IN_VIEW, PARTIAL_NONE, VERDICT_ACCEPTED, VERDICT_IMPRECISE,
                    VERDICT_OUTSIDE, VERDICT_PARALLEL, VERDICT_REFUSED, VERDICT_WHERE_POINTS, WRONG_CORNER_COUNT)
from .estimate_kernel import _detect_in, profile_gaps
from .kernel import kernel
from .pipeline_kernel import estimate_detected

MOST_GAPS = 2  # the widest gaps a profile's hypotheses look at


@kernel(**JIT)
def ridge_x(q, u, w, rot, t, i):
    """x in F where ridge i pierces the laser plane (model.render.true_corners' x, for one ridge)."""
    along = (((t[0] - q[i, 0]) * rot[0, 1] + (t[1] - q[i, 1]) * rot[1, 1] + (t[2] - q[i, 2]) * rot[2, 1]) /
             (u[i] * rot[0, 1] + rot[1, 1] + w[i] * rot[2, 1]))
    return ((q[i, 0] + along * u[i] - t[0]) * rot[0, 0] + (q[i, 1] + along - t[1]) * rot[1, 0] +
            (q[i, 2] + along * w[i] - t[2]) * rot[2, 0])


@kernel(**JIT)
def _ridges_of(table, q, u, w):
    """The m ridges of a reduced gauge's table row into q, u, w; False if that gauge does not exist."""
    if not math.isfinite(table[0, 0]):
        return False
    for i in range(u.shape[0]):
        q[i, 0], q[i, 1], q[i, 2] = table[i, 0], table[i, 1], table[i, 2]
        u[i], w[i] = table[i, 3], table[i, 4]
    return True


@kernel(**JIT)
def _buffers(m):
    """One attempt's arrays for m corners: (corners, jac, line_var, lines, rot, t, cov, cf_rot, cf_t, cf_res, res,
    info), its detection's first and its estimate's after."""
    return (np.empty((m, 2)), np.empty((2 * m, 2 * (m + 1))), np.empty(2 * (m + 1)), np.empty((m + 1, 10)),
            np.empty((3, 3)), np.empty(3), np.empty((6, 6)), np.empty((3, 3)), np.empty(3), np.empty((m, 2)),
            np.empty((m, 2)), np.zeros(4))


@kernel(**JIT)
def _estimate_attempt(points, ridges, normals, offsets, ridge_q, ridge_u, width, length, opt, buffers, fit_rms,
                      virtual):
    """estimate_detected of a reduced gauge (ridges: (q, u, w)) from the detection in buffers, which it reads
    and does not change: the placements of one run of faces all start from it."""
    q, u, w = ridges
    corners, jac, line_var, _, rot, t, cov, cf_rot, cf_t, cf_res, res, _ = buffers
    info = np.zeros(4)
    outcome = estimate_detected(points, q, u, w, normals, offsets, ridge_q, ridge_u, width, length, opt, corners, jac,
                                line_var, fit_rms, virtual, rot, t, cov, cf_rot, cf_t, cf_res, res, info)
    buffers[11][:] = info
    return outcome


@kernel(**JIT)
def _keep(buffers, m, corners, rot_out, t_out, cov_out, cf_rot, cf_t, cf_res, res_out, info):
    """The decisive attempt's outputs into the caller's arrays (sized for the whole gauge: the first m rows)."""
    a_corners, _, _, _, rot, t, cov, a_cf_rot, a_cf_t, a_cf_res, res, a_info = buffers
    corners[:m] = a_corners
    rot_out[:, :] = rot
    t_out[:] = t
    cov_out[:, :] = cov
    cf_rot[:, :] = a_cf_rot
    cf_t[:] = a_cf_t
    cf_res[:m] = a_cf_res
    res_out[:m] = res
    info[:] = a_info


@kernel(**JIT)
def _hidden_verdict(outcome, q, u, w, buffers, virtual, face, count, before, after, tolerance, max_sigma, margin,
                    width, length, where):
    """Whether the pose of a gap's hypothesis stands: refused by its estimate, too poorly determined, a real
    corner off the footprint (where[2:5] = corner, x, y in G), or the hidden faces' ridges where the profile has
    points (where[2:4] = their x range)."""
    if outcome[0] != OK:
        return VERDICT_REFUSED
    if outcome[5] > max_sigma:
        return VERDICT_IMPRECISE
    corners, rot, t = buffers[0], buffers[4], buffers[5]
    half_w, half_l = width / 2 + margin, length / 2 + margin
    for i in range(corners.shape[0]):
        x, z = corners[i, 0], corners[i, 1]
        mapped_x = x * rot[0, 0] + z * rot[0, 2] + t[0]  # the corner [x, 0, z] in G
        mapped_y = x * rot[1, 0] + z * rot[1, 2] + t[1]
        if i != virtual and (abs(mapped_x) > half_w or abs(mapped_y) > half_l):
            where[2], where[3], where[4] = i, mapped_x, mapped_y
            return VERDICT_OUTSIDE
    low, high = np.inf, -np.inf
    for i in range(face - 1, face + count):  # the ridges bounding the hidden faces
        x = ridge_x(q, u, w, rot, t, i)
        low, high = min(low, x), max(high, x)
    if low < before - tolerance or high > after + tolerance:
        where[2], where[3] = low, high
        return VERDICT_WHERE_POINTS
    return VERDICT_ACCEPTED


@kernel(**JIT)
def estimate_partial(points, segments, q, u, w, normals, offsets, ridge_q, ridge_u, width, length, relaxed,
                     unsearched, hidden_table, view_table, max_sigma, margin, corners, rot_out, t_out, cov_out, cf_rot,
                     cf_t, cf_res, res_out, info, which, where):
    """The pose of a profile with faces hidden by a gap or out of view, or a refusal saying why, or nothing.

    segments: the profile's estimate_kernel._segments, which every detection here starts from (relaxed and
    unsearched differ from the options they were made with only in what detection does not read).
    relaxed: the kernel vector for a gap's hypotheses (hidden_face._unbounded); unsearched: for the placements
    of a run of faces in view (hidden_face._without_search); hidden_table[count - 1, face]: the ridges of
    gauge.without_face(face, count); view_table[first, last]: those of gauge.faces_in_view(first, last);
    max_sigma: the precision gate on the published position std; margin: the real corners' footprint margin.
    Returns the decisive estimate's (status, iterations, fit_rms, error, cf_error, sigma, search_starts, corners)
    with its outputs in corners[:corners], rot_out ...; which = (kind, a, b, verdict), where = numbers for the
    reason: PARTIAL_NONE (no hypothesis fits the profile's look: the caller's refusal stands); PARTIAL_HIDDEN
    (a = count, b = face; where = the gap's x before and after, then the verdict's numbers); PARTIAL_IN_VIEW (a, b =
    first, last); PARTIAL_AMBIGUOUS (a = corners seen, b = placements that explain the profile)."""
    n = u.shape[0]
    which[:] = 0
    where[:] = np.nan
    none = (OK, 0, np.nan, np.nan, np.nan, np.nan, 0, 0)
    which[0] = PARTIAL_NONE
    gaps = np.empty((MOST_GAPS, 2))
    valid, found_gaps, pitch = profile_gaps(points, GAP_PITCHES, gaps)
    if valid < 3:
        return none
    # a face that showed fewer points than a segment needs would not have been found either
    tolerance = relaxed[O_MINSEG] * pitch
    # the faces a gap's detection finds do not depend on how many corners it was asked for (only whether that is
    # the count found): once known, the hypotheses that count cannot meet need no detection of their own
    faces_found = np.full(MOST_GAPS, -1)
    vector = relaxed.copy()  # its gap is set per hypothesis
    for count in range(1, MAX_HIDDEN_IN_A_GAP + 1):
        m = n - count
        if m < MIN_RIDGES:
            break
        for k in range(found_gaps):
            if faces_found[k] >= 0 and faces_found[k] != m + 1:
                continue
            before, after = gaps[k, 0], gaps[k, 1]
            # its detection does not merge the faces either side of the gap: the corner between them is virtual
            vector[O_GAP] = 0.5 * (before + after)
            buffers = _buffers(m)
            d_corners, jac, line_var, lines, _, _, _, _, _, _, _, d_info = buffers
            status, _, fit_rms = _detect_in(segments, m, vector, d_corners, jac, line_var, d_info, lines)
            faces_found[k] = m + 1 if status == OK else (int(d_info[1]) if status == WRONG_CORNER_COUNT else -1)
            if faces_found[k] == 0:
                faces_found[k] = -1
            if status != OK:
                continue
            virtual = -1
            for i in range(m):
                if lines[i, 9] <= before and lines[i + 1, 8] >= after:
                    virtual = i
                    break
            if virtual < 0:
                continue
            face = virtual + 1
            which[0], which[1], which[2] = PARTIAL_HIDDEN, count, face
            where[0], where[1] = before, after
            ridges = (np.empty((m, 3)), np.empty(m), np.empty(m))
            if not _ridges_of(hidden_table[count - 1, face], ridges[0], ridges[1], ridges[2]):
                which[3] = VERDICT_PARALLEL
                return none
            outcome = _estimate_attempt(points, ridges, normals, offsets, ridge_q, ridge_u, width, length, vector,
                                        buffers, fit_rms, virtual)
            _keep(buffers, m, corners, rot_out, t_out, cov_out, cf_rot, cf_t, cf_res, res_out, info)
            which[3] = _hidden_verdict(outcome, q, u, w, buffers, virtual, face, count, before, after, tolerance,
                                       max_sigma, margin, width, length, where)
            return outcome + (m,)
    # faces out of view at the ends (the gauge near the edge of the profiler's field, or a gap over the end of
    # the lit span, which may take the next face's few points with it): the lines seen are a run of the gauge's
    # faces, one shorter per corner missing
    m = n - 1
    buffers = _buffers(m)
    status, _, fit_rms = _detect_in(segments, m, unsearched, buffers[0], buffers[1], buffers[2], buffers[11],
                                    buffers[3])
    if status == WRONG_CORNER_COUNT and MIN_RIDGES + 1 <= buffers[11][1] < n:
        m = int(buffers[11][1]) - 1
        buffers = _buffers(m)
        status, _, fit_rms = _detect_in(segments, m, unsearched, buffers[0], buffers[1], buffers[2], buffers[11],
                                        buffers[3])
    if status != OK:
        return none
    lines = buffers[3]
    seen_from, seen_to = lines[0, 8], lines[m, 9]
    accepted = 0
    kept = none
    for first in range(n - m + 1):
        last = first + m
        ridges = (np.empty((m, 3)), np.empty(m), np.empty(m))
        if not _ridges_of(view_table[first, last], ridges[0], ridges[1], ridges[2]):
            continue  # partial_tables makes every run a detection here can see: a table it did not make explains none
        outcome = _estimate_attempt(points, ridges, normals, offsets, ridge_q, ridge_u, width, length, unsearched,
                                    buffers, fit_rms, -1)
        if outcome[0] != OK or outcome[5] > max_sigma:
            continue
        rot, t = buffers[4], buffers[5]
        # the corners of the faces beyond those seen must lie beyond the profile's points
        if first > 0 and ridge_x(q, u, w, rot, t, first - 1) > seen_from + tolerance:
            continue
        if last < n and ridge_x(q, u, w, rot, t, last) < seen_to - tolerance:
            continue
        accepted += 1
        if accepted == 1:
            _keep(buffers, m, corners, rot_out, t_out, cov_out, cf_rot, cf_t, cf_res, res_out, info)
            kept = outcome + (m,)
            which[0], which[1], which[2] = PARTIAL_IN_VIEW, first, last
    if accepted > 1:
        which[0], which[1], which[2] = PARTIAL_AMBIGUOUS, m, accepted
    return kept
