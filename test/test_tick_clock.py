"""STATEs read late by a busy host are stamped at their controller's tick."""
import numpy as np
import pytest

from profile_pose_ros.core.timing.tick_clock import TickClock

PERIOD_US = 12_000


def test_ticks_read_late_are_stamped_within_the_least_delay_of_the_window() -> None:
    rng = np.random.default_rng(1)
    clock, epoch = TickClock(), 1_700_000_000.0
    errors = []
    for k in range(2_000):
        tick = epoch + k * PERIOD_US * 1e-6
        delay = 0.1e-3 + (rng.exponential(3e-3) if rng.random() < 0.7 else 8e-3)  # some runs read most STATEs ~8 ms late
        stamp = clock.host_time(k * PERIOD_US, tick + delay)
        if k > 50:
            errors.append(stamp - tick)
    assert max(errors) < 0.5e-3 and min(errors) >= 0.1e-3  # the read times were off by up to ~20 ms


def test_a_restarted_controller_clock_starts_a_new_envelope() -> None:
    clock = TickClock()
    assert clock.host_time(5_000_000, 100.0) == pytest.approx(100.0)
    assert clock.host_time(5_012_000, 100.020) == pytest.approx(100.012)  # 8 ms late: the first one's offset
    assert clock.host_time(12_000, 200.0) == pytest.approx(200.0)  # time_us back to the start: no old offset
    assert clock.host_time(24_000, 200.012) == pytest.approx(200.012)


def test_the_envelope_forgets_what_is_older_than_its_window() -> None:
    clock = TickClock(window_s=1.0)
    clock.host_time(0, 10.0)  # an offset of 10.0 s, then every STATE 5 ms slower
    for k in range(1, 200):
        stamp = clock.host_time(k * PERIOD_US, 10.005 + k * PERIOD_US * 1e-6)
    assert stamp == pytest.approx(10.005 + 199 * PERIOD_US * 1e-6)  # the 10.0 s offset left the window
