"""The bridge's sum of the corrections of one answer: nothing lost or sent twice at any correction rate."""
import numpy as np
import pytest

from profile_pose_ros.core.control.correction_spacing import CorrectionSpacing

PERIOD = 0.004


def answers(stamps, batches, velocity=1.0):
    """Feed corrections stamped `stamps` (each `velocity`), answering after each batch size; the increments."""
    spacing, out, queue = CorrectionSpacing(PERIOD), [], list(stamps)
    for n in batches:
        batch = [queue.pop(0) for _ in range(n)]
        for stamp in batch:
            spacing.add(stamp)
        out.append(float(spacing.increment([np.full(6, velocity)] * n)[0]) if n else 0.0)
    return out


def test_one_correction_a_period_late_by_a_fraction_moves_the_arm_by_both_in_the_next_answer() -> None:
    stamps = [k * PERIOD for k in range(10)]
    moved = answers(stamps, [1, 1, 1, 0, 2, 1, 1, 1, 1, 1])
    assert moved[3] == 0.0 and moved[4] == pytest.approx(2 * PERIOD)
    assert sum(moved) == pytest.approx(10 * PERIOD)  # the mean of the two would have lost one period's


def test_four_samples_a_period_move_the_period_once_and_a_late_one_moves_once_later() -> None:
    stamps = [k * PERIOD / 4 for k in range(40)]
    moved = answers(stamps, [4, 4, 3, 5] + [4] * 6)
    assert moved[1] == pytest.approx(PERIOD)
    assert moved[2] == pytest.approx(0.75 * PERIOD) and moved[3] == pytest.approx(1.25 * PERIOD)
    assert sum(moved) == pytest.approx(10 * PERIOD)


def test_jittered_stamps_once_a_period_stand_for_a_whole_period_each() -> None:
    rng = np.random.default_rng(3)
    stamps = np.cumsum(PERIOD + rng.uniform(-0.001, 0.001, 40))  # the newest pose of each controller period
    moved = answers(list(stamps), [1] * 40)
    assert moved[20:] == pytest.approx([PERIOD] * 20, rel=0.26)
    assert np.median(moved[20:]) == pytest.approx(PERIOD, rel=0.05)


def test_repeated_stamps_a_gap_and_a_stamp_going_back_do_not_change_what_a_correction_stands_for() -> None:
    spacing = CorrectionSpacing(PERIOD)
    assert spacing.share == PERIOD  # nothing known yet: one period
    for k in range(10):
        spacing.add(k * 0.001)
    for stamp in (0.009, 0.009, 0.009, 1.0, 0.5, 0.501, 0.502):  # watchdog zeros repeat a stamp; a gap; back
        spacing.add(stamp)
    assert spacing.share == pytest.approx(0.001)
