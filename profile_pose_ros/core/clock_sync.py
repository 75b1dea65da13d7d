"""Mapping a device clock to host time, and matching profiles to the triggers that took them.

Each trigger line reaches the host some time after the trigger: the serial transmission (known from
the baud rate) plus a latency that is never negative and only sometimes small (USB polling, the OS
scheduler). So the host time of a device tick follows the *lower envelope* of (arrival - transmission)
against device time, with a slope for the MCU oscillator's drift (a ceramic resonator: up to 0.5 %).
A mean-based fit would add the average scheduling delay to every stamp; the envelope adds only the
smallest one, which the link then estimates from PING round trips and subtracts.
"""
from __future__ import annotations

from collections import OrderedDict, deque

import numpy as np


CHUNK_S = 0.1  # s of samples per envelope candidate (their least-delayed one)
MIN_CHUNKS = 10


def lower_envelope_slope(x: np.ndarray, y: np.ndarray) -> float:
    """Slope of the line under every point that hugs them most closely (least total height above it):
    the lower convex hull's edge over the mean of x. Delays only ever add height, so unlike a least-squares
    fit it ignores however many late samples there are, as long as some got through quickly."""
    hull: list[tuple[float, float]] = []
    for point in zip(x.tolist(), y.tolist()):  # x ascending (monotone chain)
        while len(hull) >= 2 and _turns_clockwise(hull[-2], hull[-1], point):
            hull.pop()
        hull.append(point)
    middle = float(np.mean(x))
    for (x1, y1), (x2, y2) in zip(hull, hull[1:]):
        if x2 >= middle and x2 > x1:
            return (y2 - y1) / (x2 - x1)
    return 0.0


def _turns_clockwise(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> bool:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) <= 0.0


class ClockMap:
    """host = offset + slope * device. The slope is the lower envelope's over a long window (through the
    least-delayed sample of each chunk); the offset comes from the lower envelope of the last few seconds
    (a short span keeps a small slope error from growing). A least-squares slope, used here before, let a
    loaded machine's late samples tilt the map by up to 1 %: stamps ms off within a second of start."""

    def __init__(self, window_s: float = 10.0, recent_s: float = 3.0, jump_s: float = 0.05,
                 refit_s: float = 0.25, slope_after_s: float = 0.25, converged_after_s: float = 2.0,
                 max_drift: float = 0.01) -> None:
        self.window_s, self.recent_s = window_s, recent_s
        self.jump_s = jump_s  # a sample this far below the fit, or this far back in device time: a clock jump
        self.refit_s = refit_s  # full refits this often (device time); in between, only the offset moves
        self.slope_after_s = slope_after_s  # before this span of samples, assume no drift
        self.converged_after_s = converged_after_s
        self.max_drift = max_drift  # a ceramic resonator is within 0.5 %
        self._samples: deque[tuple[float, float]] = deque()
        self._ref: tuple[float, float] | None = None
        self._fit: tuple[float, float] | None = None  # (intercept, slope) relative to _ref
        self._fitted_at = -np.inf
        self.resets = 0

    def reset(self) -> None:
        self._samples.clear()
        self._ref = self._fit = None
        self._fitted_at = -np.inf
        self.resets += 1

    @property
    def ready(self) -> bool:
        return self._fit is not None

    @property
    def span(self) -> float:
        """Device seconds covered by the samples in the window."""
        return self._samples[-1][0] - self._samples[0][0] if self._samples else 0.0

    @property
    def converged(self) -> bool:
        return self.span >= self.converged_after_s

    def add(self, device_s: float, host_s: float) -> None:
        if self._ref is None:
            self._ref = (device_s, host_s)
        if self._fit is not None and (host_s < self.to_host(device_s) - self.jump_s
                                      or device_s < self._ref[0] + self._samples[-1][0] - self.jump_s):
            self.reset()  # the device restarted or its clock was set: start over
            self._ref = (device_s, host_s)
        d, h = device_s - self._ref[0], host_s - self._ref[1]
        self._samples.append((d, h))
        while self._samples and d - self._samples[0][0] > self.window_s:
            self._samples.popleft()
        if self._fit is None or d - self._fitted_at >= self.refit_s:
            self._refit()
            self._fitted_at = d
        else:
            intercept, slope = self._fit
            self._fit = (min(intercept, h - slope * d), slope)

    def _refit(self) -> None:
        data = np.asarray(self._samples)
        d, h = data[:, 0], data[:, 1]
        span = d[-1] - d[0]
        slope = 1.0
        if span >= self.slope_after_s:  # the envelope through each chunk's least-delayed sample
            residual = h - d
            chunk = np.floor((d - d[0]) / min(CHUNK_S, span / MIN_CHUNKS)).astype(int)
            order = np.lexsort((residual, chunk))
            first = order[np.r_[True, np.diff(chunk[order]) > 0]]
            slope = 1.0 + lower_envelope_slope(d[first], residual[first])
        slope = float(np.clip(slope, 1.0 - self.max_drift, 1.0 + self.max_drift))
        recent = d >= d[-1] - self.recent_s
        self._fit = (float(np.min(h[recent] - slope * d[recent])), slope)

    def to_host(self, device_s: float) -> float:
        """Host time of a device time; raises RuntimeError before the first sample."""
        if self._fit is None or self._ref is None:
            raise RuntimeError("clock map has no samples yet")
        intercept, slope = self._fit
        return self._ref[1] + intercept + slope * (device_s - self._ref[0])

    def residual_stats(self) -> tuple[float, float]:
        """(median, max) of each sample's delay above the envelope, s: the link's latency jitter."""
        if self._fit is None or not self._samples:
            return float("nan"), float("nan")
        data = np.asarray(self._samples)
        intercept, slope = self._fit
        above = data[:, 1] - (intercept + slope * data[:, 0])
        return float(np.median(above)), float(np.max(above))

    @property
    def drift_ppm(self) -> float:
        """How fast the device clock runs against the host's (positive: device fast)."""
        return float("nan") if self._fit is None else (1.0 / self._fit[1] - 1.0) * 1e6


