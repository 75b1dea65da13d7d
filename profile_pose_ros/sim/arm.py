"""The simulated arm: per Cartesian axis, the flange follows its commanded position as a lightly damped
second-order system with the paper's open-loop behaviour (a 10 Hz resonance), after a command-to-motion
delay:

    p'' = w^2 (u(t - delay) - p) - 2 zeta w p' - c p'^3

The cubic term is why Table IV's open-loop damping grows with the step (y: 0.13 at 1 mm, 0.28 at
2 mm): zeta and c per axis were fitted once to Table IV's open-loop overshoots at 1 mm and 2 mm, and
reproduce them (and so the damping ratios) to 0.01 %. A quadratic term cannot: it at most doubles the
damping from 1 to 2 mm. Rotations: zeta 0.7, linear (the paper reports translations only). Integrated
by RK4 on a 0.25 ms step, compiled with numba (as the renderer is): in numpy the 4,000 small steps a
second cost sim_cell 30 % of a core at a 4 ms control period.

The delay defaults to one 4 ms interpolation clock plus the paper's mean profile transfer time (6.61 ms,
Table III): this sim's profiler has no transfer time of its own, so the arm carries it. It is a model
input, not a tuning knob.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numba import njit

DT = 2.5e-4  # s, integration step
DEFAULT_DAMPING = (0.6762, 0.0109, 0.4549, 0.7, 0.7, 0.7)  # linear zeta: x y z fitted to Table IV; rotations
DEFAULT_CUBIC = (1432.2, 7852.2, 15651.3, 0.0, 0.0, 0.0)  # c (s/m^2 for x y z), fitted with the above
DEFAULT_DELAY = 4e-3 + 6.61e-3


@dataclass(frozen=True)
class ArmModel:
    natural_frequency_hz: float = 10.0
    damping: tuple[float, ...] = DEFAULT_DAMPING
    cubic: tuple[float, ...] = DEFAULT_CUBIC
    delay_s: float = DEFAULT_DELAY

    def __post_init__(self) -> None:
        if (len(self.damping) != 6 or len(self.cubic) != 6 or min(self.damping) < 0
                or min(self.cubic) < 0 or self.natural_frequency_hz <= 0 or self.delay_s < 0):
            raise ValueError("arm model: six damping ratios and six cubic terms >= 0, a positive frequency, "
                             "a delay >= 0")


@dataclass
class Arm:
    """Offsets from the start pose (x y z in m, rotations in rad, small), all six axes."""

    model: ArmModel = field(default_factory=ArmModel)

    def __post_init__(self) -> None:
        self._w2 = (2 * np.pi * self.model.natural_frequency_hz) ** 2
        self._c1 = 2 * np.asarray(self.model.damping) * 2 * np.pi * self.model.natural_frequency_hz
        self._c3 = np.asarray(self.model.cubic, dtype=float)
        self.state = np.zeros((6, 2))
        self.command = np.zeros(6)
        steps = int(round(self.model.delay_s / DT))
        self._pipeline: deque[np.ndarray] = deque([np.zeros(6)] * steps)

    @property
    def position(self) -> np.ndarray:
        return self.state[:, 0].copy()

    @property
    def velocity(self) -> np.ndarray:
        return self.state[:, 1].copy()

    def advance(self, seconds: float) -> None:
        """Run the dynamics for `seconds` (a whole number of DT) with the current command."""
        steps = int(round(seconds / DT))
        inputs = np.empty((steps, 6))
        for k in range(steps):
            self._pipeline.append(self.command.copy())
            inputs[k] = self._pipeline.popleft()
        self.state = _integrate(self.state.copy(), inputs, self._w2, self._c1, self._c3, DT)


@njit(cache=True)
def _integrate(state: np.ndarray, inputs: np.ndarray, w2: float, c1: np.ndarray, c3: np.ndarray,
               dt: float) -> np.ndarray:
    """RK4 of p'' = w2 (u - p) - c1 p' - c3 p'^3 per axis, one step per row of inputs."""
    for k in range(inputs.shape[0]):
        for axis in range(state.shape[0]):
            u, p, v = inputs[k, axis], state[axis, 0], state[axis, 1]
            a, c, e = w2, c1[axis], c3[axis]
            k1p, k1v = v, a * (u - p) - c * v - e * v ** 3
            p2, v2 = p + dt / 2 * k1p, v + dt / 2 * k1v
            k2p, k2v = v2, a * (u - p2) - c * v2 - e * v2 ** 3
            p3, v3 = p + dt / 2 * k2p, v + dt / 2 * k2v
            k3p, k3v = v3, a * (u - p3) - c * v3 - e * v3 ** 3
            p4, v4 = p + dt * k3p, v + dt * k3v
            k4p, k4v = v4, a * (u - p4) - c * v4 - e * v4 ** 3
            state[axis, 0] = p + dt / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
            state[axis, 1] = v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return state
