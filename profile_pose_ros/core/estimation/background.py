"""The gauge's own span in a profile that also sees what the gauge stands on.

In a cell the laser line is wider than the gauge: beside it lie the table, the fixture's plate or a clamp, and
their segments are faces to corner detection ("found n + 3 corners", or a side wall between faces). The gauge
stands proud of them, so its span is bounded by depth steps: a side wall the laser lights (a run of near-vertical
points) or a shadow the wall casts (a gap with a drop across it). The span is the run between the steps nearest
to the sensor's nearest point, which lies on the gauge's top; everything beyond is background.

Used only when corner detection refused a profile for too many faces or a steep segment between them, so no
profile the estimator accepted without it changes; whatever it keeps still passes every check a pose passes.
"""
from __future__ import annotations

import math

import numpy as np

MIN_STEP = 1e-3  # m; a depth change smaller than this is not taken for the gauge's edge (glints are smaller or
# single points, and the median of five below takes those)


def without_background(points: np.ndarray, max_face_angle: float) -> np.ndarray | None:
    """points with everything beyond the gauge's edges set to NaN, or None when no edge is found (nothing to cut).
    An edge is a run of steps between consecutive valid points (median of five, so glints do not make them)
    steeper than max_face_angle (rad; no face shows so steep) whose depth changes by more than MIN_STEP."""
    valid = np.flatnonzero(np.isfinite(points[:, 0]) & np.isfinite(points[:, 1]))
    if valid.size < 5:
        return None
    x, z = points[valid, 0], _median_of_five(points[valid, 1])
    steep = np.abs(np.diff(z)) > math.tan(max_face_angle) * np.abs(np.diff(x))
    change = np.diff(np.concatenate(([0], steep.astype(np.int8), [0])))
    steps = [(start, end) for start, end in zip(np.flatnonzero(change == 1), np.flatnonzero(change == -1))
             if abs(z[end] - z[start]) > MIN_STEP]  # a run of steep pairs from point start to point end
    nearest = int(np.argmin(z))
    first = max((end for start, end in steps if end <= nearest), default=0)
    last = min((start for start, end in steps if start >= nearest), default=valid.size - 1)
    if first == 0 and last == valid.size - 1:
        return None
    kept = points.copy()
    kept[valid[:first]] = np.nan
    kept[valid[last + 1:]] = np.nan
    return kept


def _median_of_five(z: np.ndarray) -> np.ndarray:
    """Each value's median with its two neighbours either side (the ends repeated), by min and max: of two pairs'
    smaller values the least has three above it and of their larger ones the greatest three below, so neither
    is the median, which is then the median of the other two and the fifth value (np.median: several times
    slower)."""
    padded = np.concatenate((z[:1], z[:1], z, z[-1:], z[-1:]))
    a, b, c, d, e = (padded[k:k + z.size] for k in range(5))
    low = np.maximum(np.minimum(a, b), np.minimum(c, d))
    high = np.minimum(np.maximum(a, b), np.maximum(c, d))
    return np.maximum(np.minimum(low, high), np.minimum(np.maximum(low, high), e))
