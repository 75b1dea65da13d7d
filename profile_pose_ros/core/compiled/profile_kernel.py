"""A profile's estimate in one compiled call: the whole gauge's, and where its corners cannot be detected (a gap
hides a face, faces lie out of view) the partial view's hypotheses. Both start from one segmentation of the
profile (estimate_kernel._segments), which is most of a detection's time: the hypotheses' detections only merge
its segments again, around the gap they assume.
"""
from __future__ import annotations

import numpy as np

from .codes import JIT, MAX_HIDDEN_IN_A_GAP, MIN_RIDGES, OK, PARTIAL_NONE
from .estimate_kernel import _detect_in, _segments
from .kernel import kernel
from .partial_kernel import estimate_partial
from .pipeline_kernel import _unset, estimate_detected


@kernel(**JIT)
def estimate(points, q, u, w, normals, offsets, ridge_q, ridge_u, width, length, opt, partial_opt, tables, max_sigma,
             margin, corners, rot_out, t_out, cov_out, cf_rot, cf_t, cf_res, res_out, info, where):
    """The whole pipeline. Returns (status, iterations, fit_rms, reprojection_error, cf_reprojection_error,
    position_sigma, search_starts, corners, kind, a, b, verdict), its outputs in the first `corners` rows of
    corners, cf_res and res_out (fewer than the gauge's ridges when part of it was seen). kind says whose:
    PARTIAL_NONE, the whole gauge's (refused by its detection when no hypothesis fits the profile's look);
    otherwise estimate_partial's, with its which (kind, a, b, verdict) and where.

    partial_opt: estimate_partial's relaxed and unsearched vectors as rows; tables: its hidden_table rows
    (MAX_HIDDEN_IN_A_GAP of them) then its view_table rows, none to try no partial view. (Packed: every argument
    is converted on every profile's call.)"""
    # writable copies of the caller's read-only arrays: numba compiles a function once per argument type, and
    # read-only is a type of its own; the hypotheses pass arrays made in the call, so with these the whole
    # pipeline below is compiled once, not once for each
    q, u, w, opt = q.copy(), u.copy(), w.copy(), opt.copy()
    n = u.shape[0]
    segments = _segments(points, opt)
    jac = np.empty((2 * n, 2 * (n + 1)))
    line_var = np.empty(2 * (n + 1))
    status, _, fit_rms = _detect_in(segments, n, opt, corners, jac, line_var, info, np.empty((n + 1, 10)))
    if status == OK:
        return estimate_detected(points, q, u, w, normals, offsets, ridge_q, ridge_u, width, length, opt, corners,
                                 jac, line_var, fit_rms, -1, rot_out, t_out, cov_out, cf_rot, cf_t, cf_res, res_out,
                                 info) + (n, PARTIAL_NONE, 0, 0, 0)
    _unset(rot_out, t_out, cov_out)
    refused = (status, 0, np.nan, np.nan, np.nan, np.nan, 0, n, PARTIAL_NONE, 0, 0, 0)
    if tables.shape[0] == 0 or n < MIN_RIDGES + 1:  # without a face, n - 1 >= MIN_RIDGES must remain
        return refused
    # the refusal's info stays as it is unless a hypothesis decides (estimate_partial writes it only then)
    which = np.zeros(4, dtype=np.int64)
    outcome = estimate_partial(points, segments, q, u, w, normals, offsets, ridge_q, ridge_u, width, length,
                               partial_opt[0].copy(), partial_opt[1].copy(), tables[:MAX_HIDDEN_IN_A_GAP],
                               tables[MAX_HIDDEN_IN_A_GAP:], max_sigma, margin, corners, rot_out, t_out, cov_out,
                               cf_rot, cf_t, cf_res, res_out, info, which, where)
    if which[0] == PARTIAL_NONE:
        return refused
    return outcome + (which[0], which[1], which[2], which[3])
