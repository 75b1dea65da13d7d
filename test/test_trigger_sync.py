"""Trigger-MCU lines, the 32-bit clock unwrap, the clock map and trigger/profile pairing (pure code)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from profile_pose_ros.core.timing.clock_sync import ClockMap, SampleWindow, TriggerMatcher, chunk_minima, lower_envelope_slope
from profile_pose_ros.core.wire.trigger_protocol import (MICROS_WRAP, Ack, McuError, MicrosUnwrapper, Pong, Ready, Trigger,
                                                         TriggerLineError, format_trigger, parse_line)


def test_every_message_parses() -> None:
    assert parse_line(format_trigger(12, MICROS_WRAP + 5).strip()) == Trigger(12, 5)
    assert parse_line(b"PONG 99") == Pong(99)
    assert parse_line(b"OK DISARM") == Ack("DISARM")
    assert parse_line(b"READY trigger_mcu 1\r") == Ready("trigger_mcu", "1")
    assert parse_line(b"E unknown command FOO") == McuError("unknown command FOO")


@pytest.mark.parametrize("line", [b"", b"T 1", b"T -1 5", b"T 1 4294967296", b"T x 5", b"PONG", b"OK JUMP",
                                  b"\xff\xfe", b"T 1 2 3", b"hello", b"T " + b"9" * 70])
def test_garbage_lines_are_rejected(line: bytes) -> None:
    with pytest.raises(TriggerLineError):
        parse_line(line)


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=80))
def test_fuzz_lines_parse_or_raise_the_documented_error(line: bytes) -> None:
    try:
        parse_line(line)
    except TriggerLineError:
        pass


def test_unwrap_counts_wraps_and_tolerates_small_steps_back() -> None:
    unwrap = MicrosUnwrapper()
    values = [MICROS_WRAP - 10, MICROS_WRAP - 5, 3, 1, 20]
    assert [unwrap(v) for v in values] == [MICROS_WRAP - 10, MICROS_WRAP - 5, MICROS_WRAP + 3, MICROS_WRAP + 1,
                                           MICROS_WRAP + 20]


def simulated_samples(rate_hz: float, seconds: float, drift_ppm: float, seed: int = 0):
    """(device time, host arrival, true host time): a drifting clock seen through a jittery link."""
    rng = np.random.default_rng(seed)
    host = 1.79e9 + np.arange(0, seconds, 1.0 / rate_hz)
    device = 4000.0 + (host - host[0]) * (1 + drift_ppm * 1e-6)
    arrival = host + 20e-6 + rng.exponential(150e-6, len(host))  # a floor plus scheduling jitter
    return device, arrival, host


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 30), st.integers(0, 4)), min_size=1, max_size=200))
def test_chunk_minima_is_the_sorted_pick(pairs: list[tuple[int, int]]) -> None:
    """The O(n) pick is what sorting by (chunk, value) and taking each chunk's first gives."""
    chunk = np.sort(np.array([c for c, _ in pairs]))
    values = np.array([v for _, v in pairs], dtype=float)
    order = np.lexsort((values, chunk))
    assert np.array_equal(chunk_minima(chunk, values), order[np.r_[True, np.diff(chunk[order]) > 0]])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 0.5), max_size=3000), st.floats(0.01, 2.0))
def test_sample_window_keeps_exactly_the_last_window(steps: list[float], window_s: float) -> None:
    window, kept = SampleWindow(capacity=4), []
    device = 0.0
    for k, step in enumerate(steps):
        device += step
        window.append(device, float(k), window_s)
        kept = [(d, h) for d, h in kept + [(device, float(k))] if device - d <= window_s]
        if k % 97 == 0 or k == len(steps) - 1:
            d, h = window.arrays()
            assert list(zip(d.tolist(), h.tolist())) == kept
            assert window.span() == kept[-1][0] - kept[0][0]


@pytest.mark.parametrize("drift_ppm", [-5000.0, 0.0, 300.0])
def test_clock_map_follows_drift_to_the_link_floor(drift_ppm: float) -> None:
    clock = ClockMap()
    device, arrival, host = simulated_samples(1000.0, 20.0, drift_ppm)
    errors = []
    for d, a, h in zip(device, arrival, host):
        clock.add(d, a)
        errors.append(clock.to_host(d) - h)
    errors = np.array(errors)[3000:]  # after convergence
    assert clock.converged
    assert abs(clock.drift_ppm - drift_ppm) < 5.0
    assert np.all(errors > 0) and np.max(errors) < 20e-6 + 30e-6  # the floor plus a few us


