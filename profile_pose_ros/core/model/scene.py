"""What a viewer (RViz, Foxglove) draws of the cell: the gauge as triangles and a profile laid on it.

Both in the gauge frame G, so the scan shows where the estimate put it: a profile that sits on the gauge's
faces is a pose that explains the scan; one that floats or cuts through is not.
"""
from __future__ import annotations

import numpy as np

from .gauge import Gauge
from .gauge_mesh import gauge_mesh

# A viewer's marker is a list of message points, built one by one in Python: a whole 3,200-point profile
# costs milliseconds per message, and a few hundred points show its shape as well.
MAX_PROFILE_MARKER_POINTS = 640


def gauge_triangles(gauge: Gauge) -> np.ndarray:
    """(3k, 3) vertices of the gauge solid's k triangles, three per triangle, outward winding (G, m)."""
    mesh = gauge_mesh(gauge)
    return np.asarray(mesh.vertices)[np.asarray(mesh.faces)].reshape(-1, 3)


def profile_in_gauge(points_xz: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                     max_points: int = MAX_PROFILE_MARKER_POINTS) -> np.ndarray:
    """(M, 3) profile points in G (p_G = R p_F + t; the laser plane is F's x-z plane), every k-th valid
    point so that M <= max_points; invalid (NaN) points left out."""
    valid = points_xz[np.isfinite(points_xz).all(axis=1)]
    step = max(1, -(-len(valid) // max(1, max_points)))
    xz = valid[::step]
    in_f = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    return in_f @ np.asarray(rotation).T + np.asarray(translation)
