"""Building gauges from designer-friendly numbers: ridge positions, ridge angles and face slopes.

Each top face is a heightfield plane z = a_k x + b_k y + c_k. Given face 0's slopes and, for each ridge i,
its x at y = 0 and its angle from the gauge's y axis, continuity across ridge i fixes face i+1's b and c
from its chosen x-slope a_{i+1}. config/gauge_paper_n5.yaml was made this way.
"""
from __future__ import annotations

import numpy as np

from .gauge import Gauge


def heightfield_gauge(name: str, width: float, length: float, ridge_x: np.ndarray, ridge_angles: np.ndarray,
                      face_slopes: np.ndarray, y_slope0: float = 0.0, min_height: float = 0.015,
                      base_z: float = 0.0) -> Gauge:
    """A validated gauge; raises GaugeError if the numbers do not make one."""
    ridge_x = np.asarray(ridge_x, dtype=float)
    u = np.tan(np.asarray(ridge_angles, dtype=float))
    a = np.asarray(face_slopes, dtype=float)
    if len(a) != len(ridge_x) + 1 or len(u) != len(ridge_x):
        raise ValueError("need n ridge positions, n ridge angles and n+1 face slopes")
    b = np.zeros(len(a))
    c = np.zeros(len(a))
    b[0] = y_slope0
    for i in range(len(ridge_x)):
        b[i + 1] = b[i] + (a[i] - a[i + 1]) * u[i]
        c[i + 1] = c[i] + (a[i] - a[i + 1]) * ridge_x[i]
    xs, ys = np.meshgrid(np.linspace(-width / 2, width / 2, 241), np.linspace(-length / 2, length / 2, 101))
    face = np.sum(ridge_x + u * ys[..., None] < xs[..., None], axis=-1)
    c += base_z + min_height - np.min(a[face] * xs + b[face] * ys + c[face])
    faces = []
    for k in range(len(a)):
        normal = np.array([-a[k], -b[k], 1.0])
        norm = np.linalg.norm(normal)
        faces.append({"normal": (normal / norm).tolist(), "offset": float(c[k] / norm)})
    document = {"gauge": {"name": name, "width": width, "length": length, "base_z": base_z, "faces": faces}}
    return Gauge.from_dict(document, source=name)
