"""The simulated cell without ROS: a gauge in the world, the profiler on a moving flange, the trigger MCU
and the profiler device, and the robot controller's per-cycle signal that drives them.

Each signal: the MCU fires (if armed), the profiler counts the trigger and renders what it sees at the
profiler's true pose at that instant, and the truth goes to `on_truth` (sim_cell publishes it as
/sim/ground_truth, the paper's VICON).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.model.gauge import Gauge
from ..core.model.render import DEFAULT_PROFILER, ProfilerModel, render_profile
from ..core.compiled.render_kernel import visible_depth_fast
from ..core.timing.latency_window import LatencyWindow
from .motion import MotionSource
from .profiler_device import ProfilerDevice
from .trigger_mcu import TriggerMcu


def paired_clocks(tolerance_ns: int = 20_000, tries: int = 5) -> tuple[int, int]:
    """(wall, monotonic) read at the same instant: the truth's stamp and the MCU's clock come from one
    moment, even if this thread is preempted between two clock reads (retry until they bracket tightly)."""
    for _ in range(tries):
        before = time.time_ns()
        mono = time.monotonic_ns()
        after = time.time_ns()
        if after - before <= tolerance_ns:
            break
    return (before + after) // 2, mono


@dataclass(frozen=True)
class Truth:
    trigger_count: int  # the profiler's count for this trigger
    seq: int  # the MCU's sequence number
    time_ns: int  # host wall-clock time of the trigger (the stamp a perfect driver would give)
    rotation: np.ndarray
    translation: np.ndarray
    frame: str  # what happened to its frame: sent, dropped, corrupted (...)


@dataclass
class SensorNoise:
    noise_std: float = 5e-6  # m, depth repeatability (LJ-X8400: 5 um)
    spike_fraction: float = 0.0


class SimCell:
    def __init__(self, gauge: Gauge, motion: MotionSource, profiler: ProfilerDevice, mcu: TriggerMcu,
                 noise: SensorNoise | None = None, model: ProfilerModel = DEFAULT_PROFILER,
                 on_truth: Callable[[Truth], None] | None = None, seed: int = 2) -> None:
        self.gauge, self.motion, self.profiler, self.mcu = gauge, motion, profiler, mcu
        self.noise = noise or SensorNoise()
        self.model = model
        self.on_truth = on_truth
        self.rng = np.random.default_rng(seed)
        self.start_ns = time.monotonic_ns()
        self.signals = 0
        self.frame_latency = LatencyWindow("trigger_to_frame_sent_ms")
        self.late_signals = 0  # the trigger clock's deadlines skipped, a period or more late (this machine overloaded)
        self._lock = threading.Lock()
        self._clock: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> "SimCell":
        # compile (or load) the ray trace now: the first render would otherwise stall the first cycles
        rotation, translation = self.motion.pose_at(0.0)
        render_profile(self.gauge, rotation, translation, profiler=self.model, depth=visible_depth_fast)
        self.profiler.start()
        self.mcu.start()
        return self

    def robot_signal(self, at_ns: int | None = None, final: bool = False) -> Truth | None:
        """One per-cycle output edge of the robot controller, at monotonic time at_ns (None: now). Thread-safe;
        returns the truth if it fired. A real controller's edges come from its hardware clock, on time
        however late this process is to simulate them: the MCU stamps, the truth and the arm's pose are
        all taken at at_ns."""
        with self._lock:
            wall, mono = paired_clocks()
            if at_ns is not None:
                wall, mono = wall - (mono - at_ns), at_ns
            self.signals += 1
            seq = self.mcu.robot_signal(mono)
            if seq is None:
                return None
            rotation, translation = self.motion.pose_at((mono - self.start_ns) * 1e-9)
            device_us = (mono - self.profiler.boot_ns) // 1000
            points = render_profile(self.gauge, rotation, translation, noise_std=self.noise.noise_std,
                                    spike_fraction=self.noise.spike_fraction, rng=self.rng, profiler=self.model,
                                    depth=visible_depth_fast)
            status = self.profiler.trigger(device_us, self.model.x_start, self.model.x_pitch, points[:, 1],
                                           final=final)
            # the simulator's own share of every latency the loop measures from the trigger: a real profiler's
            # is its exposure and transfer, fixed
            self.frame_latency.add((time.monotonic_ns() - mono) * 1e-9)
            truth = Truth(self.profiler.trigger_count, seq, wall, rotation, translation, status)
        if self.on_truth is not None:
            self.on_truth(truth)
        return truth

    def run_clock(self, rate_hz: float, max_triggers: int = 0) -> None:
        """Signal at rate_hz from a thread (absolute deadlines, so late cycles do not drift the rate),
        replacing a running clock; rate 0 stops it. max_triggers counts from now (0: no limit)."""
        self.stop_clock()
        if rate_hz <= 0:
            return
        self._stop.clear()
        self._clock = threading.Thread(target=self._clock_loop, args=(rate_hz, max_triggers), name="cell-clock",
                                       daemon=True)
        self._clock.start()

    def _clock_loop(self, rate_hz: float, max_triggers: int) -> None:
        """The profiler's own trigger clock. A device fires when it fires: each edge is taken (MCU stamp, truth,
        the arm's pose) at the time this thread gets to it, and deadlines it missed by a whole period are
        skipped (late_signals), not fired late in a batch with past stamps. Such a batch put stamps older than
        the PONGs the MCU had answered meanwhile onto the serial line, which a real MCU never does, and its
        lateness counted as the loop's latency."""
        period = 1.0 / rate_hz
        deadline = time.monotonic() + period
        fired = 0
        while not self._stop.is_set():
            delay = deadline - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
                if self._stop.is_set():
                    return
            elif delay < -period:
                missed = int(-delay / period)
                self.late_signals += missed
                deadline += missed * period
            final = max_triggers > 0 and fired + 1 >= max_triggers
            if self.robot_signal(final=final) is not None:
                fired += 1
                if final:
                    return
            deadline += period

    def join_clock(self, timeout: float) -> bool:
        """Wait for a clock started with max_triggers to fire its last signal; False on timeout."""
        clock = self._clock
        if clock is not None:
            clock.join(timeout)
        return clock is None or not clock.is_alive()

    def stop_clock(self) -> None:
        self._stop.set()
        if self._clock is not None and self._clock.is_alive() and self._clock is not threading.current_thread():
            self._clock.join(timeout=2.0)
        self._clock = None

    def close(self) -> None:
        self.stop_clock()
        self.profiler.close()
        self.mcu.close()
