"""The renderer's ray trace compiled with numba, for sim_cell at 1 kHz (the numpy trace in render.py is
the reference; tests hold the two equal). One loop over rays instead of whole-array passes per face, so
the simulated profiler keeps up with its trigger (docs/design_notes.md). `visible_depth_fast` adds the
emitter's shadow and the measurement range in the same compiled call."""
from __future__ import annotations

import numpy as np

from ..model.gauge import Gauge
from ..model.render import ProfilerModel
from .kernel import kernel


@kernel(cache=True, fastmath=False)
def _trace(x, t, r0, direction, normals, offsets, ridge_q, ridge_u, half_w, half_l, base_z):  # pragma: no cover
    """Ray i starts at t + x[i] r0. Per face, what does not depend on the ray is computed once:
    the ray's slope to the face and the face's distance along it as a + x b (3x fewer flops)."""
    n_rays = x.shape[0]
    n_faces = offsets.shape[0]
    denom = np.empty(n_faces)
    at_origin = np.empty(n_faces)
    per_x = np.empty(n_faces)
    for k in range(n_faces):
        denom[k] = normals[k, 0] * direction[0] + normals[k, 1] * direction[1] + normals[k, 2] * direction[2]
        at_origin[k] = offsets[k] - (normals[k, 0] * t[0] + normals[k, 1] * t[1] + normals[k, 2] * t[2])
        per_x[k] = normals[k, 0] * r0[0] + normals[k, 1] * r0[1] + normals[k, 2] * r0[2]
    out = np.full(n_rays, np.nan)
    for i in range(n_rays):
        ox, oy, oz = t[0] + x[i] * r0[0], t[1] + x[i] * r0[1], t[2] + x[i] * r0[2]
        best = np.inf
        for k in range(n_faces):
            if denom[k] >= 0:
                continue
            s = (at_origin[k] - x[i] * per_x[k]) / denom[k]
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
                s = (sign * bound - (ox if axis == 0 else oy)) / direction[axis]
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


@kernel(cache=True, fastmath=False)
def _shadow_and_range(x, z, occlusion, emitter_z, z_near, z_far, half_near, half_slope):  # pragma: no cover
    """render.shadow_mask (if occlusion) and ProfilerModel.in_range, in place, with the same arithmetic;
    x ascending."""
    n = x.shape[0]
    if occlusion:
        angle = np.arctan2(x, z - emitter_z)
        first_right = 0
        while first_right < n and x[first_right] < 0:
            first_right += 1
        for start, stop, step, sign in ((first_right, n, 1, 1.0), (first_right - 1, -1, -1, -1.0)):
            running = -np.inf
            for i in range(start, stop, step):
                if not np.isfinite(angle[i]):
                    continue
                a = sign * angle[i]
                running = max(running, a)
                if a < running - 1e-12:
                    z[i] = np.nan
    for i in range(n):
        zi = z[i]
        if not (zi >= z_near and zi <= z_far and abs(x[i]) <= half_near + half_slope * (zi - z_near)):
            z[i] = np.nan
    return z


def visible_depth_fast(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray,
                       profiler: ProfilerModel) -> np.ndarray:
    """Same contract as render.visible_depth (which stays the reference)."""
    x = profiler.x
    z = trace_depth_fast(gauge, rotation, translation, x)
    return _shadow_and_range(x, z, profiler.occlusion, profiler.emitter_z, profiler.z_near, profiler.z_far,
                             0.5 * profiler.width_near, profiler.fan_slope)


def trace_depth_fast(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Same contract as render.trace_depth."""
    rotation = np.asarray(rotation, dtype=float)
    return _trace(np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(translation, dtype=float),
                  np.ascontiguousarray(rotation[:, 0]), np.ascontiguousarray(rotation[:, 2]),
                  np.ascontiguousarray(gauge.normals, dtype=float), np.ascontiguousarray(gauge.offsets, dtype=float),
                  np.ascontiguousarray(gauge.q[:, 0], dtype=float), np.ascontiguousarray(gauge.u, dtype=float),
                  gauge.width / 2, gauge.length / 2, float(gauge.base_z))
