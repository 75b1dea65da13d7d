"""Ramer-Douglas-Peucker simplification of a profile polyline (corner candidates, paper II-D)."""
from __future__ import annotations

import numpy as np


def rdp_vertices(points: np.ndarray, epsilon: float) -> np.ndarray:
    """Sorted indices of the vertices RDP keeps (always the first and the last point).

    Iterative with an explicit stack, so a noisy 3,200-point profile cannot hit the recursion limit.
    """
    n = len(points)
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        first, last = stack.pop()
        if last - first < 2:
            continue
        a = points[first]
        chord = points[last] - a
        length = np.hypot(chord[0], chord[1])
        rel = points[first + 1:last] - a
        if length > 0:
            dist = np.abs(chord[0] * rel[:, 1] - chord[1] * rel[:, 0]) / length
        else:
            dist = np.hypot(rel[:, 0], rel[:, 1])
        i = int(np.argmax(dist))
        if dist[i] > epsilon:
            split = first + 1 + i
            keep[split] = True
            stack.append((first, split))
            stack.append((split, last))
    return np.nonzero(keep)[0]
