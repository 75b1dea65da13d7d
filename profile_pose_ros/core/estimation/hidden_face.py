"""A face no point falls on: a gap in the profile (an occlusion, a dropout, a dirty patch) wider than a
narrow face hides the face and both its corners, and corner detection finds one corner too few; a gap over
the corner between two narrow faces hides both, and it finds two too few.

The two faces beside the gap are still seen. Their planes cross in a line of the gauge — a virtual ridge —
and their fitted lines cross where that line pierces the laser plane, so the gauge without the hidden faces
(Gauge.without_face) describes the profile exactly and the usual estimator solves it. The corner in the gap
is an extrapolation of the two fits, and its covariance (from the same line-fit Jacobian) says how far.

Which faces are hidden follows from where the gap is: those between the two face fits either side of it.
With no such gap, faces may be out of view at the ends (the gauge near the edge of the profiler's field, or
a gap over the end of the lit span): the faces seen are then a run of the gauge's (Gauge.faces_in_view), every
placement of the run is tried, and only an unambiguous answer is kept. Every answer is checked against the
pose it gives: the full gauge at that pose must put what was not seen where the profile has no points, or
the hypothesis is refused.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace
from functools import lru_cache
from typing import Callable

import numpy as np

from ..compiled import codes
from ..compiled.codes import MAX_HIDDEN_IN_A_GAP, MIN_RIDGES
from ..compiled.loader import kernels
from ..model.gauge import Gauge, GaugeError
from .result import EstimatorOptions, PoseEstimate, reason_outside, rejected

# (outcome, outputs, gauge seen, options, timings) -> the checked estimate: estimator.py's, which owns the kernels'
# outcomes
Describe = Callable[[tuple, tuple, Gauge, EstimatorOptions, dict], PoseEstimate]


def estimate_past_a_hidden_face(points: np.ndarray, gauge: Gauge, options: EstimatorOptions, describe: Describe
                                ) -> PoseEstimate | None:
    """The pose with one or two adjacent faces hidden by a gap or faces out of view at the ends, or a refusal
    saying why not, or None when the profile looks like none of these: the caller's refusal stands."""
    n = gauge.n_ridges
    points = np.ascontiguousarray(points, dtype=np.float64)
    if n < MIN_RIDGES + 1 or points.ndim != 2 or points.shape[1] != 2:  # without a face n - 1 >= MIN_RIDGES remain
        return None
    relaxed, unsearched = _unbounded(options), _without_search(options)
    outputs = (np.empty((n, 2)), np.empty((3, 3)), np.empty(3), np.empty((6, 6)), np.empty((3, 3)), np.empty(3),
               np.empty((n, 2)), np.empty((n, 2)), np.zeros(4))
    which, where = np.zeros(4, dtype=np.int64), np.empty(6)
    start = time.perf_counter()
    *outcome, m = kernels().estimate_partial(points, gauge.q, gauge.u, gauge.w, *gauge.kernel_faces, gauge.width,
                                             gauge.length, relaxed.kernel_vector, unsearched.kernel_vector,
                                             *partial_tables(gauge), options.max_position_sigma,
                                             options.footprint_margin, *outputs, which, where)
    timings = {"total": time.perf_counter() - start}
    kind, a, b, verdict = which.tolist()
    outputs = (outputs[0][:m], *outputs[1:6], outputs[6][:m], outputs[7][:m], outputs[8])
    if kind == codes.PARTIAL_NONE:
        return None
    if kind == codes.PARTIAL_AMBIGUOUS:
        return PoseEstimate(False, f"corner detection: found {a} corners; {b} placements of the faces in view "
                                   f"explain the profile (ambiguous)", timings=timings)
    if kind == codes.PARTIAL_IN_VIEW:
        found = describe(tuple(outcome), outputs, gauge.faces_in_view(a, b), unsearched, timings)
        one_hidden = {(1, n): 0, (0, n - 1): n}.get((a, b))
        return replace(found, hidden_face=one_hidden, faces_hidden=0 if one_hidden is None else 1, faces_in_view=(a, b))
    return _hidden_in_gap(tuple(outcome), outputs, gauge, relaxed, describe, timings, a, b, verdict, where.tolist())


