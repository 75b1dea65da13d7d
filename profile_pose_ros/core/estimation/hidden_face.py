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
from dataclasses import replace
from functools import lru_cache
from typing import Callable

import numpy as np

from ..compiled import codes
from ..compiled.loader import kernels
from ..model.gauge import Gauge, GaugeError
from .corners import CornerResult
from .result import EstimatorOptions, PoseEstimate, reason_outside, rejected
from .stages import detect_with

# a run between two valid points wider than this many point pitches is a gap, not the profiler's spacing
GAP_PITCHES = 3.0
MIN_RIDGES = 4  # the fewest the estimator solves: a gauge seen in part must keep as many
# the most adjacent faces one gap may hide: two narrow faces side by side under a gap over their corner
MAX_HIDDEN_IN_A_GAP = 2


def profile_gaps(points: np.ndarray, most: int = 2) -> tuple[int, float, list[tuple[float, float]]]:
    """(valid points, their usual x spacing, (x before, x after) of up to `most` gaps between them, widest
    first); the points' x increasing."""
    gaps = np.empty((most, 2))
    valid, found, pitch = kernels().profile_gaps(np.ascontiguousarray(points, dtype=np.float64), GAP_PITCHES, gaps)
    return int(valid), float(pitch), [(float(before), float(after)) for before, after in gaps[:found]]


def estimate_past_a_hidden_face(points: np.ndarray, gauge: Gauge, options: EstimatorOptions,
                                estimate: Callable[[np.ndarray, Gauge, EstimatorOptions], PoseEstimate]
                                ) -> PoseEstimate | None:
    """The pose with one or two adjacent faces hidden by a gap or faces out of view at the ends, or a refusal
    saying why not, or None when the profile looks like none of these: the caller's refusal stands."""
    n = gauge.n_ridges
    points = np.ascontiguousarray(points, dtype=np.float64)
    if n < MIN_RIDGES + 1 or points.ndim != 2 or points.shape[1] != 2:  # without a face n - 1 >= MIN_RIDGES remain
        return None
    valid, pitch, gaps = profile_gaps(points)
    if valid < 3:
        return None
    # a face that showed fewer points than a segment needs would not have been found either
    tolerance = options.corners.min_segment_points * pitch
    relaxed = _unbounded(options)
    vectors: list[np.ndarray | None] = [None] * len(gaps)  # made when a gap's detection is first needed
    # the faces a gap's detection finds do not depend on how many corners it was asked for (only whether that
    # is the count found): once known, the hypotheses that count cannot meet need no detection of their own
    faces_found: list[int | None] = [None] * len(gaps)
    for count in range(1, MAX_HIDDEN_IN_A_GAP + 1):
        if n - count < MIN_RIDGES:
            break
        for k, (before, after) in enumerate(gaps):
            if faces_found[k] is not None and faces_found[k] != n + 1 - count:
                continue
            if vectors[k] is None:
                vectors[k] = _vector_for_a_gap(relaxed, before, after)
            detection = detect_with(points, n - count, vectors[k], relaxed.corners)
            faces_found[k] = len(detection.lines) if detection.ok else detection.faces_found or None
            found = _with_faces_hidden_in_gap(points, gauge, options, relaxed, vectors[k], detection, estimate,
                                              before, after, tolerance, count)
            if found is not None:
                return found
    # faces out of view at the ends (the gauge near the edge of the profiler's field, or a gap over the end of
    # the lit span, which may take the next face's few points with it): the lines seen are a run of the
    # gauge's faces, one shorter per corner missing
    unsearched = _without_search(options)
    detection = detect_with(points, n - 1, unsearched.kernel_vector, options.corners)
    if not detection.ok and MIN_RIDGES + 1 <= detection.faces_found < n:
        detection = detect_with(points, detection.faces_found - 1, unsearched.kernel_vector, options.corners)
    if not detection.ok:
        return None
    seen = (detection.lines[0].x_min, detection.lines[-1].x_max)
    shown = len(detection.lines) - 1  # faces first..first + shown are in view
    runs = [_with_faces_out_of_view(points, gauge, unsearched, estimate, detection, first, first + shown, seen,
                                    tolerance) for first in range(n - shown + 1)]
    accepted = [found for found in runs if found.ok]
    if len(accepted) == 1:
        return accepted[0]
    if len(accepted) > 1:
        return PoseEstimate(False, f"corner detection: found {shown} corners; {len(accepted)} placements of the "
                                   f"faces in view explain the profile (ambiguous)", timings=accepted[0].timings)
    return None


