"""Mapping a device clock to host time, and matching profiles to the triggers that took them.

Each trigger line reaches the host some time after the trigger: the serial transmission (known from
the baud rate) plus a latency that is never negative and only sometimes small (USB polling, the OS
scheduler). So the host time of a device tick follows the *lower envelope* of (arrival - transmission)
against device time, with a slope for the MCU oscillator's drift (a ceramic resonator: up to 0.5 %).
A mean-based fit would add the average scheduling delay to every stamp; the envelope adds only the
smallest one, which the link then estimates from PING round trips and subtracts.

How far off the map can be is known only from samples with a known bound on their own delay: a PONG's
delay is at most its PING's round trip (the MCU read its clock after the PING arrived), so the true line
passes between the PONG's time and that time less its bound. Two such PONGs far apart bound the true
slope; with it, `error_bound` bounds the map's error now on both sides: its offset's (what a bounded
sample allows) plus its slope's error carried from the samples that set the offset. Stamps are trusted
only while it is small, because a map still settling moves between two triggers, and profiles stamped in
that time get gaps that are not whole trigger periods (or, with a burst of late lines, one stamp twice).
"""
from __future__ import annotations

from collections import OrderedDict, deque

import numpy as np


CHUNK_S = 0.1  # s of samples per envelope candidate (their least-delayed one)
BOUND_CHUNK_S = 0.5  # s of bounded samples per slope-bound candidate (their tightest one)
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


