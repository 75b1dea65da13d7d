"""Searching gauge designs that minimise the worst Cramér-Rao bound over a required range of motion.

A design is the heightfield of gauge_design.heightfield_gauge: ridge positions at both ends of the
gauge (so faces never cross and every face keeps its minimum width), face slopes alternating up and down
(every ridge a visible bend), face 0's slope along y, the gauge's width and length. scipy's differential evolution searches those numbers on both cores; a design that
breaks a fabrication rule or loses a corner anywhere in the range scores worse than any valid one.
The score is max(worst position bound / reference's, worst rotation bound / reference's), so a score
of 0.25 means both are at least 4x lower than the reference gauge's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.gauge import Gauge, GaugeError
from .gauge_check import RequiredMotion, check_rules, motion_poses, precision_over, worst_bound
from .gauge_design import RandomGaugeRules, heightfield_gauge

INVALID = 1e3  # score of a design that cannot be built
NOT_SEEN = 1e2  # score of a design that loses a corner in the range (plus the share of poses lost)


@dataclass(frozen=True)
class DesignSpace:
    n_ridges: int
    width_range: tuple[float, float]
    rules: RandomGaugeRules
    motion: RequiredMotion
    noise_std: float
    reference: tuple[float, float]  # worst (position m, rotation rad) of the reference gauge
    length_range: tuple[float, float] = (0.05, 0.15)
    max_y_slope: float = 0.25

    def bounds(self) -> list[tuple[float, float]]:
        n, r = self.n_ridges, self.rules
        slopes = (np.tan(np.radians(r.min_face_angle_deg)), np.tan(np.radians(r.max_face_angle_deg)))
        return ([self.width_range, self.length_range] + [(0.0, 1.0)] * (2 * n) + [slopes] * (n + 1)
                + [(-self.max_y_slope, self.max_y_slope), (-1.0, 1.0)])

    def gauge(self, x: np.ndarray, name: str = "designed") -> Gauge:
        """The gauge of a parameter vector (raises GaugeError if it makes none)."""
        n, rules = self.n_ridges, self.rules
        width, length = float(x[0]), float(x[1])
        free = width - (n + 1) * rules.min_face_width
        if free <= 0:
            raise GaugeError(f"{n} ridges with faces >= {rules.min_face_width} m do not fit in {width} m")
        steps = rules.min_face_width * np.arange(1, n + 1)
        near = -width / 2 + steps + np.sort(x[2:2 + n]) * free
        far = -width / 2 + steps + np.sort(x[2 + n:2 + 2 * n]) * free
        magnitudes = x[2 + 2 * n:3 + 3 * n]
        sign = 1.0 if x[-1] >= 0 else -1.0
        slopes = sign * (-1.0) ** np.arange(n + 1) * magnitudes
        return heightfield_gauge(name, width, length, 0.5 * (near + far), np.arctan((far - near) / length),
                                 slopes, y_slope0=float(x[-2]))

    def score(self, x: np.ndarray) -> float:
        try:
            gauge = self.gauge(x)
        except GaugeError:
            return INVALID
        failed = [c for c in check_rules(gauge, self.rules) if not c.ok]
        if failed:
            return INVALID / 2 + len(failed)
        bounds = precision_over(gauge, motion_poses(gauge, self.motion), self.noise_std, dense=False)
        lost = sum(not b.visible for b in bounds)
        if lost:
            return NOT_SEEN + lost / len(bounds)
        position, rotation = worst_bound(bounds)
        return max(position / self.reference[0], rotation / self.reference[1])


def design_gauge(space: DesignSpace, seed: int = 0, max_generations: int = 60, population: int = 12,
                 workers: int = 2, callback=None):
    """(best gauge, its score, scipy's result) of a differential-evolution search."""
    from scipy.optimize import differential_evolution

    result = differential_evolution(space.score, space.bounds(), seed=seed, maxiter=max_generations,
                                    popsize=population, tol=1e-3, polish=False, workers=workers,
                                    updating="deferred" if workers != 1 else "immediate", callback=callback)
    return space.gauge(result.x), float(result.fun), result
