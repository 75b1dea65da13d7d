"""Rigid transforms for the cell's frames (robot base, flange, tool, profiler, gauge) and the controller's
way of writing an orientation.

`Transform(R, t)` maps a point from the child frame into the parent's: p_parent = R p_child + t, the same
convention as the estimator's pose of F in G. Parameters carry a transform as six numbers: x y z (m) and a
rotation vector (rad).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .rotation import so3_exp, so3_log


@dataclass(frozen=True)
class Transform:
    rotation: np.ndarray
    translation: np.ndarray

    @classmethod
    def identity(cls) -> "Transform":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_vector(cls, vector) -> "Transform":
        """[x, y, z, rx, ry, rz]: translation (m) and rotation vector (rad)."""
        vector = np.asarray(vector, dtype=float)
        if vector.shape != (6,) or not np.all(np.isfinite(vector)):
            raise ValueError(f"a transform needs six finite numbers (x y z rx ry rz), got {vector.tolist()}")
        return cls(so3_exp(vector[3:]), vector[:3].copy())

    def vector(self) -> np.ndarray:
        return np.concatenate([self.translation, so3_log(self.rotation)])

    def __matmul__(self, other: "Transform") -> "Transform":
        return Transform(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def inverse(self) -> "Transform":
        return Transform(self.rotation.T, -self.rotation.T @ self.translation)

    def apply(self, point: np.ndarray) -> np.ndarray:
        return self.rotation @ point + self.translation


def difference(a: Transform, b: Transform) -> np.ndarray:
    """a relative to b as six numbers, both expressed in the parent frame: translation a.t - b.t and the
    rotation vector of a.R b.R^T (the left perturbation the estimator's covariance uses)."""
    return np.concatenate([a.translation - b.translation, so3_log(a.rotation @ b.rotation.T)])


def rotation_from_controller_angles(angles) -> np.ndarray:
    """A Yaskawa controller's Rx, Ry, Rz (rad): turns about the fixed base axes x, then y, then z,
    R = Rz Ry Rx (as the pendant shows a Cartesian pose). Written out: the bridge turns every STATE's angles
    into a rotation, and a scipy Rotation costs tens of microseconds there."""
    a, b, c = (float(v) for v in angles)
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    return np.array([[cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa],
                     [sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa],
                     [-sb, cb * sa, cb * ca]])


def controller_angles(rotation: np.ndarray) -> np.ndarray:
    """The inverse of rotation_from_controller_angles (rad, each in (-pi, pi]); written out for sim_cell's
    controller, which reports its pose every period. At Ry = +-90 deg only Rx - Rz (or Rx + Rz) is defined:
    scipy's convention decides there."""
    r = np.asarray(rotation, dtype=float)
    if abs(r[2, 0]) > 1.0 - 1e-9:
        return Rotation.from_matrix(r).as_euler("xyz")
    return np.array([math.atan2(r[2, 1], r[2, 2]), math.atan2(-r[2, 0], math.hypot(r[2, 1], r[2, 2])),
                     math.atan2(r[1, 0], r[0, 0])])
