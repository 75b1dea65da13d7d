"""The simulated arm: per Cartesian axis, the flange follows its commanded position as a lightly damped
second-order system (the paper's open-loop behaviour: a 10 Hz resonance; Table IV's open-loop damping
x 0.68, y 0.13, z 0.53), after a command-to-motion delay.

Discretised exactly (zero-order hold on the command) on a 1 ms step, so the response does not depend on
how the controller's 4 ms clock is sampled. The delay defaults to one 4 ms interpolation clock plus the
paper's mean profile transfer time (6.61 ms, Table III): this sim's profiler has no transfer time of
its own, so the arm carries it. It is a model input, not a tuning knob.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

DT = 1e-3  # s, integration step
DEFAULT_DAMPING = (0.68, 0.13, 0.53, 0.7, 0.7, 0.7)  # x y z (Table IV open loop), rotations: assumed
DEFAULT_DELAY = 4e-3 + 6.61e-3


@dataclass(frozen=True)
class ArmModel:
    natural_frequency_hz: float = 10.0
    damping: tuple[float, ...] = DEFAULT_DAMPING
    delay_s: float = DEFAULT_DELAY

    def __post_init__(self) -> None:
        if len(self.damping) != 6 or min(self.damping) <= 0 or self.natural_frequency_hz <= 0 or self.delay_s < 0:
            raise ValueError("arm model: six positive damping ratios, a positive frequency, a delay >= 0")


def _discrete(omega: float, zeta: float) -> tuple[np.ndarray, np.ndarray]:
    """x[k+1] = A x[k] + B u[k] for x = [position, velocity], u held over DT."""
    continuous = np.array([[0.0, 1.0, 0.0], [-omega ** 2, -2 * zeta * omega, omega ** 2], [0.0, 0.0, 0.0]])
    m = expm(continuous * DT)
    return m[:2, :2], m[:2, 2]


@dataclass
class Arm:
    """Offsets from the start pose (x y z in m, rotations in rad, small), all six axes."""

    model: ArmModel = field(default_factory=ArmModel)

    def __post_init__(self) -> None:
        omega = 2 * np.pi * self.model.natural_frequency_hz
        mats = [_discrete(omega, z) for z in self.model.damping]
        self._a = np.array([m[0] for m in mats])  # (6, 2, 2)
        self._b = np.array([m[1] for m in mats])  # (6, 2)
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
        for _ in range(int(round(seconds / DT))):
            self._pipeline.append(self.command.copy())
            delayed = self._pipeline.popleft()
            self.state = np.einsum("aij,aj->ai", self._a, self.state) + self._b * delayed[:, None]
