"""The robot controller's own limits, in its units, as sim_cell configures its controller.

The limits that bound the arm's motion belong to the controller (a client that declares its own could
declare anything). The MotoPlus application (firmware/motoplus) reads them from its D variables and lets
a HELLO narrow them, never widen them; this is the SI-to-units conversion sim_cell's parameters go through
on their way to those variables.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..wire import motoplus_protocol as mp


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
