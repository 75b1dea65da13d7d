"""The renderer's ray trace compiled with numba, for sim_cell at 1 kHz (the numpy trace in render.py is
the reference; a test holds the two equal). One loop over rays instead of whole-array passes per face:
about 20x faster, so the simulated profiler keeps up with its trigger."""
from __future__ import annotations

import numpy as np
from numba import njit

from .gauge import Gauge


@njit(cache=True, fastmath=False)
def _trace(origins, direction, normals, offsets, ridge_q, ridge_u, half_w, half_l, base_z):  # pragma: no cover
    n_rays = origins.shape[0]
    n_faces = offsets.shape[0]
    out = np.full(n_rays, np.nan)
    for i in range(n_rays):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        best = np.inf
        for k in range(n_faces):
            denom = normals[k, 0] * direction[0] + normals[k, 1] * direction[1] + normals[k, 2] * direction[2]
            if denom >= 0:
                continue
            s = (offsets[k] - (normals[k, 0] * ox + normals[k, 1] * oy + normals[k, 2] * oz)) / denom
            if not (s > 0 and s < best):
                continue
            hx = ox + s * direction[0]
            hy = oy + s * direction[1]
            if abs(hx) > half_w or abs(hy) > half_l:
                continue
            if k > 0 and hx < ridge_q[k - 1] + ridge_u[k - 1] * hy:
                continue
            if k < n_faces - 1 and hx > ridge_q[k] + ridge_u[k] * hy:
                continue
            best = s
        for axis in range(2):
            bound = half_w if axis == 0 else half_l
            other_bound = half_l if axis == 0 else half_w
            for sign in (-1.0, 1.0):
                if direction[axis] * sign >= 0:
                    continue
                s = (sign * bound - origins[i, axis]) / direction[axis]
                if not (s > 0 and s < best):
                    continue
                hx = ox + s * direction[0]
                hy = oy + s * direction[1]
                hz = oz + s * direction[2]
                if abs(hy if axis == 0 else hx) > other_bound or hz < base_z:
                    continue
                cx = min(max(hx, -half_w), half_w)
                cy = min(max(hy, -half_l), half_l)
                face = 0
                for r in range(ridge_q.shape[0]):
                    if ridge_q[r] + ridge_u[r] * cy < cx:
                        face += 1
                top = (offsets[face] - normals[face, 0] * cx - normals[face, 1] * cy) / normals[face, 2]
                if hz <= top:
                    best = s
        if best < np.inf:
            out[i] = best
    return out


def trace_depth_fast(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Same contract as render.trace_depth."""
    rotation = np.asarray(rotation, dtype=float)
    origins = np.asarray(translation, dtype=float)[None, :] + x[:, None] * rotation[:, 0][None, :]
    return _trace(np.ascontiguousarray(origins), np.ascontiguousarray(rotation[:, 2]),
                  np.ascontiguousarray(gauge.normals, dtype=float), np.ascontiguousarray(gauge.offsets, dtype=float),
                  np.ascontiguousarray(gauge.q[:, 0], dtype=float), np.ascontiguousarray(gauge.u, dtype=float),
                  gauge.width / 2, gauge.length / 2, float(gauge.base_z))
