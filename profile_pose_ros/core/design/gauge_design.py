"""Building gauges from designer-friendly numbers: ridge positions, ridge angles and face slopes.

Each top face is a heightfield plane z = a_k x + b_k y + c_k. Given face 0's slopes and, for each ridge i,
its x at y = 0 and its angle from the gauge's y axis, continuity across ridge i fixes face i+1's b and c
from its chosen x-slope a_{i+1}. config/gauge_paper_n5.yaml was made this way.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.gauge import Gauge


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


@dataclass(frozen=True)
class RandomGaugeRules:
    """The paper's random-gauge protocol (III-B) with fabrication limits (III-D)."""

    width: float = 0.120
    length: float = 0.100
    max_face_angle_deg: float = 40.0  # steepest face from horizontal (occlusion limit: beta >= 50 deg)
    min_face_angle_deg: float = 15.0  # flatter faces give weak corners
    max_ridge_angle_deg: float = 20.0  # ridge direction from the gauge's y axis
    min_ridge_separation_deg: float = 3.0  # at least 4 ridges pairwise this far apart in direction: two
    # nearly parallel ridges carry one ridge's information about the tilt, and a gauge with fewer than four
    # distinct directions has cost minima centimetres apart that no start can tell apart reliably
    min_face_width: float = 0.004  # m, everywhere along the gauge
    max_relief: float = 0.045  # m


def face_widths(gauge: Gauge) -> np.ndarray:
    """Width of every face at both ends of the gauge (faces are planar, so the extremes are there)."""
    ys = np.array([-gauge.length / 2, gauge.length / 2])
    ridges = gauge.ridge_x(ys)
    edges = np.column_stack([np.full(2, -gauge.width / 2), ridges, np.full(2, gauge.width / 2)])
    return np.diff(edges, axis=1)


def distinct_directions(angles: np.ndarray, separation_deg: float) -> int:
    """Most ridges (angles in rad) that are pairwise at least separation_deg apart (greedy, optimal in 1-D)."""
    count, last = 0, -np.inf
    for angle in np.sort(np.degrees(np.asarray(angles, dtype=float))):
        if angle >= last + separation_deg:
            count, last = count + 1, angle
    return count


def random_gauge(n_ridges: int, rng: np.random.Generator, rules: RandomGaugeRules = RandomGaugeRules(),
                 check_poses: int = 5, max_tries: int = 500) -> Gauge:
    """A valid random gauge with n ridges whose corners are all visible over the pose range."""
    from ..model.gauge import GaugeError
    from ..model.poses import sample_pose

    free = rules.width - (n_ridges + 1) * rules.min_face_width
    if free <= 0:
        raise ValueError(f"{n_ridges} ridges with faces >= {rules.min_face_width} m do not fit in {rules.width} m")

    def ends() -> np.ndarray:
        """Ridge x at one end of the gauge: sorted, every face at least min_face_width wide."""
        steps = rules.min_face_width * np.arange(1, n_ridges + 1)
        return -rules.width / 2 + steps + np.sort(rng.uniform(0.0, free, n_ridges))

    for attempt in range(max_tries):
        near, far = ends(), ends()  # at y = -length/2 and y = +length/2: faces never cross
        ridge_x = 0.5 * (near + far)
        angles = np.arctan((far - near) / rules.length)
        if (np.max(np.abs(np.degrees(angles))) > rules.max_ridge_angle_deg
                or distinct_directions(angles, rules.min_ridge_separation_deg) < 4):
            continue
        magnitudes = np.tan(np.radians(rng.uniform(rules.min_face_angle_deg, rules.max_face_angle_deg, n_ridges + 1)))
        signs = rng.choice([-1.0, 1.0]) * (-1.0) ** np.arange(n_ridges + 1)  # alternate: every ridge a corner
        try:
            gauge = heightfield_gauge(f"random_n{n_ridges}_{attempt}", rules.width, rules.length, ridge_x, angles,
                                      signs * magnitudes, y_slope0=rng.uniform(-0.1, 0.1))
        except GaugeError:
            continue
        heights = gauge.corner_heights()
        if (np.min(face_widths(gauge)) < rules.min_face_width
                or np.max(gauge.face_slope_deg()) > rules.max_face_angle_deg
                or np.ptp(heights) > rules.max_relief):
            continue
        try:
            for _ in range(check_poses):
                sample_pose(gauge, rng, max_tries=50)
        except RuntimeError:
            continue
        return gauge
    raise RuntimeError(f"no valid random gauge with {n_ridges} ridges after {max_tries} tries; relax the rules")