@pytest.mark.parametrize("drift_ppm", [-5000.0, 300.0])
def test_clock_map_holds_from_half_a_second_on_a_loaded_machine(drift_ppm: float) -> None:
    """A third of the lines wait 1-25 ms for a busy CPU: stamps must not follow them (a least-squares slope
    once tilted the young map by up to 1 %, stamps 5-12 ms off within the first seconds)."""
    worst = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        device, arrival, host = simulated_samples(50.0, 4.0, drift_ppm, seed)
        late = rng.random(len(host)) < 0.3
        arrival[late] += rng.uniform(1e-3, 25e-3, late.sum())
        clock = ClockMap()
        errors = []
        for d, a, h in zip(device, arrival, host):
            clock.add(d, a)
            errors.append(clock.to_host(d) - h)
        worst.append(np.max(np.abs(errors[25:])))  # from 0.5 s on
    assert max(worst) < 0.5e-3


def pings_and_triggers(seconds: float, drift_ppm: float, seed: int, pong_delay_ms: tuple[float, float],
                       bursts: bool):
    """(device time, arrival, true host time, delay bound) of a 12 ms trigger and PONGs every 20 ms: each
    PONG's bound is its round trip (its delay plus the PING's way out); a third of the trigger lines wait
    1-25 ms, and with `bursts` every 0.5 s a CPU stall delivers 4 lines at once."""
    rng = np.random.default_rng(seed)
    lines = []
    for host in np.arange(0.0, seconds, 0.012):
        delay = 20e-6 + (rng.uniform(1e-3, 25e-3) if rng.random() < 0.3 else rng.exponential(100e-6))
        lines.append((host, delay, np.inf))
    for host in np.arange(0.005, seconds, 0.02):
        delay = rng.uniform(*pong_delay_ms) * 1e-3
        lines.append((host, delay, rng.uniform(20e-6, 300e-6)))  # the PING's way out
    lines.sort()
    host = np.array([h for h, _, _ in lines]) + 1.79e9
    arrival = host + np.array([d for _, d, _ in lines])
    if bursts:
        for k, h in enumerate(host):
            stalled_until = np.floor((h - host[0]) / 0.5) * 0.5 + host[0] + 0.048
            if h <= stalled_until:
                arrival[k] = max(arrival[k], stalled_until)
    device = 4000.0 + (host - host[0]) * (1 + drift_ppm * 1e-6)
    return device, arrival, host, arrival - host + np.array([b for _, _, b in lines])  # a round trip, stall and all


@pytest.mark.parametrize("seed", range(6))
def test_clock_map_error_bound_holds_for_every_line(seed: int) -> None:
    """Whenever the map offers a bound, a stamp is between the truth and the truth plus that bound (and the
    slope's few microseconds): a profile stamped under it cannot be a whole trigger period off, nor share
    a stamp with its neighbour."""
    clock = ClockMap()
    device, arrival, host, bounds = pings_and_triggers(6.0, 300.0 * (seed - 3), seed, (0.03, 2.0), bursts=True)
    bounded = 0
    for d, a, h, b in zip(device, arrival, host, bounds):
        clock.add(d, a, b)
        if clock.error_bound < np.inf:
            bounded += 1
            assert abs(clock.to_host(d) - h) <= clock.error_bound + 1e-9
    assert bounded > 0.5 * len(device)


def test_clock_map_bounds_nothing_until_converged_nor_from_slow_pongs() -> None:
    """A young map, or one whose every PONG was slow (a loaded machine), offers no small bound: the
    first seconds after a start or an MCU restart give no trusted stamp."""
    clock = ClockMap()
    device, arrival, host, bounds = pings_and_triggers(6.0, 300.0, 1, (12.0, 30.0), bursts=True)
    for d, a, b in zip(device, arrival, bounds):
        clock.add(d, a, b)
        assert clock.error_bound == np.inf or clock.error_bound >= 12e-3
        if d - device[0] < clock.converged_after_s - 0.05:
            assert clock.error_bound == np.inf
    assert clock.converged and clock.error_bound < np.inf
    clock.reset()
    assert clock.error_bound == np.inf


def test_clock_map_bound_expires_with_the_samples_that_set_the_offset() -> None:
    """PONGs for 3 s, then none: once the last one is out of the recent window, nothing bounds the offset."""
    clock = ClockMap()
    device, arrival, host = simulated_samples(100.0, 6.5, 0.0)
    for d, a, h in zip(device, arrival, host):
        bound = a - h + 1e-4 if d - device[0] < 3.0 else np.inf
        clock.add(d, a, bound)
        if d - device[0] < 3.0:
            three_seconds = clock.error_bound
    assert three_seconds < 2e-4
    assert clock.error_bound == np.inf


