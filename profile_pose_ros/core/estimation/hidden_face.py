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
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Callable

import numpy as np

from ..compiled import codes
from ..compiled.codes import MAX_HIDDEN_IN_A_GAP, MIN_RIDGES
from ..model.gauge import Gauge, GaugeError, ridge_lines
from .result import EstimatorOptions, PoseEstimate, reason_outside, rejected

# (outcome, outputs, gauge seen, options, timings) -> the checked estimate: estimator.py's, which owns the kernels'
# outcomes. The gauge seen comes as a function that makes it: only a refusal's words need it, and making a reduced
# gauge (validating it) costs about as much as a profile's estimate
Describe = Callable[[tuple, tuple, Callable[[], Gauge], EstimatorOptions, dict], PoseEstimate]

_NO_TABLES = np.empty((0, 1, 1, 5))  # tries no partial view
_NO_TABLES.setflags(write=False)
_KEPT_OPTIONS = 8


def partial_view_inputs(gauge: Gauge, options: EstimatorOptions) -> tuple:
    """What the compiled estimate (profile_kernel.estimate) needs to try a partial view of `gauge` under `options`:
    the relaxed and unsearched option vectors as rows, the reduced gauges' ridge tables, the precision gate and
    the footprint margin. Made once per gauge and options object, as every profile needs it; no tables when the
    options try no partial view."""
    kept = gauge.__dict__.setdefault("_partial_view_inputs", {})  # beside partial_tables' (Gauge._with_faces)
    entry = kept.get(id(options))  # each entry holds its options: an id in the dict is not reused
    if entry is None:
        if len(kept) >= _KEPT_OPTIONS:  # a process uses a few options objects; more are not kept for ever
            kept.clear()
        partial = options.for_a_partial_view
        vectors = np.stack([_unbounded(partial).kernel_vector, _without_search(partial).kernel_vector])
        vectors.setflags(write=False)
        tables = partial_tables(gauge) if options.hidden_faces and gauge.n_ridges >= MIN_RIDGES + 1 else _NO_TABLES
        entry = kept[id(options)] = (options, (vectors, tables, partial.max_position_sigma, partial.footprint_margin))
    return entry[1]


def partial_view_estimate(outcome: tuple, outputs: tuple, which: tuple, where: np.ndarray, gauge: Gauge,
                          options: EstimatorOptions, describe: Describe, timings: dict) -> PoseEstimate:
    """The estimate of a partial view the compiled estimate decided (its outcome and outputs; which = (kind, a,
    b, verdict), kind not PARTIAL_NONE) for `gauge` under `options`: one or two adjacent faces hidden by a gap,
    faces out of view at the ends, or a refusal saying why."""
    n = gauge.n_ridges
    kind, a, b, verdict = which
    partial = options.for_a_partial_view
    if kind == codes.PARTIAL_AMBIGUOUS:
        return PoseEstimate(False, f"corner detection: found {a} corners; {b} placements of the faces in view "
                                   f"explain the profile (ambiguous)", timings=timings)
    if kind == codes.PARTIAL_IN_VIEW:
        found = describe(outcome, outputs, lambda: gauge.faces_in_view(a, b), _without_search(partial), timings)
        one_hidden = {(1, n): 0, (0, n - 1): n}.get((a, b))
        found.hidden_face, found.faces_hidden, found.faces_in_view = (one_hidden, 0 if one_hidden is None else 1,
                                                                      (a, b))  # found is this call's own
        return found
    return _hidden_in_gap(outcome, outputs, gauge, _unbounded(partial), describe, timings, a, b, verdict, where)


def _hidden_in_gap(outcome: tuple, outputs: tuple, gauge: Gauge, relaxed: EstimatorOptions, describe: Describe,
                   timings: dict, count: int, face: int, verdict: int, where: np.ndarray) -> PoseEstimate:
    """The estimate of the gauge without `count` faces from `face`, which the gap (where[0], where[1]) hid, or
    why not (the verdict, with its numbers in where[2:])."""
    faces = f"face {face}" if count == 1 else f"faces {face}..{face + count - 1}"
    if verdict == codes.VERDICT_PARALLEL:
        return PoseEstimate(False, f"corner detection: {_gap(faces, where)}, but faces {face - 1} and {face + count} "
                                   f"are parallel: without a corner between them the faces seen do not determine "
                                   f"the pose", timings=timings)
    found = describe(outcome, outputs, lambda: gauge.without_face(face, count), relaxed, timings)
    if not found.ok:
        return replace(found, reason=f"{found.reason} (with {_gap(faces, where)})")
    if verdict == codes.VERDICT_OUTSIDE:
        return rejected(found, f"{reason_outside(int(where[2]), where[3], where[4], gauge)} (with "
                               f"{_gap(faces, where)})")
    if verdict == codes.VERDICT_WHERE_POINTS:
        return rejected(found, f"the pose puts {faces} at x {where[2] * 1e3:.1f}..{where[3] * 1e3:.1f} mm, where "
                               f"the profile has points (with {_gap(faces, where)})")
    found.hidden_face, found.faces_hidden = face, count  # found is this call's own
    return found


