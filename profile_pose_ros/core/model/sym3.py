"""The largest eigenvalue of a symmetric 3 x 3 matrix in closed form, plain Python on floats, so that the
numpy path (result.position_sigma) and the compiled kernel (estimate_kernel.py compiles this same function) share
one source. LAPACK through numpy would cost a fifth of the compiled estimator (docs/design_notes.md)."""
from __future__ import annotations

import math


def largest_eigenvalue(a: float, b: float, c: float, d: float, e: float, f: float) -> float:
    """Of [[a, b, c], [b, d, e], [c, e, f]] (finite entries), by the trigonometric solution of the
    characteristic cubic: with B = (A - mean I) / p, the eigenvalues are mean + 2 p cos(angle)."""
    off = b * b + c * c + e * e
    mean = (a + d + f) / 3.0
    spread = ((a - mean) ** 2 + (d - mean) ** 2 + (f - mean) ** 2 + 2.0 * off) / 6.0
    if spread <= 0.0:
        return mean
    p = math.sqrt(spread)
    a, d, f = (a - mean) / p, (d - mean) / p, (f - mean) / p
    b, c, e = b / p, c / p, e / p
    half_det = (a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c)) / 2.0
    return mean + 2.0 * p * math.cos(math.acos(min(1.0, max(-1.0, half_det))) / 3.0)
