"""The bridge's last line of defence: every increment about to be sent to the robot is checked against the
safety invariants by code that shares nothing with the code that computed it.

The bridge already clamps, zeroes stale corrections and disarms on faults; this monitor re-derives each rule
from the raw facts (the increment, whether the session is armed, the correction's trigger stamp, the
controller's reported total offset, the faults seen since the last explicit arm) so that a bug in one place
cannot move the robot. A violation means such a bug: the increment is replaced by zero, the session is
disarmed, and the count goes to /diagnostics as an ERROR.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

from ..timing.freshness import stamp_age_ok

INVARIANTS = {
    "clamp": "an increment above the per-cycle clamp",
    "not_armed": "motion without an armed session",
    "after_fault": "motion after a fault before an explicit re-arm",
    "stale": "motion on a stale, future-stamped or missing correction",
    "offset": "motion taking the total offset beyond its bound",
}


@dataclass
class SafetyMonitor:
    """Counts, per invariant, the increments that would have broken it (in controller units)."""

    max_step: Sequence[int]
    max_offset: Sequence[int]
    max_age_s: Callable[[], float]  # read at every check: the bridge's max_age may change at run time
    max_future_s: Callable[[], float] = lambda: 0.002  # how far ahead of this clock a stamp may be
    violations: dict[str, int] = field(default_factory=lambda: dict.fromkeys(INVARIANTS, 0))
    checked: int = 0
    last_violation: str = ""
    fault_latched: bool = True  # nothing may move before the first explicit arm

    def rearmed(self) -> None:
        """An explicit arm request (~/start): the only thing that clears a fault."""
        self.fault_latched = False

    def fault(self) -> None:
        """A controller FAULT, a lost session, a protocol error: latched until rearmed()."""
        self.fault_latched = True

    def check(self, units: Sequence[int], armed: bool, stamp_s: float | None, now_s: float,
              offset: Sequence[int] | None) -> list[str]:
        """The invariants this increment would break (empty: send it). A zero increment breaks none."""
        self.checked += 1
        if not any(units):
            return []
        broken = []
        if any(abs(u) > m for u, m in zip(units, self.max_step)):
            broken.append("clamp")
        if not armed:
            broken.append("not_armed")
        if self.fault_latched:
            broken.append("after_fault")
        if stamp_s is None or not stamp_age_ok(now_s - stamp_s, self.max_age_s(), self.max_future_s()):
            broken.append("stale")
        if offset is None or any(abs(o + u) > m for o, u, m in zip(offset, units, self.max_offset)):
            broken.append("offset")
        for name in broken:
            self.violations[name] += 1
        if broken:
            self.last_violation = ", ".join(INVARIANTS[name] for name in broken)
        return broken

    @property
    def total_violations(self) -> int:
        return sum(self.violations.values())
