"""Whether a stamped message may still drive motion: two-sided stamp checks, and deadlines on the local
monotonic clock.

A stamp is the trigger time of the profile a message comes from, so on a healthy cell it is always a little
in the past. One stamped in the future is no fresher than a stale one: it comes from a wrong clock (a PC
clock set back, a bad MCU mapping) or a rogue publisher, and a one-sided `now - stamp > limit` test would
let it drive the arm until the wall clock caught up. How long a message stays usable is then counted on
this process's monotonic clock from the moment it arrived, so no later wall-clock step extends it.
"""
from __future__ import annotations

import math


def stamp_age_ok(age_s: float, max_age_s: float, max_future_s: float) -> bool:
    """now - stamp within [-max_future_s, max_age_s]; False for NaN."""
    return -max_future_s <= age_s <= max_age_s


def fresh_until(received_monotonic_s: float, age_at_receipt_s: float, max_age_s: float) -> float:
    """The monotonic time at which a message that was age_at_receipt_s old on arrival turns stale (a stamp
    slightly ahead counts as new, not as extra life)."""
    return received_monotonic_s + max_age_s - max(0.0, age_at_receipt_s)


def describe_age(age_s: float, max_age_s: float, max_future_s: float) -> str:
    """Why a stamp was refused, for logs and diagnostics."""
    if math.isnan(age_s):
        return "stamp is not a number"
    if age_s < -max_future_s:
        return f"stamped {-age_s:.3f} s in the future (tolerance {max_future_s:.3f} s)"
    return f"{age_s:.3f} s old (limit {max_age_s:.3f} s)"
