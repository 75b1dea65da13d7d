"""How the corrections that reach the bridge between two answers become one period's increment.

A correction is a velocity. Sent once a control period (the modal law, or a profiler the controller
triggers), each is that period's motion; sent several times a period (a faster profiler under the PD
law), they are samples of one velocity. A correction that misses its answer by a fraction of a
millisecond is answered with the next one, and must still move the arm once: averaging the two (as if
they were samples of one period) loses half of each, which costs a planned step a visible part of its
travel. So each correction counts for the time it stands for, the corrections' usual stamp spacing (their
median, at most one period), and an answer sends the sum. At one correction a period that is the sum of
their increments; at four a period, their mean velocity over the period; with one late at four a period,
five quarters now and three next time, so that nothing is lost or sent twice.

Corrections that answer the controller's STATEs (the bridge's await_reply, beside a compensator on the
controller's clock) stand for one period each, whatever their stamps say. Their stamps are the fused
poses' times, which wander by a few ms from period to period; a median of spacings capped at the period
came out 4-8 % short of it, so every increment, a planned step's first one too, was cut by as much, at
random from step to step, and the arm fell tens of um behind its plan.
"""
from __future__ import annotations

from collections import deque
from statistics import median

import numpy as np

SPACING_WINDOW = 16  # stamp spacings the median is taken over: a few controller periods at 1 kHz
# Answers to STATEs come about once a period; corrections this much more often are a profiler's samples
# (a PD law on a faster profiler behind await_reply), each standing for its spacing, not a period
ANSWERS_AT_LEAST = 0.5


class CorrectionSpacing:
    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._spacings: deque[float] = deque(maxlen=SPACING_WINDOW)
        self._last_stamp: float | None = None

    def add(self, stamp_s: float) -> None:
        """A correction stamped stamp_s (its pose's trigger time) arrived. The watchdog's repeated zeros carry
        one stamp and say nothing of the spacing; a gap or a stamp going back counts as one period."""
        if self._last_stamp is not None and stamp_s != self._last_stamp:
            spacing = stamp_s - self._last_stamp
            self._spacings.append(spacing if 0.0 < spacing < self.period_s else self.period_s)
        self._last_stamp = stamp_s

    def share(self, answers: bool = False) -> float:
        """The time one correction stands for (s): the period until the spacing is known. answers: the
        corrections answer the controller's STATEs, one a period each."""
        if not self._spacings:
            return self.period_s
        spacing = median(self._spacings)
        return self.period_s if answers and spacing >= ANSWERS_AT_LEAST * self.period_s else spacing

    def increment(self, velocities: list[np.ndarray], answers: bool = False) -> np.ndarray:
        """The motion the corrections of one answer stand for (m, rad)."""
        return np.sum(velocities, axis=0) * self.share(answers)