def prepare_partial_views(gauge: Gauge, options: EstimatorOptions) -> int:
    """Make, before the first profile, every reduced gauge and options object a partial view can ask for (each
    made once per gauge and kept): a gauge costs a few hundred microseconds to build and validate, which the
    first profile to need it would otherwise pay. Returns how many gauges."""
    n = gauge.n_ridges
    _without_search(options)
    made = 0
    for count in range(1, MAX_HIDDEN_IN_A_GAP + 1):
        for face in range(1, n - count + 1) if n - count >= MIN_RIDGES else ():
            made += _gauge_without(gauge, face, count) is not None
    for shown in range(MIN_RIDGES, n):
        for first in range(n - shown + 1):
            gauge.faces_in_view(first, first + shown)  # the gauge's own ridges: it always exists
            made += 1
    return made


def _gauge_without(gauge: Gauge, face: int, count: int) -> Gauge | None:
    """gauge.without_face(face, count), or None where the faces either side of them are parallel (a symmetric
    gauge): they meet nowhere, so there is no virtual ridge and no corner between them."""
    try:
        return gauge.without_face(face, count)
    except GaugeError:
        return None


def _vector_for_a_gap(relaxed: EstimatorOptions, before: float, after: float) -> np.ndarray:
    """The kernel vector of `relaxed` (_unbounded) with the gap (before, after) marked: its detection does not
    merge the faces either side of it, and the corner between them is virtual. Set in a copy of the vector
    rather than made as an options object, whose validation and packing cost more than the rest of a
    hypothesis' Python on every gap profile."""
    vector = relaxed.kernel_vector.copy()
    vector[codes.O_GAP] = 0.5 * (before + after)
    return vector


@lru_cache(maxsize=8)
def _unbounded(options: EstimatorOptions) -> EstimatorOptions:
    """options for the gauge without the faces a gap hides. The virtual corner may lie far outside the
    footprint (faces nearly parallel): that check is made for the real corners only (_outside_footprint). Its
    residual may be large and still within its (extrapolated) covariance: the consistency test, which weighs
    it so, stands for the absolute reprojection bound."""
    return replace(options, footprint_margin=math.inf, max_reprojection_error=math.inf)


@lru_cache(maxsize=8)
def _without_search(options: EstimatorOptions) -> EstimatorOptions:
    """options for a run of faces in view, without the basin search: a placement whose corner pose the checks
    refuse is a wrong placement, whose corners fit no pose of that run (residuals thousands of times the
    noise), and searching around it cost most of a gap profile's slow tail without changing a decision
    (docs/estimator.md, Unclean profiles). Made once per options object, which packs its kernel vector once."""
    return options.with_changes(basin_search=False)


def _with_faces_hidden_in_gap(points: np.ndarray, gauge: Gauge, options: EstimatorOptions,
                              relaxed: EstimatorOptions, vector: np.ndarray, detection: CornerResult,
                              estimate: Callable, before: float, after: float, tolerance: float,
                              count: int) -> PoseEstimate | None:
    """The pose with `count` adjacent faces hidden by the gap (before, after), or None when the faces found
    either side of it (detection, with the relaxed options and the gap's kernel vector) do not leave that
    many out."""
    n = gauge.n_ridges
    if not detection.ok:
        return None
    lines = detection.lines
    virtual = next((i for i in range(n - count) if lines[i].x_max <= before and lines[i + 1].x_min >= after), None)
    if virtual is None:
        return None
    face = virtual + 1
    faces = f"face {face}" if count == 1 else f"faces {face}..{face + count - 1}"
    where = f"{faces} hidden by the gap at x {before * 1e3:.1f}..{after * 1e3:.1f} mm"
    without = _gauge_without(gauge, face, count)
    if without is None:
        return PoseEstimate(False, f"corner detection: {where}, but faces {face - 1} and {face + count} are parallel: "
                                   f"without a corner between them the faces seen do not determine the pose")
    found = estimate(points, without, relaxed, vector=vector, detection=detection)
    if not found.ok:
        return replace(found, reason=f"{found.reason} (with {where})")
    hidden = _ridge_x(gauge, found.R, found.t, face - 1, face + count)  # the ridges bounding them
    reason = _outside_footprint(found, virtual, gauge, options)
    if not reason and (min(hidden) < before - tolerance or max(hidden) > after + tolerance):
        reason = (f"the pose puts {faces} at x {min(hidden) * 1e3:.1f}..{max(hidden) * 1e3:.1f} mm, where "
                  f"the profile has points")
    if reason:
        return rejected(found, f"{reason} (with {where})")
    found.hidden_face, found.faces_hidden = face, count  # found is this call's own
    return found


