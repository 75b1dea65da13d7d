"""Small SO(3) helpers used by the estimator's on-manifold updates and by the error metrics."""
from __future__ import annotations

import math

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x, so that skew(a) @ b == cross(a, b); for (..., 3) input, one matrix per vector."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(v: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, with the series form near zero so tiny steps stay exact."""
    theta2 = float(v @ v)
    k = skew(v)
    if theta2 < 1e-16:
        return np.eye(3) + k + 0.5 * (k @ k)
    theta = np.sqrt(theta2)
    return np.eye(3) + (np.sin(theta) / theta) * k + ((1.0 - np.cos(theta)) / theta2) * (k @ k)


def so3_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (angle < pi). On Python floats, like quaternion_xyzw: the
    compensator takes one per pose, and numpy scalar arithmetic was most of its cost."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(rotation, dtype=float).tolist()
    cos_angle = min(max((m00 + m11 + m22 - 1.0) / 2.0, -1.0), 1.0)
    angle = math.acos(cos_angle)
    scale = 0.5 if angle < 1e-7 else angle / (2.0 * math.sin(angle))
    return np.array([scale * (m21 - m12), scale * (m02 - m20), scale * (m10 - m01)])


def rotation_angle(rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
    """Geodesic angle between two rotations, accurate for tiny differences (rad)."""
    return float(np.linalg.norm(so3_log(rotation_a.T @ rotation_b)))


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """Closest rotation in the Frobenius sense (det +1), paper eq. (13)."""
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def quaternion_xyzw(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) with w >= 0, as geometry_msgs wants it. On Python floats: every
    published pose needs one, and numpy's per-call overhead on scalars costs several times the arithmetic."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(rotation, dtype=float).tolist()
    trace = m00 + m11 + m22
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    norm = math.sqrt(sum(v * v for v in q))
    sign = -1.0 if q[3] < 0 else 1.0
    return np.array([sign * v / norm for v in q])


HALF_TURN_X = (1.0, 0.0, 0.0, 0.0)  # the profiler looking down on the gauge: the default orientation hint


def quaternion_near(rotation: np.ndarray, hint=HALF_TURN_X) -> np.ndarray:
    """quaternion_xyzw, signed so that its dot product with `hint` (x y z w) is >= 0. w >= 0 flips the sign
    wherever w crosses zero, which is where a profiler looking down on a gauge lives (a half turn), so
    consecutive poses jumped between hemispheres. Against a fixed hint the sign changes only for rotations a
    half turn away from the hint's, and it depends on nothing but this rotation, so a replay reproduces it."""
    q = quaternion_xyzw(rotation)
    return -q if sum(a * b for a, b in zip(q.tolist(), hint)) < 0.0 else q


def rotation_from_quaternion_xyzw(q: np.ndarray) -> np.ndarray:
    x, y, z, w = np.asarray(q, dtype=float).tolist()  # Python floats: see quaternion_xyzw
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm == 0.0:  # no rotation at all (a corrupt message): NaN, which callers reject, not an exception
        return np.full((3, 3), np.nan)
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
