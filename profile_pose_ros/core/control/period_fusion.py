"""The poses of one controller period as one measurement, for a profiler faster than the controller.

A 1 kHz profiler gives four poses in a 4 ms controller period, each with its own noise; the controller takes
one increment a period. Fused by their covariances, the period's poses halve the noise the law acts on
(four equal poses), where taking one of them would leave three quarters of the information unused. The arm
moves during the period, so each pose is first carried to the newest one's time along the velocity the
law's filter holds; the fused pose is then a measurement at that time, with the variance of the fused mean.
Per axis (the compensator's filters are per axis and take the covariance's diagonal in the base frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PeriodPose:
    """One pose taken during the period: its stamp (s), its trigger time (ns, as the correction carries it),
    its value and variance per axis in the base frame (x y z rx ry rz)."""

    stamp: float
    stamp_ns: int
    value: np.ndarray
    variance: np.ndarray


def fuse_period(poses: list[PeriodPose], velocity: np.ndarray) -> PeriodPose:
    """The inverse-variance mean of `poses`, each carried to the newest stamp along `velocity` (per axis, units
    per second), stamped with the newest."""
    newest = max(poses, key=lambda p: p.stamp)
    if len(poses) == 1:
        return newest
    weights = np.array([1.0 / p.variance for p in poses])
    values = np.array([p.value + velocity * (newest.stamp - p.stamp) for p in poses])
    total = weights.sum(axis=0)
    return PeriodPose(newest.stamp, newest.stamp_ns, (weights * values).sum(axis=0) / total, 1.0 / total)
