"""The arm's mode from its measured response to a small step: natural frequency, damping ratio, gain and
delay, with their uncertainties, for the modal law's model (core/control/modal_control.py).

The response to a step of size s commanded at t = 0 is fitted as the second-order system's

    y(t) = y0 + g s (1 - e^(-zeta w u) (cos(w_d u) + zeta / sqrt(1 - zeta^2) sin(w_d u))),  u = t - delay >= 0

by nonlinear least squares (scipy), weighted by the poses' noise. The uncertainties are the fit's
(Jacobian and residual) and, over repeats, the larger of that and the repeats' own scatter: an arm whose
damping depends on the amplitude, or a step that was not quite a step, shows there rather than hiding
in a too small formal error. Small steps (0.2-0.5 mm) keep a nonlinear damping near its small-motion
value, the one that matters to a loop whose corrections are small.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import least_squares

MIN_SAMPLES = 20


@dataclass(frozen=True)
class ModeFit:
    frequency_hz: float
    damping: float
    gain: float  # the response's final value per unit of the commanded step
    delay_s: float
    frequency_sigma: float
    damping_sigma: float
    gain_sigma: float
    delay_sigma: float
    residual_rms: float  # m: about the poses' noise when the model fits
    samples: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


def step_response(t: np.ndarray, frequency_hz: float, damping: float, delay_s: float) -> np.ndarray:
    """Unit step response of the second-order system, delayed."""
    u = np.maximum(np.asarray(t, dtype=float) - delay_s, 0.0)
    w = 2 * np.pi * frequency_hz
    z = min(damping, 0.999)
    root = np.sqrt(1 - z * z)
    return 1 - np.exp(-z * w * u) * (np.cos(w * root * u) + z / root * np.sin(w * root * u))


def fit_step(t: np.ndarray, y: np.ndarray, step: float, noise_std: float | None = None) -> ModeFit:
    """The mode from one step response: t (s, from the command), y (m, from where the arm stood)."""
    t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
    keep = np.isfinite(t) & np.isfinite(y)
    t, y = t[keep], y[keep]
    if len(t) < MIN_SAMPLES or not step:
        raise ValueError(f"a step response needs {MIN_SAMPLES} samples and a non-zero step, got {len(t)} and {step}")

    def residual(v: np.ndarray) -> np.ndarray:
        y0, gain, frequency, damping, delay = v
        return y - (y0 + gain * step * step_response(t, frequency, damping, delay))

    # the delay starts where the response first passes a tenth of the step (less a little for its rise)
    moved = np.nonzero(np.abs(y) > 0.1 * abs(step))[0]
    delay = max(0.0, float(t[moved[0]]) - 0.02) if len(moved) else 0.0
    best = None
    for frequency in (3.0, 6.0, 10.0, 15.0, 25.0):  # a few starts: the cost has side minima in frequency
        for damping in (0.05, 0.3, 0.7):
            result = least_squares(residual, [0.0, 1.0, frequency, damping, delay],
                                   bounds=([-np.inf, 0.1, 0.5, 0.0, 0.0], [np.inf, 10.0, 100.0, 0.99, 0.5]),
                                   x_scale=[abs(step), 0.1, 1.0, 0.1, 0.01])
            if best is None or result.cost < best.cost:
                best = result
    dof = max(len(t) - 5, 1)
    rms = float(np.sqrt(2 * best.cost / dof))
    sigma = noise_std if noise_std else rms
    jtj = best.jac.T @ best.jac
    covariance = np.linalg.pinv(jtj) * max(sigma, rms) ** 2  # never more certain than the fit's residual says
    errors = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    _, gain, frequency, damping, delay = best.x
    return ModeFit(float(frequency), float(damping), float(gain), float(delay), float(errors[2]),
                   float(errors[3]), float(errors[1]), float(errors[4]), rms, len(t))


def combine(fits: list[ModeFit]) -> ModeFit:
    """One estimate from repeated fits: the inverse-variance mean of each quantity, with the larger of its
    formal error and the standard error of the repeats' scatter."""
    if not fits:
        raise ValueError("no fits to combine")

    def pooled(value: str, sigma: str) -> tuple[float, float]:
        values = np.array([getattr(f, value) for f in fits])
        sigmas = np.maximum(np.array([getattr(f, sigma) for f in fits]), 1e-12)
        weights = sigmas ** -2
        mean = float(np.sum(weights * values) / np.sum(weights))
        formal = float(np.sqrt(1 / np.sum(weights)))
        scatter = float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0
        return mean, max(formal, scatter)

    (f, fs), (z, zs), (g, gs), (d, ds) = (pooled("frequency_hz", "frequency_sigma"), pooled("damping", "damping_sigma"),
                                          pooled("gain", "gain_sigma"), pooled("delay_s", "delay_sigma"))
    rms = float(np.sqrt(np.mean([fit.residual_rms ** 2 for fit in fits])))
    return ModeFit(f, z, g, d, fs, zs, gs, ds, rms, sum(fit.samples for fit in fits))
