"""The corner residual of paper eq. (9), its Jacobian and covariance, and the pose types built on it, in numpy:
for the bound (design/crlb.py), the wrong-minimum check, and the benchmark's baseline. The estimator's own
closed form and refinement are the compiled kernels' (compiled/estimate_kernel.py).

The corner residual used throughout is the algebraic residual of eq. (9): for corner p = [px, pz] of
F mapped into G as P = R [px, 0, pz] + t, the x-z offset between P and ridge i at the same y,
    r_i = [P_x - u_i P_y - q_ix,  P_z - w_i P_y - q_iz].
It is a length. Eq. (17) as printed (a difference of unit-y ridge directions) equals r_i / |P_y|, so
|r_i| is what we report as the paper's reprojection error.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..model.gauge import Gauge
from ..model.rotation import skew


class RidgeLines(Protocol):
    """The ridges as lines (a gauge, or a subset of its ridges): x = q_x + u y, z = q_z + w y in G."""

    q: np.ndarray  # (n, 3) ridge points in the y = 0 plane
    u: np.ndarray  # (n,)
    w: np.ndarray  # (n,)


@dataclass(frozen=True)
class PoseSolution:
    rotation: np.ndarray  # (3, 3), p_G = R p_F + t
    translation: np.ndarray  # (3,)
    residuals: np.ndarray  # (n, 2) corner residuals r_i, metres

    @property
    def reprojection_error(self) -> float:
        """Mean over corners of |r_i| (m): the paper's eq. (17) metric, as a length."""
        return float(np.mean(np.hypot(self.residuals[:, 0], self.residuals[:, 1])))


REASON_CF_DEGENERATE = "closed form produced a degenerate rotation"


def reason_cf_rank(n: int, rank: int) -> str:
    return f"closed form is underdetermined with {n} corners (rank {rank} < 9)"


def corner_residuals(gauge: RidgeLines, corners: np.ndarray, rotation: np.ndarray, translation: np.ndarray
                     ) -> np.ndarray:
    mapped = corners[:, :1] * rotation[:, 0] + corners[:, 1:] * rotation[:, 2] + translation
    return np.column_stack([
        mapped[:, 0] - gauge.u * mapped[:, 1] - gauge.q[:, 0],
        mapped[:, 2] - gauge.w * mapped[:, 1] - gauge.q[:, 2],
    ])


def _ridge_rows(gauge: RidgeLines) -> np.ndarray:
    """(n, 2, 3) C_i with r_i = C_i P_i - q_i: the x and z offsets from ridge i at P's y."""
    n = len(gauge.u)
    c = np.zeros((n, 2, 3))
    c[:, 0, 0] = 1.0
    c[:, 0, 1] = -gauge.u
    c[:, 1, 1] = -gauge.w
    c[:, 1, 2] = 1.0
    return c


def residual_jacobian(gauge: Gauge, corners: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(2n, 6) d r / d [delta, t] for the right perturbation R <- R exp([delta]x)."""
    n = len(corners)
    c = _ridge_rows(gauge)
    skews = skew(np.column_stack([corners[:, 0], np.zeros(n), corners[:, 1]]))  # p = [px, 0, pz]
    jac = np.empty((n, 2, 6))
    jac[:, :, :3] = -np.einsum("nij,jk,nkl->nil", c, rotation, skews)
    jac[:, :, 3:] = c
    return jac.reshape(2 * n, 6)


def residual_covariance(gauge: Gauge, rotation: np.ndarray, corner_covariance: np.ndarray) -> np.ndarray:
    """Covariance of the stacked residuals induced by the corners' covariance (linear in the corners)."""
    n = len(gauge.u)
    blocks = _ridge_rows(gauge) @ rotation[:, [0, 2]]  # (n, 2, 2)
    mapping = np.zeros((2 * n, 2 * n))
    for i in range(n):
        mapping[2 * i:2 * i + 2, 2 * i:2 * i + 2] = blocks[i]
    return mapping @ corner_covariance @ mapping.T


@dataclass(frozen=True)
class Refinement:
    solution: PoseSolution
    covariance: np.ndarray  # (6, 6) over [delta_F (3), t (3)]
    iterations: int


def solution_cost(gauge: Gauge, solution: PoseSolution, corner_covariance: np.ndarray | None, weighted: bool) -> float:
    """The cost refine() minimises, at a solution (so minima from different starts can be compared)."""
    r = solution.residuals.ravel()
    if not weighted or corner_covariance is None or not corner_covariance.size:
        return float(r @ r)
    return float(r @ np.linalg.solve(residual_covariance(gauge, solution.rotation, corner_covariance), r))