class TriggerMatcher:
    """Pairs profiles (by the profiler's trigger count) with MCU triggers (by sequence number).

    The two counters differ by a constant, learnt once per arming: the driver disarms the MCU, waits
    until the stream is quiet, resets and re-arms it, and then the first profile and the first trigger
    after arming are the same pulse. Periodic triggers make any other pairing ambiguous by whole periods.
    """

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self._times: OrderedDict[int, float] = OrderedDict()  # seq -> host trigger time
        self.offset: int | None = None
        self._armed = False
        self._first_seq: int | None = None
        self._first_count: int | None = None
        self._expected_offset: int | None = None
        self.disagreements = 0

    def arm(self, last_count: int | None = None) -> None:
        """Forget the pairing; the next trigger and the next profile define it. `last_count`, the profiler's
        count of the last profile before disarming, gives a second opinion: the first trigger after arming
        is last_count + 1. If the first profile after arming was lost, the two disagree and pairing fails
        (offset stays None, `disagreements` counts it) so the caller pairs again."""
        self.forget()
        self._armed = True
        self._expected_offset = None if last_count is None else last_count & 0xFFFFFFFF

    def forget(self) -> None:
        """No pairing until the next arm() (the MCU or the profiler restarted)."""
        self._times.clear()
        self.offset = None
        self._armed = False
        self._first_seq = self._first_count = None

    @property
    def pairing(self) -> bool:
        """Armed and waiting for the first trigger and profile."""
        return self._armed

    def add_trigger(self, seq: int, host_time: float) -> None:
        if self._armed and self._first_seq is None:
            self._first_seq = seq
            self._learn()
        self._times[seq] = host_time
        while len(self._times) > self.capacity:
            self._times.popitem(last=False)

    def note_profile(self, trigger_count: int) -> None:
        if self._armed and self._first_count is None:
            self._first_count = trigger_count
            self._learn()

    def _learn(self) -> None:
        if self._first_seq is not None and self._first_count is not None:
            offset = (self._first_count - self._first_seq) & 0xFFFFFFFF
            self._armed = False
            if self._expected_offset is not None and offset != self._expected_offset:
                self.disagreements += 1
                return
            self.offset = offset

    def trigger_time(self, trigger_count: int) -> float | None:
        if self.offset is None:
            return None
        return self._times.get((trigger_count - self.offset) & 0xFFFFFFFF)