def _with_faces_out_of_view(points: np.ndarray, gauge: Gauge, options: EstimatorOptions, estimate: Callable,
                            detection: CornerResult, first: int, last: int, seen: tuple[float, float],
                            tolerance: float) -> PoseEstimate:
    """The pose with only faces first..last in view (their corners: detection, with options): the corners of
    the faces beyond them must lie beyond the faces seen (x span `seen`)."""
    found = estimate(points, gauge.faces_in_view(first, last), options, detection=detection)
    if not found.ok:
        return found
    ridges = _ridge_x(gauge, found.R, found.t, 0, gauge.n_ridges)
    if first > 0 and ridges[first - 1] > seen[0] + tolerance:
        return rejected(found, f"the pose puts the corner left of face {first} at x {ridges[first - 1] * 1e3:.1f} "
                               f"mm, where the profile has points")
    if last < gauge.n_ridges and ridges[last] < seen[1] - tolerance:
        return rejected(found, f"the pose puts the corner right of face {last} at x {ridges[last] * 1e3:.1f} mm, "
                               f"where the profile has points")
    one_hidden = {(1, gauge.n_ridges): 0, (0, gauge.n_ridges - 1): gauge.n_ridges}.get((first, last))
    return replace(found, hidden_face=one_hidden, faces_hidden=0 if one_hidden is None else 1,
                   faces_in_view=(first, last))


def _outside_footprint(found: PoseEstimate, virtual: int, gauge: Gauge, options: EstimatorOptions) -> str:
    """Why the first real corner of the pose lies off the gauge's footprint, or "" (the virtual corner may lie far
    out when its faces are nearly parallel). In plain floats, as _ridge_x."""
    (r00, _, r02), (r10, _, r12), _ = found.R.tolist()
    t0, t1, _ = found.t.tolist()
    half_w, half_l = gauge.width / 2 + options.footprint_margin, gauge.length / 2 + options.footprint_margin
    for i, (x, z) in enumerate(found.corners.tolist()):
        mapped_x, mapped_y = x * r00 + z * r02 + t0, x * r10 + z * r12 + t1  # the corner [x, 0, z] in G
        if i != virtual and (abs(mapped_x) > half_w or abs(mapped_y) > half_l):
            return reason_outside(i, mapped_x, mapped_y, gauge)
    return ""


def _ridge_x(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, first: int, stop: int) -> list[float]:
    """x in F where ridges first..stop - 1 pierce the laser plane (render.true_corners' x, for those alone: a
    hypothesis checks a few ridges of its pose on every gap profile; in plain floats, which numpy's per-call
    cost outweighs at this size)."""
    (r00, r01, _), (r10, r11, _), (r20, r21, _) = rotation.tolist()
    t0, t1, t2 = translation.tolist()
    xs = []
    for (q0, q1, q2), u, w in zip(gauge.q[first:stop].tolist(), gauge.u[first:stop].tolist(),
                                  gauge.w[first:stop].tolist()):
        along = ((t0 - q0) * r01 + (t1 - q1) * r11 + (t2 - q2) * r21) / (u * r01 + r11 + w * r21)
        xs.append((q0 + along * u - t0) * r00 + (q1 + along - t1) * r10 + (q2 + along * w - t2) * r20)
    return xs
