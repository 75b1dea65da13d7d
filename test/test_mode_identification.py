"""Identifying the arm's mode from small steps (core/control/mode_identification.py, tools/identify.py), on
sim_cell's arm model sampled as the profiler sees it: the fit finds the arm's frequency and small-motion
damping, says how sure it is, and finds the steps in a recording by itself."""
from __future__ import annotations

import numpy as np
import pytest

from profile_pose_ros.core.control.mode_identification import combine, fit_step, step_response
from profile_pose_ros.sim.arm import DT, Arm, ArmModel
from profile_pose_ros.tools.identify import find_steps, fit_recorded

PERIOD = 0.012
NOISE = (1e-6, 15e-6, 1e-6)


def stepped_arm(axis: int, size: float, rng, seconds: float = 1.5, phase: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The arm's response to a program step of `size` on `axis` at t = 0, sampled every PERIOD with noise."""
    arm = Arm(ArmModel())
    arm.command[axis] = size
    arm.advance(round(phase / DT) * DT)
    t0 = round(phase / DT) * DT
    times, values = [], []
    for k in range(int(seconds / PERIOD)):
        times.append(t0 + k * PERIOD)
        values.append(arm.position[axis] + rng.normal(0, NOISE[axis]))
        arm.advance(PERIOD)
    return np.array(times), np.array(values)


@pytest.mark.parametrize("axis, damping", [(0, 0.6762), (1, 0.0109), (2, 0.4549)])
def test_small_steps_give_the_arms_frequency_and_small_motion_damping(axis: int, damping: float) -> None:
    rng = np.random.default_rng(axis)
    fits = [fit_step(*stepped_arm(axis, 0.3e-3, rng, phase=rng.uniform(0, PERIOD)), 0.3e-3) for _ in range(3)]
    mode = combine(fits)
    assert mode.frequency_hz == pytest.approx(10.0, rel=0.02)
    # the cubic damping adds a little at 0.3 mm (y most: its linear damping is tiny)
    assert damping - 3 * mode.damping_sigma <= mode.damping <= damping + (0.012 if axis == 1 else 0.015)
    assert mode.gain == pytest.approx(1.0, abs=0.1)
    assert mode.delay_s == pytest.approx(ArmModel().delay_s, abs=0.003)
    assert 0 < mode.frequency_sigma < 0.3 and 0 < mode.damping_sigma < 0.02
    assert mode.residual_rms < 3 * NOISE[axis] + 2e-6


def test_a_fit_says_how_sure_it_is() -> None:
    """On an exact second-order response with known noise, the true values lie within 3 sigma."""
    rng = np.random.default_rng(5)
    t = np.arange(0, 1.5, PERIOD)
    truth = dict(frequency_hz=8.3, damping=0.12, delay_s=0.02)
    misses = 0
    for _ in range(20):
        y = 0.9 * 5e-4 * step_response(t, **truth) + rng.normal(0, 5e-6, len(t))
        fit = fit_step(t, y, 5e-4, noise_std=5e-6)
        misses += abs(fit.frequency_hz - 8.3) > 3 * fit.frequency_sigma or abs(fit.damping - 0.12) > 3 * fit.damping_sigma
    assert misses <= 1


def test_too_few_samples_or_no_step_is_refused() -> None:
    with pytest.raises(ValueError):
        fit_step(np.arange(5) * PERIOD, np.zeros(5), 1e-3)
    with pytest.raises(ValueError):
        fit_step(np.arange(50) * PERIOD, np.zeros(50), 0.0)


def test_steps_are_found_in_a_recording_and_fitted() -> None:
    """A recording as a real cell gives it: rest, a step up on x, rest, a step down on z, ... (positions of
    all three axes, the program's step times unknown to the tool)."""
    rng = np.random.default_rng(7)
    size, t_all, p_all = 0.3e-3, [], []
    position = np.zeros(3)
    for k, (axis, sign) in enumerate([(0, 1), (2, -1), (1, 1)]):
        start = 0.5 + 2.5 * k
        t_rest = np.arange(start - 0.5, start, PERIOD)
        t_all.append(t_rest)
        p_all.append(np.tile(position, (len(t_rest), 1)) + rng.normal(0, 1e-6, (len(t_rest), 3)))
        t_step, y = stepped_arm(axis, sign * size, rng, seconds=2.0, phase=0.005)
        moving = np.tile(position, (len(t_step), 1))
        moving[:, axis] += y
        t_all.append(start + t_step)
        p_all.append(moving)
        position = moving[-1].copy()
    t, p = np.concatenate(t_all), np.concatenate(p_all)
    steps = find_steps(t, p, size)
    assert [axis for axis, _ in steps] == [0, 2, 1]
    # the arm left its rest a delay and the start of a rise after the command
    assert all(0 < when - (0.5 + 2.5 * k) < 0.04 for k, (_, when) in enumerate(steps))
    fits = fit_recorded(t, p, size)
    assert all(len(fits[a]) == 1 for a in "xyz")
    assert all(fits[a][0]["fit"].frequency_hz == pytest.approx(10.0, rel=0.03) for a in "xyz")
    assert fits["z"][0]["step"] < 0  # a step down is fitted as one
