"""The calibration's moves and recording, as a state machine the calibrate command feeds with what it hears.

Each controller period (each robot_state) it answers with the velocity that moves the tool along a
minimum-jerk path to the next station: open loop, since the bridge integrates it over the period, and
smooth, so the arm's lightly damped mode is barely excited. At a station it waits for the arm to settle,
then records the controller's poses and the estimates for a while; their averages are the station.
Each move starts from where the controller says the tool is, so a move cut short (the bridge stopped the
session, the caller stalled) is resumed from there instead of leaving the rest of the sequence off by it.
Times are the caller's monotonic clock.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model.transform import Transform, difference
from .hand_eye import Station, station

MIN_POSES = 20  # a station with fewer estimates (the gauge out of view, the estimator refusing) is refused
MAX_DWELLS = 3
GAP_S = 0.25  # no period for this long: the arm did not follow the moves meanwhile; resume the phase


@dataclass(frozen=True)
class Timing:
    move_s: float = 0.8
    settle_s: float = 0.8
    dwell_s: float = 1.2


def minimum_jerk_rate(tau: float) -> float:
    """d/dtau of 10 tau^3 - 15 tau^4 + 6 tau^5 (zero rate and acceleration at both ends)."""
    tau = min(max(tau, 0.0), 1.0)
    return 30.0 * tau ** 2 - 60.0 * tau ** 3 + 30.0 * tau ** 4


@dataclass
class Procedure:
    offsets: np.ndarray  # (k, 6) stations as offsets from the start pose; the first is normally zero
    timing: Timing = field(default_factory=Timing)
    index: int = -1  # the station being approached or recorded; -1: not started
    phase: str = "idle"  # idle, moving, settling, recording, returning (at the end), rehoming, rehomed, done
    phase_start: float = 0.0
    recorded: list[Station] = field(default_factory=list)
    failed: str | None = None
    resumed: int = 0  # phases started again after a gap
    _move: np.ndarray = field(default_factory=lambda: np.zeros(6))  # the current move's offset change
    _start_tool: Transform | None = None  # the controller's pose at the start
    _tool: Transform | None = None  # ... and the newest
    _last_call: float = -np.inf
    _tools: list[Transform] = field(default_factory=list)
    _estimates: list[Transform] = field(default_factory=list)
    _covariances: list[np.ndarray] = field(default_factory=list)

    @property
    def done(self) -> bool:
        return self.phase == "done"

    @property
    def motion_s(self) -> float:
        """How long the whole sequence keeps the robot busy (s)."""
        t = self.timing
        return len(self.offsets) * (t.move_s + t.settle_s + t.dwell_s) + t.move_s

    def velocity(self, now: float, tool: Transform) -> np.ndarray:
        """This period's velocity command (m/s, rad/s, base axes); also records the controller's pose."""
        self._tool = tool
        if self.phase == "idle":
            self._start_tool = tool
            self._enter(0, "moving", now)
        elif now - self._last_call > GAP_S:
            self._resume(now)
        self._last_call = now
        elapsed = now - self.phase_start
        t = self.timing
        if self.phase in ("moving", "returning", "rehoming"):
            if elapsed >= t.move_s:
                if self.phase == "returning":
                    self.phase = "done"
                elif self.phase == "rehoming":
                    self.phase = "rehomed"  # at the start pose: the caller starts a session here
                else:
                    self.phase, self.phase_start = "settling", now
                return np.zeros(6)
            return self._move * minimum_jerk_rate(elapsed / t.move_s) / t.move_s
        if self.phase == "settling" and elapsed >= t.settle_s:
            self.phase, self.phase_start = "recording", now
            self._tools, self._estimates, self._covariances = [], [], []
        elif self.phase == "recording":
            self._tools.append(tool)
            # a station short of poses (the estimates came late: this process or the estimator stalled)
            # records on, up to MAX_DWELLS times as long, before it is refused
            if elapsed >= t.dwell_s and (len(self._estimates) >= MIN_POSES or elapsed >= MAX_DWELLS * t.dwell_s):
                self._close_station(now)
        return np.zeros(6)

    def estimate(self, pose: Transform, covariance: np.ndarray) -> None:
        if self.phase == "recording" and np.all(np.isfinite(covariance)):
            self._estimates.append(pose)
            self._covariances.append(covariance)

    def _close_station(self, now: float) -> None:
        if len(self._estimates) < MIN_POSES or not self._tools:
            self.failed = (f"station {self.index} (offset {np.round(self.offsets[self.index], 4).tolist()}): "
                           f"{len(self._estimates)} poses in {MAX_DWELLS * self.timing.dwell_s:g} s, fewer than "
                           f"{MIN_POSES}: is the gauge in view there, and the estimator running?")
            self._enter(len(self.offsets), "returning", now)
            return
        self.recorded.append(station(self._tools, self._estimates, self._covariances))
        last = self.index + 1 >= len(self.offsets)
        self._enter(self.index + 1, "returning" if last else "moving", now)

    @property
    def waiting_for_session(self) -> bool:
        """Back at the start pose after a lost session: the caller ends this session and starts one here."""
        return self.phase == "rehomed"

    def rehome(self, now: float) -> None:
        """A session armed again mid-sequence bounds its offsets from where the tool is, not from the start
        pose: go back there first (within that bound), and let the caller start a session there
        (waiting_for_session, then session_restarted) before going on to the station it was at."""
        if self.phase not in ("idle", "done", "returning"):
            self._enter(self.index, "rehoming", now)
            self._last_call = now

    def session_restarted(self, now: float) -> None:
        if self.phase == "rehomed":
            self._enter(self.index, "moving", now)
            self._last_call = now

    def _enter(self, index: int, phase: str, now: float) -> None:
        """Start the move to station `index`, or to the start pose (returning, rehoming), from where the tool is."""
        to = np.zeros(6) if phase in ("returning", "rehoming") else self.offsets[index]
        self._move = to - self.measured_offset()
        self.index, self.phase, self.phase_start = index, phase, now

    def _resume(self, now: float) -> None:
        """After a gap: a move starts again from where the tool is; a station waits and records afresh."""
        if self.phase in ("moving", "returning", "rehoming"):
            self._enter(self.index, self.phase, now)
        elif self.phase in ("settling", "recording"):
            self.phase, self.phase_start = "settling", now
        self.resumed += 1

    def measured_offset(self) -> np.ndarray:
        """The tool's offset from its start pose as the controller reports it (base axes)."""
        if self._start_tool is None or self._tool is None:
            return np.zeros(6)
        return difference(self._tool, self._start_tool)