def _gap(faces: str, where: np.ndarray) -> str:
    """The words for the gap that hid the faces: only a refusal prints them, and an accepted pose is the common
    case on a gap profile."""
    return f"{faces} hidden by the gap at x {where[0] * 1e3:.1f}..{where[1] * 1e3:.1f} mm"


def partial_tables(gauge: Gauge) -> np.ndarray:
    """The ridges [q, u, w] of every gauge a partial view can ask for, as the compiled estimate takes them (read
    only): [count - 1, face, :n - count] those of gauge.without_face(face, count) (NaN where its faces never meet),
    then from row MAX_HIDDEN_IN_A_GAP [MAX_HIDDEN_IN_A_GAP + first, last, :last - first] those of
    gauge.faces_in_view(first, last). Made once per gauge, on its first profile, from the gauge's own ridges and
    the virtual ones in one solve (the same numbers those gauges' validation computes, without making them: a
    gauge's first profile would otherwise wait milliseconds for a dozen of them)."""
    tables = gauge.__dict__.get("_partial_tables")  # kept beside the gauge's own caches (Gauge._with_faces)
    if tables is None:
        n = gauge.n_ridges
        layout = _table_layout(n)
        q, u, w, crossing = ridge_lines(gauge.normals, gauge.offsets, layout.left, layout.right)
        # the gauge's ridges, the virtual ones, then a NaN row: each table entry is one of them
        rows = np.vstack([np.column_stack([gauge.q, gauge.u, gauge.w]), np.column_stack([q, u, w]),
                          np.full((1, 5), np.nan)])
        tables = rows[layout.source]
        never_meet = layout.hypotheses[~crossing]  # faces that never meet leave no gauge: all NaN
        tables[never_meet[:, 0] - 1, never_meet[:, 1]] = np.nan
        tables.setflags(write=False)
        gauge.__dict__["_partial_tables"] = tables
    return tables


@dataclass(frozen=True)
class _TableLayout:
    """Where each entry of an n-ridge gauge's partial tables comes from: source indexes its ridges (0..n-1), the
    virtual ridges between faces left[k] and right[k] of hypothesis k (n + k), or a NaN row (the last)."""
    source: np.ndarray  # (MAX_HIDDEN_IN_A_GAP + n + 1, n + 1, n)
    hypotheses: np.ndarray  # (k, 2): count, face of gauge.without_face(face, count)
    runs: tuple[tuple[int, int], ...]  # first, last of gauge.faces_in_view(first, last)

    @property
    def left(self) -> np.ndarray:
        """The face before each hypothesis's hidden ones."""
        return self.hypotheses[:, 1] - 1

    @property
    def right(self) -> np.ndarray:
        """The face after them."""
        return self.hypotheses[:, 1] + self.hypotheses[:, 0]


@lru_cache(maxsize=16)
def _table_layout(n: int) -> _TableLayout:
    hypotheses = np.array([(count, face) for count in range(1, MAX_HIDDEN_IN_A_GAP + 1) if n - count >= MIN_RIDGES
                           for face in range(1, n - count + 1)], dtype=int).reshape(-1, 2)
    runs = tuple((first, first + shown) for shown in range(MIN_RIDGES, n) for first in range(n - shown + 1))
    nan_row = n + len(hypotheses)
    source = np.full((MAX_HIDDEN_IN_A_GAP + n + 1, n + 1, n), nan_row)
    for k, (count, face) in enumerate(hypotheses):  # ridges before the gap, the virtual one, those after
        source[count - 1, face, :n - count] = [*range(face - 1), n + k, *range(face + count, n)]
    for first, last in runs:
        source[MAX_HIDDEN_IN_A_GAP + first, last, :last - first] = range(first, last)
    for shared in (source, hypotheses):  # one layout serves every gauge of n ridges
        shared.setflags(write=False)
    return _TableLayout(source, hypotheses, runs)


def make_partial_gauges(gauge: Gauge) -> None:
    """Every gauge a partial view's answer names (Gauge.without_face, Gauge.faces_in_view), made before the first
    profile (warm_up): the first answer of each would otherwise wait for its validation."""
    layout = _table_layout(gauge.n_ridges)
    for count, face in layout.hypotheses:
        _gauge_without(gauge, int(face), int(count))
    for first, last in layout.runs:
        gauge.faces_in_view(first, last)


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
