"""The bridge's sum of the corrections of one answer: nothing lost or sent twice at any correction rate."""
import numpy as np
import pytest

from profile_pose_ros.core.control.correction_spacing import CorrectionSpacing

PERIOD = 0.004


def answers(stamps, batches, velocity=1.0, to_states=False):
    """Feed corrections stamped `stamps` (each `velocity`), answering after each batch size; the increments.
    to_states: the corrections answer the controller's STATEs (the bridge's await_reply)."""
    spacing, out, queue = CorrectionSpacing(PERIOD), [], list(stamps)
    for n in batches:
        batch = [queue.pop(0) for _ in range(n)]
        for stamp in batch:
            spacing.add(stamp)
        out.append(float(spacing.increment([np.full(6, velocity)] * n, answers=to_states)[0]) if n else 0.0)
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


def test_answers_to_states_stand_for_a_whole_period_each_however_their_stamps_wander() -> None:
    """A compensator on the controller's clock stamps each answer with its fused poses' time, which wanders
    by a few ms about the controller's tick (spacings 8-16 ms at 83.3 Hz, measured live): a median spacing
    capped at the period read 4-8 % short, and cut every increment by as much."""
    rng = np.random.default_rng(3)
    stamps = np.arange(40) * PERIOD + rng.uniform(-PERIOD / 4, PERIOD / 4, 40)
    assert answers(list(stamps), [1] * 40, to_states=True) == [PERIOD] * 40
    late = answers(list(stamps), [1] * 10 + [0, 2] + [1] * 28, to_states=True)  # one missed its answer
    assert late[10] == 0.0 and late[11] == 2 * PERIOD and sum(late) == pytest.approx(40 * PERIOD)
    capped = answers(list(stamps), [1] * 40)  # read from the stamps, as a free-running correction is
    assert min(capped) < 0.95 * PERIOD and sum(capped) < 0.99 * 40 * PERIOD


def test_samples_faster_than_the_answers_still_stand_for_their_spacing() -> None:
    """A PD law on a 1 kHz profiler behind await_reply: several corrections an answer, each one its spacing
    (taking each for a period would move the arm four times too far)."""
    stamps = [k * PERIOD / 4 for k in range(40)]
    moved = answers(stamps, [4] * 10, to_states=True)
    assert moved == pytest.approx([PERIOD] * 10)


def test_repeated_stamps_a_gap_and_a_stamp_going_back_do_not_change_what_a_correction_stands_for() -> None:
    spacing = CorrectionSpacing(PERIOD)
    assert spacing.share() == PERIOD  # nothing known yet: one period
    for k in range(10):
        spacing.add(k * 0.001)
    for stamp in (0.009, 0.009, 0.009, 1.0, 0.5, 0.501, 0.502):  # watchdog zeros repeat a stamp; a gap; back
        spacing.add(stamp)
    assert spacing.share() == pytest.approx(0.001)