def chunk_minima(chunk: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Index of each chunk's smallest value (the earliest on a tie); `chunk` is non-decreasing. O(n), where
    a lexsort is O(n log n) and was a third of the refit."""
    starts = np.flatnonzero(np.r_[True, chunk[1:] != chunk[:-1]])
    minima = np.minimum.reduceat(values, starts)
    at_minimum = np.flatnonzero(values == np.repeat(minima, np.diff(np.r_[starts, len(values)])))
    return at_minimum[np.r_[True, chunk[at_minimum[1:]] != chunk[at_minimum[:-1]]]]


def _turns_clockwise(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> bool:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) <= 0.0


class SampleWindow:
    """(device, host) samples of the last window_s device seconds, in two numpy arrays. A deque of tuples
    turned into an array at each refit holds the GIL for milliseconds at 1 kHz, in the trigger thread, and
    the driver's profile thread stalls behind it at every refit."""

    def __init__(self, capacity: int = 1024) -> None:
        self._data = np.empty((2, capacity))
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def clear(self) -> None:
        self._start = self._end = 0

    def append(self, device_s: float, host_s: float, window_s: float) -> None:
        """Add a sample and drop those more than window_s device seconds older than it."""
        if self._end == self._data.shape[1]:
            kept = self._data[:, self._start:self._end]
            if 2 * kept.shape[1] > self._data.shape[1]:  # more than half full: grow
                self._data = np.empty((2, 2 * self._data.shape[1]))
            self._data[:, :kept.shape[1]] = kept.copy()
            self._start, self._end = 0, kept.shape[1]
        self._data[0, self._end] = device_s
        self._data[1, self._end] = host_s
        self._end += 1
        device = self._data[0]
        while device_s - device[self._start] > window_s:
            self._start += 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Views of the device and host times, oldest first (valid until the next append)."""
        return self._data[0, self._start:self._end], self._data[1, self._start:self._end]

    def last_device(self) -> float:
        return float(self._data[0, self._end - 1])

    def span(self) -> float:
        return float(self._data[0, self._end - 1] - self._data[0, self._start]) if len(self) else 0.0


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
        self._samples = SampleWindow()
        self._bounded: deque[tuple[float, float, float]] = deque()  # (device, host, delay bound) in the window
        self._ref: tuple[float, float] | None = None
        self._fit: tuple[float, float] | None = None  # (intercept, slope) relative to _ref
        self._fitted_at = -np.inf
        self._forget_bounds()
        self.resets = 0
        self.last_reset = "none"  # why the map last started over
        self.bounds_refused = 0
        self.bounds_contradicted = 0

    def _forget_bounds(self) -> None:
        self._slope_error = np.inf  # the most the map's slope can be off the true one
        self._late_anchor = np.inf  # min over the offset's bounded samples of (bound - slope_error * device)
        self._offset_set_at = np.inf  # device time of the sample that set the offset

    def reset(self, reason: str = "") -> None:
        self.last_reset = reason
        self._samples.clear()
        self._bounded.clear()
        self._ref = self._fit = None
        self._fitted_at = -np.inf
        self._forget_bounds()
        self.resets += 1

    @property
    def ready(self) -> bool:
        return self._fit is not None

    @property
    def span(self) -> float:
        """Device seconds covered by the samples in the window."""
        return self._samples.span()

    @property
    def converged(self) -> bool:
        return self.span >= self.converged_after_s

    @property
    def error_bound(self) -> float:
        """How far (s, either way) the map may put the newest device time from its true host time (inf
        before convergence, or without bounded samples early and late in the window).

        The map lies under every sample of its offset's set, so at a bounded sample p it is at most b_p
        late, and carried to now with a slope at most `slope_error` off, at most b_p + slope_error * age_p
        late. The true line lies under every sample too, the one that set the offset (s) included, so the
        map is at most slope_error * age_s early."""
        if not self.converged or self._slope_error == np.inf:
            return float("inf")
        newest = self._samples.last_device()
        late = self._late_anchor + self._slope_error * newest
        early = self._slope_error * (newest - self._offset_set_at)
        return float(max(late, early))

    def add(self, device_s: float, host_s: float, delay_bound: float = float("inf")) -> None:
        """A sample: the device time of a line and the host time it was sent; delay_bound, if known, is
        the most the line can have been delayed (a PONG: its PING's round trip)."""
        if self._ref is None:
            self._ref = (device_s, host_s)
        early = self._fit is not None and host_s < self.to_host(device_s) - self.jump_s
        if early or (self._fit is not None and device_s < self._ref[0] + self._samples.last_device() - self.jump_s):
            # the device restarted or its clock was set: start over
            self.reset("a line far earlier than the map" if early else "the device time went back")
            self._ref = (device_s, host_s)
        d, h = device_s - self._ref[0], host_s - self._ref[1]
        if delay_bound < float("inf") and self._fit is not None and (
                h - (self._fit[0] + self._fit[1] * d) > delay_bound + self.error_bound):
            # Its height above the map is at most its true delay plus how early the map may be: a bound
            # below that is false, e.g. a PONG paired with a later PING than it answered. A map without a
            # bound refuses none (its slope may be the one that is wrong); the slope range drops the false.
            self.bounds_refused += 1
            delay_bound = float("inf")
        self._samples.append(d, h, self.window_s)
        if delay_bound < float("inf"):
            self._bounded.append((d, h, delay_bound))
        while self._bounded and self._bounded[0][0] < d - self.window_s:
            self._bounded.popleft()
        if self._fit is None or d - self._fitted_at >= self.refit_s:
            self._refit()
            self._fitted_at = d
        else:
            intercept, slope = self._fit
            if h - slope * d < intercept:
                self._fit = (h - slope * d, slope)
                self._offset_set_at = d
            if delay_bound < float("inf") and self._slope_error < np.inf:
                self._late_anchor = min(self._late_anchor, delay_bound - self._slope_error * d)

    def _refit(self) -> None:
        d, h = self._samples.arrays()
        span = d[-1] - d[0]
        slope = 1.0
        if span >= self.slope_after_s:  # the envelope through each chunk's least-delayed sample
            residual = h - d
            chunk = np.floor((d - d[0]) / min(CHUNK_S, span / MIN_CHUNKS)).astype(int)
            first = chunk_minima(chunk, residual)
            slope = 1.0 + lower_envelope_slope(d[first], residual[first])
        slope = float(np.clip(slope, 1.0 - self.max_drift, 1.0 + self.max_drift))
        low, high = self._slope_range()
        if low <= high:
            slope = float(np.clip(slope, low, high))
            self._slope_error = max(slope - low, high - slope)
        else:
            self._slope_error = np.inf
        recent = np.flatnonzero(d >= d[-1] - self.recent_s)
        offsets = h[recent] - slope * d[recent]
        lowest = int(np.argmin(offsets))
        self._fit = (float(offsets[lowest]), slope)
        self._offset_set_at = float(d[recent[lowest]])
        self._late_anchor = np.inf
        if self._slope_error < np.inf:
            self._late_anchor = min((b - self._slope_error * bd for bd, _, b in self._bounded
                                     if bd >= d[-1] - self.recent_s), default=np.inf)

    def _slope_range(self) -> tuple[float, float]:
        """The true slope's range allowed by the bounded samples: the true line passes within each one's
        bound below it, so any two apart bound its slope, and it meets every such bound at once. Pairs of
        the tightest sample of each BOUND_CHUNK_S keep it cheap. (inf, -inf) without a pair.

        An empty range means a false bound (a PONG paired with the wrong PING) among the two pairs that
        set its ends: their samples are dropped, counted in bounds_contradicted, until the rest agree."""
        if len(self._bounded) < 2:
            return np.inf, -np.inf
        d, h, b = np.array(self._bounded).T
        tightest = chunk_minima(np.floor((d - d[0]) / BOUND_CHUNK_S).astype(int), b)
        d, h, b = d[tightest], h[tightest], b[tightest]
        first, second = np.triu_indices(len(d), 1)
        apart = d[second] > d[first]
        first, second = first[apart], second[apart]
        while len(first):
            span = d[second] - d[first]
            lows, highs = (h[second] - b[second] - h[first]) / span, (h[second] - h[first] + b[first]) / span
            at_low, at_high = int(np.argmax(lows)), int(np.argmin(highs))
            if lows[at_low] <= highs[at_high]:
                return float(lows[at_low]), float(highs[at_high])
            suspects = {first[at_low], second[at_low], first[at_high], second[at_high]}
            self.bounds_contradicted += 1
            false_times = {float(d[k]) for k in suspects}
            self._bounded = deque(sample for sample in self._bounded if sample[0] not in false_times)
            keep = ~(np.isin(first, list(suspects)) | np.isin(second, list(suspects)))
            first, second = first[keep], second[keep]
        return np.inf, -np.inf

    def to_host(self, device_s: float) -> float:
        """Host time of a device time; raises RuntimeError before the first sample."""
        if self._fit is None or self._ref is None:
            raise RuntimeError("clock map has no samples yet")
        intercept, slope = self._fit
        return self._ref[1] + intercept + slope * (device_s - self._ref[0])

    def residual_stats(self) -> tuple[float, float]:
        """(median, max) of each sample's delay above the envelope, s: the link's latency jitter."""
        if self._fit is None or not len(self._samples):
            return float("nan"), float("nan")
        d, h = self._samples.arrays()
        intercept, slope = self._fit
        above = h - (intercept + slope * d)
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
