"""Dense refinement's options and result: the pose from every profile point's depth, not just the corners.

The refinement itself is compiled (compiled/dense_kernel.py); estimation/stages.py calls it.

With Gaussian noise on z this is the maximum-likelihood problem the profile actually poses; the corner
model throws information away (see crlb.py: the dense bound is 1.5-2x lower in position on the shipped
gauge). Starting from the corner solution, each point is assigned to the face it lands on in the gauge
frame; points near a ridge or an edge (ambiguous), off the footprint, or far from their face (spikes,
side walls) are left out, and Gauss-Newton on SO(3) x R^3 minimises
    z_i - (d_k - n_k . (t + x_i r1)) / (n_k . r3)
over the rest, re-selecting points at each step.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np



@dataclass(frozen=True)
class DenseOptions:
    # m; points this close to a ridge or an edge (in x of G) are not used. A point put on the wrong side of a
    # ridge misses its face by its distance from the ridge times the change of slope, so the robust cut drops
    # it beyond a few tens of um anyway. On the shipped gauge 0.5 mm left the estimate 1.1x above its
    # Cramer-Rao bound; 0.05 mm reaches it.
    ridge_margin: float = 5e-5
    outlier_threshold: float = 4.0  # robust standard deviations
    min_outlier_floor: float = 2e-6  # m
    iterations: int = 8


@dataclass(frozen=True)
class DenseResult:
    rotation: np.ndarray
    translation: np.ndarray
    covariance_local: np.ndarray  # (6, 6) over [delta_F, t]
    points_used: int
    sigma: float
