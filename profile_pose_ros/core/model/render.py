"""Profile renderer: what a laser profiler at pose (R, t) sees of a gauge.

This is the ground truth for every test and study, so it is exact rather than fast: each sample
column x of the profiler frame F is a ray along +z_F (the controller resamples the line to a fixed x
grid), traced against every top face and the four side walls of the gauge solid; the first surface hit
wins. The laser fan then shadows points that a closer part of the surface hides from the emitter
(self-occlusion, paper Fig. 4b), and the trapezoidal measurement range blanks the rest. Occlusion of
the camera's view (out of the laser plane) is not modelled.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .gauge import Gauge


@dataclass(frozen=True)
class ProfilerModel:
    """Sampling grid and measurement range of a line profiler; defaults: Keyence LJ-X8400."""

    n_points: int = 3200
    x_pitch: float = 75e-6
    z_near: float = 0.285
    z_far: float = 0.600
    width_near: float = 0.163
    width_far: float = 0.320
    occlusion: bool = True

    @property
    def x_start(self) -> float:
        return -0.5 * (self.n_points - 1) * self.x_pitch

    @cached_property
    def x(self) -> np.ndarray:
        """The sample columns' x (read-only: one array shared by every render, not rebuilt for each)."""
        x = self.x_start + self.x_pitch * np.arange(self.n_points)
        x.setflags(write=False)
        return x

    @property
    def fan_slope(self) -> float:
        """How fast the measurement range's half width grows with z (the trapezoid's sides)."""
        return (self.width_far - self.width_near) / (2.0 * (self.z_far - self.z_near))

    def half_width(self, z: np.ndarray) -> np.ndarray:
        return 0.5 * self.width_near + self.fan_slope * (np.asarray(z) - self.z_near)

    @property
    def emitter_z(self) -> float:
        """The laser fan's apex: where the trapezoid's sides meet (on the z axis)."""
        return self.z_near - 0.5 * self.width_near / self.fan_slope

    def in_range(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        return (z >= self.z_near) & (z <= self.z_far) & (np.abs(x) <= self.half_width(z))


DEFAULT_PROFILER = ProfilerModel()


def trace_depth(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Depth z_F of the first surface hit for each ray x_F (NaN where the ray misses the gauge)."""
    rotation = np.asarray(rotation, dtype=float)
    origins = np.asarray(translation, dtype=float)[None, :] + x[:, None] * rotation[:, 0][None, :]
    direction = rotation[:, 2]
    best = np.full(len(x), np.inf)

    half_w, half_l = gauge.width / 2, gauge.length / 2
    n_faces = len(gauge.offsets)
    ridge_q, ridge_u = gauge.q[:, 0], gauge.u
    for k in range(n_faces):
        normal = gauge.normals[k]
        denom = normal @ direction
        if denom >= 0:  # the ray can only leave through this face, never enter
            continue
        s = (gauge.offsets[k] - origins @ normal) / denom
        hx = origins[:, 0] + s * direction[0]
        hy = origins[:, 1] + s * direction[1]
        ok = (s > 0) & (s < best) & (np.abs(hx) <= half_w) & (np.abs(hy) <= half_l)
        if k > 0:  # right of ridge k-1 ...
            ok &= hx >= ridge_q[k - 1] + ridge_u[k - 1] * hy
        if k < n_faces - 1:  # ... and left of ridge k
            ok &= hx <= ridge_q[k] + ridge_u[k] * hy
        best = np.where(ok, s, best)

    # Side walls x = +-W/2 and y = +-L/2, from the base up to the top surface.
    for axis, bound in ((0, half_w), (1, half_l)):
        other = 1 - axis
        other_bound = half_l if axis == 0 else half_w
        for sign in (-1.0, 1.0):
            if direction[axis] * sign >= 0:  # must travel inwards to enter
                continue
            s = (sign * bound - origins[:, axis]) / direction[axis]
            hit = origins + s[:, None] * direction
            maybe = np.nonzero((s > 0) & (s < best) & (np.abs(hit[:, other]) <= other_bound)
                               & (hit[:, 2] >= gauge.base_z))[0]  # few rays reach a wall: test only those
            if len(maybe):
                h = hit[maybe]
                top = gauge.surface_z(np.clip(h[:, 0], -half_w, half_w), np.clip(h[:, 1], -half_l, half_l))
                best[maybe[h[:, 2] <= top]] = s[maybe[h[:, 2] <= top]]
    best[~np.isfinite(best)] = np.nan
    return best


def shadow_mask(x: np.ndarray, z: np.ndarray, emitter_z: float) -> np.ndarray:
    """True where a point is hidden from the emitter at (0, emitter_z) by a point closer to it.

    Walking outwards from the emitter's column, a point is lit only if its ray angle is not smaller
    than that of any valid point before it (a running maximum, so O(N)).
    """
    angle = np.arctan2(x, z - emitter_z)
    hidden = np.zeros(len(x), dtype=bool)
    valid = np.isfinite(angle)
    right = np.nonzero(valid & (x >= 0))[0]  # ascending x: walking away from the emitter
    left = np.nonzero(valid & (x < 0))[0][::-1]  # descending x
    for order, sign in ((right, 1.0), (left, -1.0)):
        if len(order):
            a = sign * angle[order]
            hidden[order] = a < np.maximum.accumulate(a) - 1e-12
    return hidden


def visible_depth(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, profiler: ProfilerModel,
                  trace=None) -> np.ndarray:
    """Noise-free z of every column the profiler reports (NaN elsewhere): the trace, less what the
    emitter cannot light and what lies outside the measurement range."""
    x = profiler.x
    z = (trace or trace_depth)(gauge, rotation, translation, x)
    if profiler.occlusion:
        z[shadow_mask(x, z, profiler.emitter_z)] = np.nan
    z[~profiler.in_range(x, z)] = np.nan
    return z


def render_profile(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray, *,
                   noise_std: float = 0.0, rng: np.random.Generator | None = None,
                   spike_fraction: float = 0.0, spike_range: tuple[float, float] = (2e-4, 2e-3),
                   profiler: ProfilerModel = DEFAULT_PROFILER, trace=None, depth=None) -> np.ndarray:
    """(N, 2) array of [x, z] in metres in frame F, NaN where the profiler reports no point.

    Noise is Gaussian on z (the profiler's depth repeatability); spikes replace a fraction of the
    valid points by z +- U(spike_range), as specular glints do. `trace` replaces trace_depth (the
    study passes the compiled one of compiled/render_kernel.py); `depth` replaces visible_depth (sim_cell passes
    render_kernel's, which does all of it in one compiled pass).
    """
    if rng is None:
        rng = np.random.default_rng()
    x = profiler.x
    z = depth(gauge, rotation, translation, profiler) if depth is not None else \
        visible_depth(gauge, rotation, translation, profiler, trace)
    valid = np.isfinite(z)
    if noise_std > 0:
        z[valid] += rng.normal(0.0, noise_std, int(valid.sum()))
    if spike_fraction > 0:
        idx = np.nonzero(valid)[0]
        chosen = rng.choice(idx, size=int(round(spike_fraction * len(idx))), replace=False)
        magnitude = rng.uniform(spike_range[0], spike_range[1], len(chosen))
        z[chosen] += magnitude * rng.choice([-1.0, 1.0], len(chosen))
    return np.column_stack([x, z])


def true_corners(gauge: Gauge, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Exact corners in F: where each ridge pierces the laser plane (the F x-z plane)."""
    rotation = np.asarray(rotation, dtype=float)
    translation = np.asarray(translation, dtype=float)
    r2 = rotation[:, 1]
    directions = gauge.directions
    lam = ((translation - gauge.q) @ r2) / (directions @ r2)
    points = gauge.q + lam[:, None] * directions
    local = (points - translation) @ rotation  # rows: R^T (p - t)
    return local[:, [0, 2]]