def test_clock_map_bound_needs_pongs_early_and_late() -> None:
    """One bounded sample bounds the offset but not the slope: carried over seconds, the map's error is
    unknown, and the map says so."""
    clock = ClockMap()
    device, arrival, host = simulated_samples(100.0, 3.0, 0.0)
    for k, (d, a, h) in enumerate(zip(device, arrival, host)):
        clock.add(d, a, a - h + 1e-4 if k == 250 else np.inf)  # one PONG at 2.5 s
    assert clock.converged and clock.error_bound == np.inf


def test_lower_envelope_slope_ignores_points_above_it() -> None:
    x = np.linspace(0.0, 2.0, 200)
    y = 3e-4 * x + np.where(np.arange(200) % 3 == 0, 0.0, np.random.default_rng(1).uniform(0, 0.02, 200))
    assert lower_envelope_slope(x, y) == pytest.approx(3e-4, abs=1e-9)


def test_clock_map_restarts_when_the_device_clock_jumps_back() -> None:
    clock = ClockMap()
    device, arrival, _ = simulated_samples(100.0, 3.0, 0.0)
    for d, a in zip(device, arrival):
        clock.add(d, a)
    clock.add(0.5, arrival[-1] + 0.01)  # the MCU rebooted: its clock says 0.5 s
    assert clock.resets == 1
    assert abs(clock.to_host(0.5) - (arrival[-1] + 0.01)) < 1e-9


def test_matcher_pairs_the_first_trigger_and_profile_after_arming() -> None:
    matcher = TriggerMatcher()
    matcher.add_trigger(40, 1.0)  # before arming: forgotten
    matcher.arm()
    assert matcher.pairing and matcher.trigger_time(1000) is None
    matcher.note_profile(1000)  # the profile may come before its line ...
    matcher.add_trigger(1, 2.0)  # ... the first line after RESET is seq 1
    matcher.add_trigger(2, 2.012)
    assert not matcher.pairing and matcher.offset == 999
    assert matcher.trigger_time(1000) == 2.0 and matcher.trigger_time(1001) == 2.012
    assert matcher.trigger_time(1002) is None


def test_matcher_offset_survives_the_profilers_count_wrapping() -> None:
    matcher = TriggerMatcher()
    matcher.arm()
    matcher.add_trigger(1, 5.0)
    matcher.note_profile(2 ** 32 - 1)
    matcher.add_trigger(2, 5.001)
    assert matcher.trigger_time(0) == 5.001  # the profiler's count wrapped to 0


def test_matcher_refuses_a_pairing_the_last_count_contradicts() -> None:
    matcher = TriggerMatcher()
    matcher.arm(last_count=500)  # the last profile before disarming was count 500: the next trigger is 501
    matcher.add_trigger(1, 1.0)
    matcher.note_profile(502)  # 501's profile was lost: pairing 502 with seq 1 would be one period off
    assert matcher.offset is None and not matcher.pairing and matcher.disagreements == 1
    matcher.arm(last_count=502)
    matcher.add_trigger(1, 2.0)
    matcher.note_profile(503)
    assert matcher.offset == 502 and matcher.trigger_time(503) == 2.0


def test_clock_map_refuses_a_bound_below_the_samples_own_height() -> None:
    """A PONG paired with a later PING than the one it answered claims a round trip shorter than its delay;
    its height above the map (never below the truth) gives it away, and the bound is not taken."""
    clock = ClockMap()
    device, arrival, host = simulated_samples(100.0, 3.0, 0.0)
    for d, a, h in zip(device, arrival, host):
        clock.add(d, a, a - h + 1e-6)  # true claims: each line's own delay
    assert clock.bounds_refused == 0
    good = clock.error_bound
    clock.add(device[-1] + 0.01, arrival[-1] + 0.01 + 0.3, 1e-5)  # 300 ms late, claiming 10 us
    assert clock.bounds_refused == 1 and clock.error_bound == pytest.approx(good, abs=1e-6)


def test_clock_map_drops_a_false_bound_the_others_contradict() -> None:
    """The first PONG, 5 ms late, claims a 10 us round trip (paired with the wrong PING) before any map
    could refuse it. The other PONGs contradict it: it is dropped, and the bound holds for every line."""
    clock = ClockMap()
    device, arrival, host, bounds = pings_and_triggers(5.0, 300.0, 2, (0.03, 0.3), bursts=False)
    first_pong = int(np.flatnonzero(np.isfinite(bounds))[0])
    arrival[first_pong] += 5e-3
    bounds[first_pong] = 1e-5
    bounded = 0
    for d, a, h, b in zip(device, arrival, host, bounds):
        clock.add(d, a, b)
        if clock.error_bound < np.inf:
            bounded += 1
            assert abs(clock.to_host(d) - h) <= clock.error_bound + 1e-9
    assert clock.bounds_contradicted >= 1 and bounded > 0.3 * len(device)
