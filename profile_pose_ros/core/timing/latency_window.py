"""One stage's latency (trigger time, the message's stamp, to this node's publish or send) over one
diagnostics window, reported as count, median, p99 and max in ms.

Why in the nodes: a commissioning engineer reads each stage's latency in the diagnostics of a running
cell, and a measuring tool that subscribed to every stage at 1 kHz would itself take the CPU the graph
needs. A window's p99 bounds the run's: when no window has more than 1 % of its messages above x, neither
has the run, so windows combine by their worst p99 (`pooled`), never by averaging. For that the window's
p99 is an order statistic (numpy's "higher"), not interpolated: with 50 messages the interpolated p99 can
sit halfway below the largest, which is then 2 % of the window above it.
"""
from __future__ import annotations

import threading

import numpy as np


class LatencyWindow:
    """Thread-safe: a socket thread may add while the executor reports."""

    def __init__(self, key: str) -> None:
        self.key = key  # e.g. "trigger_to_pose_ms": the diagnostics keys are key_n, key_median, ...
        self._values: list[float] = []
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._values.append(seconds)

    def __len__(self) -> int:
        return len(self._values)

    def snapshot(self) -> list[float]:
        """The window so far (s), left in place."""
        with self._lock:
            return list(self._values)

    def report(self) -> dict[str, float]:
        """This window's figures (only the count when it is empty), and a new window."""
        with self._lock:
            values, self._values = self._values, []
        if not values:
            return {f"{self.key}_n": 0}
        ms = np.asarray(values) * 1e3
        return {f"{self.key}_n": len(ms), f"{self.key}_median": float(np.median(ms)),
                f"{self.key}_p99": float(np.percentile(ms, 99, method="higher")), f"{self.key}_max": float(ms.max())}


def pooled(windows: list[dict[str, float]], key: str) -> dict[str, float]:
    """Many windows' reports of `key` as one: the total count, the count-weighted median of the windows'
    medians (an estimate), the worst window's p99 (an upper bound of the whole run's p99) and the max."""
    rows = [w for w in windows if float(w.get(f"{key}_n", 0)) > 0 and f"{key}_p99" in w]
    if not rows:
        return {"n": 0}
    counts = np.array([float(w[f"{key}_n"]) for w in rows])
    medians = np.array([float(w[f"{key}_median"]) for w in rows])
    order = np.argsort(medians)
    cumulative = np.cumsum(counts[order])
    median = float(medians[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])
    return {"n": int(counts.sum()), "median": median, "p99": max(float(w[f"{key}_p99"]) for w in rows),
            "max": max(float(w[f"{key}_max"]) for w in rows), "windows": len(rows)}
