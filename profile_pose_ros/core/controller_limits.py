"""The robot controller's own limits, and the session limits a HELLO may ask for within them.

The limits that bound the arm's motion belong to the controller: a client that declares its own could
declare anything (a HELLO asking for a 1000 m step, or a second HELLO that widens the clamp mid-session).
So the controller holds its configured limits, and a HELLO may only narrow them: every field is checked
against both bounds (zero is refused, never read as "no limit"), and the session runs on the narrower of
the two, with the per-period step also bounded by the configured speed.
"""
from __future__ import annotations

from dataclasses import dataclass

from . import motoplus_protocol as mp

HELLO_TIMEOUT_S = 1.0  # a connection that has not armed by then is closed: the one client slot stays free


class HelloRefused(ValueError):
    """A HELLO outside the controller's limits; the text names the field, the value and the bound."""


@dataclass(frozen=True)
class ControllerLimits:
    max_step: tuple[int, ...]  # per period, um / 0.0001 deg
    max_offset: tuple[int, ...]  # total offset from the start pose
    max_speed: tuple[int, ...]  # per second
    max_watchdog_ms: int  # the longest silence a session may ask to be allowed

    @classmethod
    def from_si(cls, max_step, max_offset, max_speed, max_watchdog_s: float) -> "ControllerLimits":
        limits = cls(mp.metres_to_units(max_step), mp.metres_to_units(max_offset), mp.metres_to_units(max_speed),
                     int(round(max_watchdog_s * 1e3)))
        for name in ("max_step", "max_offset", "max_speed"):
            values = getattr(limits, name)
            if len(values) != 6 or min(values) <= 0:
                raise ValueError(f"controller {name} needs six values, each at least one unit")
        if limits.max_watchdog_ms <= 0:
            raise ValueError("controller max_watchdog must be positive")
        return limits

    def session(self, hello: mp.Hello, period_us: int) -> "SessionBounds":
        """The bounds a session runs on; HelloRefused if the HELLO asks for more than this controller allows."""
        if hello.period_us != period_us:
            raise HelloRefused(f"HELLO asks for a {hello.period_us} us period; this controller runs {period_us} us")
        for name, asked, allowed in (("max_step", hello.max_step, self.max_step),
                                     ("max_offset", hello.max_offset, self.max_offset)):
            for axis, (a, b) in enumerate(zip(asked, allowed)):
                if not 0 < a <= b:
                    raise HelloRefused(f"HELLO {name}[{axis}] = {a}: must be 1..{b} (the controller's limit)")
        if not 2 * period_us // 1000 <= hello.watchdog_ms <= self.max_watchdog_ms:
            raise HelloRefused(f"HELLO watchdog_ms = {hello.watchdog_ms}: must be {2 * period_us // 1000}.."
                               f"{self.max_watchdog_ms} (two periods to the controller's limit)")
        by_speed = tuple(max(1, s * period_us // 1_000_000) for s in self.max_speed)
        return SessionBounds(tuple(min(a, s) for a, s in zip(hello.max_step, by_speed)), tuple(hello.max_offset),
                             hello.watchdog_ms)


@dataclass(frozen=True)
class SessionBounds:
    max_step: tuple[int, ...]
    max_offset: tuple[int, ...]
    watchdog_ms: int