def _hidden_in_gap(outcome: tuple, outputs: tuple, gauge: Gauge, relaxed: EstimatorOptions, describe: Describe,
                   timings: dict, count: int, face: int, verdict: int, where: list[float]) -> PoseEstimate:
    """The estimate of the gauge without `count` faces from `face`, which the gap (where[0], where[1]) hid, or
    why not (the verdict, with its numbers in where[2:])."""
    before, after = where[:2]
    faces = f"face {face}" if count == 1 else f"faces {face}..{face + count - 1}"
    gap = f"{faces} hidden by the gap at x {before * 1e3:.1f}..{after * 1e3:.1f} mm"
    if verdict == codes.VERDICT_PARALLEL:
        return PoseEstimate(False, f"corner detection: {gap}, but faces {face - 1} and {face + count} are parallel: "
                                   f"without a corner between them the faces seen do not determine the pose",
                            timings=timings)
    found = describe(outcome, outputs, _gauge_without(gauge, face, count), relaxed, timings)
    if not found.ok:
        return replace(found, reason=f"{found.reason} (with {gap})")
    if verdict == codes.VERDICT_OUTSIDE:
        return rejected(found, f"{reason_outside(int(where[2]), where[3], where[4], gauge)} (with {gap})")
    if verdict == codes.VERDICT_WHERE_POINTS:
        return rejected(found, f"the pose puts {faces} at x {where[2] * 1e3:.1f}..{where[3] * 1e3:.1f} mm, where "
                               f"the profile has points (with {gap})")
    found.hidden_face, found.faces_hidden = face, count  # found is this call's own
    return found


def partial_tables(gauge: Gauge) -> tuple[np.ndarray, np.ndarray]:
    """The ridges [q, u, w] of every gauge a partial view can ask for, as estimate_partial takes them:
    hidden[count - 1, face, :n - count] of gauge.without_face(face, count) (NaN where its faces never meet), and
    in_view[first, last, :last - first] of gauge.faces_in_view(first, last). Made once per gauge, before the
    first profile (warm_up): each reduced gauge costs a few hundred microseconds to build and validate."""
    tables = gauge.__dict__.get("_partial_tables")  # kept beside the gauge's own caches (Gauge._with_faces)
    if tables is None:
        n = gauge.n_ridges
        hidden, in_view = np.full((MAX_HIDDEN_IN_A_GAP, n + 1, n, 5), np.nan), np.full((n + 1, n + 1, n, 5), np.nan)
        for count in range(1, MAX_HIDDEN_IN_A_GAP + 1):
            for face in range(1, n - count + 1) if n - count >= MIN_RIDGES else ():
                without = _gauge_without(gauge, face, count)
                if without is not None:
                    hidden[count - 1, face, :n - count] = _ridges(without)
        for shown in range(MIN_RIDGES, n):
            for first in range(n - shown + 1):
                in_view[first, first + shown, :shown] = _ridges(gauge.faces_in_view(first, first + shown))
        tables = gauge.__dict__["_partial_tables"] = (hidden, in_view)
    return tables


def _ridges(gauge: Gauge) -> np.ndarray:
    return np.column_stack([gauge.q, gauge.u, gauge.w])


def _gauge_without(gauge: Gauge, face: int, count: int) -> Gauge | None:
    """gauge.without_face(face, count), or None where the faces either side of them are parallel (a symmetric
    gauge): they meet nowhere, so there is no virtual ridge and no corner between them."""
    try:
        return gauge.without_face(face, count)
    except GaugeError:
        return None


@lru_cache(maxsize=8)
def _unbounded(options: EstimatorOptions) -> EstimatorOptions:
    """options for the gauge without the faces a gap hides. The virtual corner may lie far outside the
    footprint (faces nearly parallel): that check is made for the real corners only (partial_kernel's
    _hidden_verdict). Its residual may be large and still within its (extrapolated) covariance: the consistency
    test, which weighs it so, stands for the absolute reprojection bound."""
    return replace(options, footprint_margin=math.inf, max_reprojection_error=math.inf)


@lru_cache(maxsize=8)
def _without_search(options: EstimatorOptions) -> EstimatorOptions:
    """options for a run of faces in view, without the basin search: a placement whose corner pose the checks
    refuse is a wrong placement, whose corners fit no pose of that run (residuals thousands of times the
    noise), and searching around it cost most of a gap profile's slow tail without changing a decision
    (docs/estimator.md, Unclean profiles). Made once per options object, which packs its kernel vector once."""
    return options.with_changes(basin_search=False)
