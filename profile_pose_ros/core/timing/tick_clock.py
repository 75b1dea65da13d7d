"""The controller's tick on this host's clock, from the time each STATE carries.

A STATE says when the controller's interpolation clock sampled its pose (`time_us`). It reaches the bridge
after a delay that is never negative and only sometimes small: the network, and above all the bridge's
socket thread waiting for a core on a busy cell PC (several milliseconds in some runs on two cores). Its
read time is therefore no stamp for the pose: a reader that pairs STATEs with the profiles the controller
triggered at those ticks (the compensator on the controller's clock) would pair some with the next
tick's. The least-delayed STATE of the last WINDOW_S (the lower envelope of read time less controller
time) puts the controller's clock on this host's within that STATE's delay; over a few seconds a
controller's crystal drifts by microseconds, so no slope is fitted.
"""
from __future__ import annotations

from collections import deque

WINDOW_S = 2.0


class TickClock:
    def __init__(self, window_s: float = WINDOW_S) -> None:
        self.window_s = window_s
        # (controller time s, read time - controller time), offsets increasing: the first is the window's least
        self._envelope: deque[tuple[float, float]] = deque()

    def host_time(self, controller_us: int, read_time: float) -> float:
        """The host time (s, the clock of read_time) of the controller's tick at controller_us."""
        controller = controller_us * 1e-6
        if self._envelope and controller <= self._envelope[-1][0]:
            self._envelope.clear()  # the controller's clock started again (a restarted application)
        offset = read_time - controller
        while self._envelope and self._envelope[-1][1] >= offset:
            self._envelope.pop()
        self._envelope.append((controller, offset))
        while self._envelope[0][0] < controller - self.window_s:
            self._envelope.popleft()
        return controller + self._envelope[0][1]
