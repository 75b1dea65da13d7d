"""The modal law (core/control/modal_control.py) on sim_cell's arm model, without ROS: its model of the loop is
right, it damps the mode where the PD law only avoids it, and it gets there through lost increments."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from profile_pose_ros.core.control.compensator import (AxisKalman, Gains, InputShaper, pd_velocity, zero_vibration_impulses,
                                                       zvd_impulses)
from profile_pose_ros.core.control.modal_control import (MAX_GAP, ModalController, ModalDesign, axis_model,
                                                         effort_at_period, lqr_gain, shaped_step_increments)
from profile_pose_ros.core.control.period_fusion import PeriodPose, fuse_period
from profile_pose_ros.sim.arm import Arm, ArmModel

TICK, TICKS = 0.004, 3
PERIOD = TICK * TICKS
NOISE = np.array([1e-6, 15e-6, 1e-6, 1e-6, 1e-6, 1e-6])


def design(**changes) -> ModalDesign:
    values = dict(frequency_hz=(10.0,) * 6, damping=(0.68, 0.13, 0.53, 0.7, 0.7, 0.7),
                  effort=(10.0, 30.0, 10.0, 10.0, 10.0, 10.0), acceleration_psd=(1e-3,) * 6, offset_walk=(1e-5,) * 6,
                  period_s=PERIOD, loop_delay_s=PERIOD + ArmModel().delay_s, reference_time_constant_s=0.25)
    values.update(changes)
    return ModalDesign(**values)


@pytest.mark.parametrize("periods_of_delay", [1.0, 1.9, 2.5])
def test_the_discrete_model_matches_the_continuous_arm(periods_of_delay: float) -> None:
    """A random command sequence through the model's (A, B) and through the differential equation."""
    f, zeta, delay = 10.0, 0.13, periods_of_delay * PERIOD
    A, B = axis_model(f, zeta, PERIOD, delay)
    w = 2 * np.pi * f
    rng = np.random.default_rng(1)
    increments = rng.normal(0, 1e-4, 40)
    commands = np.cumsum(increments)  # c_k, asked for at pose k, moves the arm from k * PERIOD + delay

    def command(t: float) -> float:
        k = int(np.floor((t - delay) / PERIOD + 1e-9))
        return commands[k] if k >= 0 else 0.0

    x = np.zeros(A.shape[0])
    for inc in increments[:30]:
        x = A @ x + B * inc
    t_end = 30 * PERIOD
    breaks = sorted({k * PERIOD + delay for k in range(40)} | {t_end})
    state, t0 = np.zeros(2), 0.0
    for t1 in [b for b in breaks if b <= t_end]:
        if t1 > t0:
            c = command(0.5 * (t0 + t1))
            state = solve_ivp(lambda _, s: [s[1], w * w * (c - s[0]) - 2 * zeta * w * s[1]], (t0, t1), state,
                              rtol=1e-11, atol=1e-14).y[:, -1]
            t0 = t1
    assert x[0] == pytest.approx(state[0], abs=1e-9)
    assert x[1] == pytest.approx(state[1], abs=1e-7)


@pytest.mark.parametrize("effort", [10.0, 30.0])
def test_one_effort_gives_one_loop_at_any_control_period(effort: float) -> None:
    """The closed loop's poles in continuous time (the mode's and the command's, beside the delay's) at 4 ms
    equal those at 12 ms when the effort is scaled to the period, and not when it is taken as it is."""
    def poles(period: float, weight: float) -> np.ndarray:
        A, B = axis_model(10.0, 0.018, period, period + ArmModel().delay_s)
        closed = np.linalg.eigvals(A - np.outer(B, lqr_gain(A, B, 10.0, weight)))
        s = np.log(closed[np.abs(closed) > 0.2].astype(complex)) / period  # the delay's poles sit at 0
        return np.array(sorted(s, key=lambda v: (v.imag, v.real)))

    at_12ms = poles(0.012, effort_at_period(effort, 0.012))
    assert effort_at_period(effort, 0.012) == effort
    np.testing.assert_allclose(poles(0.004, effort_at_period(effort, 0.004)), at_12ms, rtol=0.02)
    assert np.max(np.abs(poles(0.004, effort) - at_12ms)) > 0.2 * np.max(np.abs(at_12ms))


def test_the_model_settles_where_it_is_commanded() -> None:
    A, B = axis_model(10.0, 0.5, PERIOD, 0.0226)
    x = A @ np.zeros(A.shape[0]) + B * 1e-3
    for _ in range(200):
        x = A @ x
    assert x[0] == pytest.approx(1e-3, rel=1e-9) and abs(x[1]) < 1e-12


def run_loop(law: str, axis: int, target: float, seconds: float = 2.0, lose_every: int = 0,
             kick_at: float | None = None, seed: int = 0, disarmed: tuple[float, float] = (0.0, 0.0),
             sent: list | None = None, model: dict | None = None,
             poses_per_period: int = 1, tell_lost_after: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """sim_cell's controller and arm in one loop: each period the increment asked for at the last pose is
    applied (rounded to 1 um; lost every lose_every-th period and while `disarmed`), then poses are measured
    with noise, `poses_per_period` of them evenly spaced (a profiler on its own faster clock). `sent`
    collects (time, increment on the axis); `model` changes the law's design (a model that is off);
    tell_lost_after > 0: the bridge tells the law of each increment lost that many periods later."""
    rng = np.random.default_rng(seed)
    arm = Arm(ArmModel())
    modal = ModalController(design(**(model or {})), speed_limit=0.05)
    kalman, shaper = AxisKalman(np.array([20.0, 0.5, 20.0, 2.0, 2.0, 2.0])), InputShaper(zvd_impulses(10.0, 0.05))
    gains = Gains((4.0,) * 6, (0.0,) * 6, (0.05,) * 6)
    commanded, pending = np.zeros(6), np.zeros(6)
    reference = np.zeros(6)
    reference[axis] = target
    times, positions, told = [], [], []
    for period in range(int(seconds / PERIOD)):
        t = period * PERIOD
        applied = np.round(pending * 1e6) * 1e-6
        if lose_every and period % lose_every == lose_every - 1 or disarmed[0] <= t < disarmed[1]:
            if tell_lost_after and np.any(applied):  # the answer to the previous period's pose, told later
                told.append((period + tell_lost_after, applied, t - PERIOD))
            applied = np.zeros(6)
        commanded += applied
        for _, motion, answered in [entry for entry in told if entry[0] == period]:
            modal.lost(motion, answered)
        if kick_at is not None and abs(t - kick_at) < PERIOD / 2:
            arm.state[axis, 1] += 0.01  # a knock: 10 mm/s
        for k in range(poses_per_period):
            truth = arm.position
            z = truth + rng.normal(0, NOISE)
            if law == "modal":
                modal.update(t + k * PERIOD / poses_per_period, z, NOISE ** 2, reference)
                velocity = modal.limit(np.full(6, 0.05))
            else:
                kalman.update(t, z, NOISE ** 2)
                velocity = shaper(t, pd_velocity(reference - kalman.position, kalman.velocity, gains))
            if k == 0:
                times.append(t)
                positions.append(truth[axis])
            arm.command = commanded.copy()
            if poses_per_period == 1:
                for _ in range(TICKS):
                    arm.advance(TICK)
            else:
                arm.advance(PERIOD / poses_per_period)
        pending = velocity * PERIOD
        if sent is not None:
            sent.append((t, pending[axis]))
    return np.array(times), np.array(positions)


def ringing(t: np.ndarray, y: np.ndarray) -> float:
    """Std of what a 0.1 s moving average leaves, 0.4-0.9 s after the knock: the ringing, not the loop's
    slow return to its reference."""
    width = 8
    residual = y - np.convolve(y, np.ones(width) / width, mode="same")
    return float(np.std(residual[(t > 1.0) & (t < 1.5)]))


@pytest.mark.parametrize("model", [{}, dict(frequency_hz=(8.0,) * 6), dict(frequency_hz=(12.0,) * 6),
                                   dict(loop_delay_s=0.7 * (PERIOD + ArmModel().delay_s)),
                                   dict(loop_delay_s=1.3 * (PERIOD + ArmModel().delay_s))])
def test_modal_law_damps_a_knock_the_pd_law_leaves_ringing(model: dict) -> None:
    """y: the mode barely decays on its own; after a knock the PD law (which only avoids exciting it)
    leaves it ringing, the modal law damps it, also with its model's frequency 20 % or delay 30 % off."""
    pd_ringing = ringing(*run_loop("pd", axis=1, target=0.0, seconds=2.0, kick_at=0.6))
    modal_ringing = ringing(*run_loop("modal", axis=1, target=0.0, seconds=2.0, kick_at=0.6, model=model))
    assert pd_ringing > 30e-6
    assert modal_ringing < (0.15 if not model else 0.25) * pd_ringing


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_modal_law_reaches_a_step_without_overshoot_through_lost_increments(axis: int) -> None:
    t, y = run_loop("modal", axis=axis, target=1e-3, seconds=2.0, lose_every=20,
                    model=dict(reference_shaping="lag"))
    assert np.mean(y[t > 1.7]) == pytest.approx(1e-3, abs=15e-6)  # the lost motion was made up
    assert y.max() < 1e-3 * 1.03


@pytest.mark.parametrize("axis", [0, 1])
def test_after_two_seconds_of_nothing_reaching_the_arm_the_law_resumes_without_a_burst(axis: int) -> None:
    """The bridge disarmed mid-step: the law went on asking, nothing moved. Its offset state took in what
    never arrived, so re-armed it goes on from where the arm is: no wound-up jump, no overshoot."""
    sent: list = []
    t, y = run_loop("modal", axis=axis, target=1e-3, seconds=4.0, disarmed=(0.3, 2.3), sent=sent,
                    model=dict(reference_shaping="lag"))
    resumed = [abs(inc) for when, inc in sent if when >= 2.3]
    assert y[t >= 2.3][0] < 0.8e-3  # the step was cut short
    assert max(resumed) < 40e-6  # per 12 ms period: the law's normal pace, nothing stored up
    assert y.max() < 1e-3 * 1.02 and np.mean(y[t > 3.7]) == pytest.approx(1e-3, abs=15e-6)


def test_a_new_reference_is_glided_to_not_jumped() -> None:
    modal = ModalController(design(reference_shaping="lag"))
    z, variance = np.zeros(6), np.full(6, 1e-12)
    modal.update(0.0, z, variance, None)
    velocity = modal.update(PERIOD, z, variance, np.array([2e-3, 0, 0, 0, 0, 0]))
    first_increment = velocity[0] * PERIOD
    assert 0 < first_increment < 0.05 * 2e-3


def test_poses_within_a_period_are_not_used_and_a_long_gap_or_time_going_back_restarts() -> None:
    modal = ModalController(design())
    z, variance, reference = np.zeros(6), np.full(6, 1e-12), np.full(6, 1e-3)
    for k in range(5):
        modal.update(k * PERIOD, z, variance, reference)
    velocity = modal.update(4.3 * PERIOD, z + 1.0, variance, reference)  # 1 kHz: no increment of its own
    assert modal.skipped == 1 and np.array_equal(velocity, modal.velocity)
    assert modal.position[0] == pytest.approx(0.0, abs=1e-6)  # and not measured either
    modal.update((5 + MAX_GAP + 1) * PERIOD, z + 5e-3, variance, reference)
    assert modal.position[0] == pytest.approx(5e-3)  # started again where the arm now is
    modal.update(0.0, z + 7e-3, variance, reference)  # the clock went back: not a pose "within a period"
    assert modal.skipped == 1 and modal.position[0] == pytest.approx(7e-3)


@pytest.mark.parametrize("period, poses_per_period", [(0.004, 4), (0.004, 2), (0.012, 12), (0.012, 3), (0.012, 1.0),
                                                      (0.012, 1.2), (0.004, 1.25), (0.004, 1.5), (0.004, 2.5)])
def test_a_profiler_faster_than_the_controller_starts_one_period_per_controller_period(
        period: float, poses_per_period: float) -> None:
    """Poses at 1 kHz, or 100 Hz beside the 83.3 Hz controller, and so on (stamps jittered by 5 % of their
    spacing) beside a 4 ms or 12 ms controller: the law counts the controller's periods, not the poses'. It
    used to start a period every half period at 2 poses a period and more, and with every pose below 1.5."""
    rng = np.random.default_rng(1)
    modal = ModalController(design(period_s=period, loop_delay_s=period + ArmModel().delay_s))
    spacing, seconds = period / poses_per_period, 2.0
    poses = int(seconds / spacing)
    for k in range(poses):
        modal.update(k * spacing + rng.normal(0, 0.05 * spacing), np.zeros(6), np.full(6, 1e-12), np.zeros(6))
    periods = poses - modal.skipped
    assert abs(periods - seconds / period) <= 2


def test_a_knock_is_damped_as_well_with_four_poses_a_period() -> None:
    """The knock of the test above with the profiler 4x faster than the controller: as damped as with one
    pose a period (averaged over four noise draws; the law counting half periods as periods rang ~2x more)."""
    def mean_ringing(law: str, poses_per_period: int) -> float:
        return float(np.mean([ringing(*run_loop(law, axis=1, target=0.0, seconds=2.0, kick_at=0.6, seed=seed,
                                                poses_per_period=poses_per_period)) for seed in range(4)]))

    one, four = mean_ringing("modal", 1), mean_ringing("modal", 4)
    assert four < 1.3 * one and four < 0.2 * mean_ringing("pd", 1)


SIM_DAMPING = (0.68, 0.018, 0.46, 0.7, 0.7, 0.7)  # what profile_pose identify finds on sim_cell's arm


def step_metrics(t: np.ndarray, y: np.ndarray, size: float) -> dict:
    import control

    return control.step_info(y, T=t, yfinal=size)


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("size", [1e-3, 2e-3])
def test_a_planned_step_settles_in_a_fraction_of_the_lagged_one(axis: int, size: float) -> None:
    """ZVDD-shaped feedforward with the feedback on the difference from the model's motion: on sim_cell's
    arm (nonlinear damping, delay) a step rises in ~0.1 s and settles in ~0.2 s, where the lagged reference
    took ~0.56 s and ~1.1 s, with no more overshoot than the 2 % the issue allows."""
    planned = step_metrics(*run_loop("modal", axis=axis, target=size, seconds=1.5,
                                     model=dict(damping=SIM_DAMPING, reference_shaping="zvdd")), size)
    lagged = step_metrics(*run_loop("modal", axis=axis, target=size, seconds=1.5,
                                    model=dict(damping=SIM_DAMPING, reference_shaping="lag")), size)
    assert planned["SettlingTime"] <= 0.3 and planned["RiseTime"] <= 0.15 and planned["Overshoot"] <= 2.0
    assert lagged["SettlingTime"] > 3 * planned["SettlingTime"]


@pytest.mark.parametrize("scale", [0.8, 1.2])
def test_a_planned_step_with_the_modes_frequency_20_percent_off_stays_within_2_percent(scale: float) -> None:
    """The issue allows 5 %; ZVDD alone left the barely damped y 3.7 % here, one derivative more 1.1-1.5 %."""
    frequency = tuple(10.0 * scale for _ in range(6))
    for axis in (0, 1, 2):
        t, y = run_loop("modal", axis=axis, target=1e-3, seconds=1.5,
                        model=dict(damping=SIM_DAMPING, frequency_hz=frequency, reference_shaping="zvdd"))
        assert step_metrics(t, y, 1e-3)["Overshoot"] <= 2.0
        assert np.mean(y[t > 1.3]) == pytest.approx(1e-3, abs=10e-6)  # stable, and there


@pytest.mark.parametrize("lose_every", [7, 9])
def test_a_planned_step_told_of_its_lost_increments_settles_as_if_none_were_lost(lose_every: int) -> None:
    """Every 7th or 9th increment lost (an answer the controller replaced before applying it): told two periods
    later, as the bridge's lost_increment is, the model counts the commands the controller applied and the
    feedback makes the loss up within the 0.3 s settle; untold, the filter learns it as an offset, slowly."""
    settle = {}
    for told in (0, 2):
        settle[told] = [step_metrics(*run_loop("modal", axis=axis, target=size, seconds=1.5, lose_every=lose_every,
                                               tell_lost_after=told,
                                               model=dict(damping=SIM_DAMPING, reference_shaping="zvdd")),
                                     size)["SettlingTime"]
                        for axis in (0, 2) for size in (1e-3, 2e-3)]
    assert max(settle[2]) <= 0.3, settle
    assert max(settle[0]) > 0.4, settle  # the losses do hit the steps


@pytest.mark.parametrize("approach", [(0.0, 0.3), (0.15, 0.3), (0.5, 0.2)])
@pytest.mark.parametrize("step, speed", [(1e-3, 0.04), (-2e-3, 0.04), (1e-4, 0.04), (1e-3, np.inf)])
def test_shaped_increments_add_up_to_the_step_within_the_speed_limit(step: float, speed: float,
                                                                     approach: tuple[float, float]) -> None:
    impulses = zero_vibration_impulses(10.0, 0.1, derivatives=2)
    increments = shaped_step_increments(step, impulses, speed, PERIOD, *approach)
    assert increments.sum() == pytest.approx(step, rel=1e-12)
    assert np.all(np.sign(increments[increments != 0]) == np.sign(step))  # never back, never past
    if np.isfinite(speed):
        assert np.abs(increments).max() <= speed * PERIOD * (1 + 1e-9)
    ramp = (1 - approach[0]) * abs(step) / (speed - 1.875 * approach[0] * abs(step) / approach[1])
    assert len(increments) * PERIOD <= impulses[-1][0] + max(ramp, approach[1] if approach[0] else 0, PERIOD) + PERIOD


IDENTIFIED_AT_STEP_SIZE = dict(frequency_hz=(9.908, 10.03, 9.411, 10.0, 10.0, 10.0),
                               damping=(0.688, 0.047, 0.592, 0.7, 0.7, 0.7))  # profile_pose identify --size 1.5


def open_loop_step(axis: int, size: float, seconds: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    arm = Arm(ArmModel())
    arm.command = np.eye(6)[axis] * size
    times, positions = [], []
    for period in range(int(seconds / PERIOD)):
        times.append(period * PERIOD)
        positions.append(arm.position[axis])
        for _ in range(TICKS):
            arm.advance(TICK)
    return np.array(times), np.array(positions)


@pytest.mark.parametrize("size", [1e-3, 2e-3])
def test_a_planned_step_ends_slowly_enough_for_table_ivs_spectrum(size: float) -> None:
    """Table IV's Mf is the 5-20 Hz content after the step passes 90 %: the shaped ramp's deceleration is
    there (z 2 mm improved 72-88 % on the open loop against the paper's 96.4 %), unless the last share of the
    step comes along a slow approach, when the arm passes 90 % moving slowly. Still settled by 0.3 s."""
    from profile_pose_ros.tools.experiment import PAPER_IMPROVEMENT, step_metrics as table_iv_metrics

    for axis in (0, 2):
        open_loop = table_iv_metrics(*open_loop_step(axis, size), size)["Mf_um"]
        improvement = {}
        for share in (0.0, 0.14):
            runs = [table_iv_metrics(*run_loop("modal", axis=axis, target=size, seconds=1.5, seed=seed, model=dict(
                IDENTIFIED_AT_STEP_SIZE, reference_shaping="zvdd", approach_share=share, approach_s=0.32)), size)
                for seed in range(3)]
            improvement[share] = 100 * (1 - np.mean([r["Mf_um"] for r in runs]) / open_loop)
            if share:
                assert max(r["settling_time_s"] for r in runs) <= 0.3 and max(r["Mp"] for r in runs) <= 2.0
        paper = PAPER_IMPROVEMENT["xyz"[axis]][round(size * 1e3)][2]
        assert improvement[0.14] >= paper + 0.3, (axis, improvement)
        if axis == 2:  # the shaped ramp alone ends fast: z misses the paper's
            assert improvement[0.0] < paper, improvement


def planned_step(axis: int, waited: float, size: float = 1e-3, period_s: float = PERIOD, seconds: float = 0.6,
                 **model) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """A planned step whose reference came `waited` before the period that plans it, as sim_cell runs it (each
    increment applied from the next period, spread over its 4 ms ticks): the arm's position on 0.5 ms samples,
    timed from the reference's arrival, and the increments sent. `model` changes the law's design."""
    arm, step = Arm(ArmModel()), 0.5e-3
    modal = ModalController(design(**{**IDENTIFIED_AT_STEP_SIZE, "reference_shaping": "zvdd", "approach_share": 0.14,
                                      "approach_s": 0.3, "period_s": period_s,
                                      "loop_delay_s": period_s + (period_s - TICK) / 2 + ArmModel().delay_s, **model}),
                            speed_limit=0.05)
    reference = np.eye(6)[axis] * size
    ticks = int(round(period_s / TICK))
    commanded, pending, sent, times, positions = np.zeros(6), np.zeros(6), [], [], []
    for period in range(int(round(seconds / period_s))):
        modal.update(period * period_s, arm.position, NOISE ** 2, reference, waited=waited)
        following = modal.limit(np.full(6, 0.05)) * period_s
        start, commanded = commanded.copy(), commanded + pending
        for k in range(int(round(period_s / step))):
            arm.command = start + pending * min(1.0, (k * step // TICK + 1) / ticks)
            times.append(waited + period * period_s + k * step)
            positions.append(arm.position[axis])
            arm.advance(step)
        sent.append(float(pending[axis]))
        pending = following
    return np.array(times), np.array(positions), sent


def settled_after_its_reference(axis: int, waited: float, size: float = 1e-3) -> tuple[float, list[float]]:
    """When the arm stays within 2 % of a planned step (planned_step), counted from the reference's arrival
    (interpolated between samples), and the increments sent."""
    times, positions, sent = planned_step(axis, waited, size)
    error = np.abs(positions - size) / size
    last = int(np.nonzero(error > 0.02)[0][-1])
    return times[last] + (error[last] - 0.02) / (error[last] - error[last + 1]) * (times[1] - times[0]), sent


def test_a_planned_step_takes_as_long_after_its_reference_whatever_the_phase_it_came_in() -> None:
    """A reference comes anywhere in a controller period and is planned at the next: planned from then, a step
    settles up to a period later after its reference (half a period on average). A well damped axis plans it
    from when it came; a barely damped one waits, its plan unchanged (the sliver the first increment would carry
    unshaped rings there)."""
    for axis in (0, 2):
        settled = [settled_after_its_reference(axis, waited)[0] for waited in (0.0, 0.004, 0.008, 0.0115)]
        assert max(settled) - min(settled) < 0.006, (axis, settled)
    waits = [settled_after_its_reference(1, waited) for waited in (0.0, 0.008)]
    assert waits[0][1] == waits[1][1]
    assert waits[1][0] - waits[0][0] == pytest.approx(0.008, abs=1e-9)


def test_zero_vibration_shapers_leave_no_vibration_at_their_mode() -> None:
    """The residual vibration of the mode after the impulses (sum of gain * e^(zeta w t) e^(i w_d t)): zero
    at the design frequency for ZV, ZVD and ZVDD, and ZVDD the flattest around it."""
    def residual(impulses, f, zeta):
        w, wd = 2 * np.pi * f, 2 * np.pi * f * np.sqrt(1 - zeta ** 2)
        return abs(sum(g * np.exp(zeta * w * t) * np.exp(1j * wd * t) for t, g in impulses)) / \
            sum(g * np.exp(zeta * w * t) for t, g in impulses)

    for derivatives in (0, 1, 2):
        impulses = zero_vibration_impulses(10.0, 0.05, derivatives)
        assert sum(g for _, g in impulses) == pytest.approx(1.0)
        assert residual(impulses, 10.0, 0.05) < 1e-12
    assert zero_vibration_impulses(10.0, 0.05, 1) == zvd_impulses(10.0, 0.05)
    off = [residual(zero_vibration_impulses(10.0, 0.05, d), 8.0, 0.05) for d in (0, 1, 2)]
    assert off[2] < off[1] < off[0] and off[2] < 0.05


@pytest.mark.parametrize("change", [dict(frequency_hz=(10.0,) * 5), dict(damping=(1.0,) * 6),
                                    dict(effort=(0.0,) * 6), dict(loop_delay_s=0.5 * PERIOD),
                                    dict(reference_time_constant_s=0.0), dict(offset_walk=(-1.0,) * 6),
                                    dict(reference_shaping="zv")])
def test_a_bad_design_is_refused(change: dict) -> None:
    with pytest.raises(ValueError):
        ModalController(design(**change))


def test_the_controllers_clock_starts_a_period_at_every_call_however_close_the_stamps() -> None:
    """period_clock robot_state: each STATE brings the period's fused pose, stamped with its newest pose. A STATE
    handled late and the next one on time give stamps well under a period apart; the controller still ran a
    period between them, so the law runs one (on the poses' own spacing it would skip it)."""
    z, variance, reference = np.zeros(6), np.full(6, 1e-12), np.zeros(6)
    for on_ticks, skipped in ((False, 1), (True, 0)):
        modal = ModalController(design())
        for k in range(5):
            modal.update(k * PERIOD, z, variance, reference, tick=k * PERIOD if on_ticks else None)
        modal.update(4.4 * PERIOD, z + 1e-4, variance, reference, tick=5 * PERIOD if on_ticks else None)
        assert modal.skipped == skipped
        assert modal.started_period == on_ticks
    assert modal.position[0] > 0.5e-4  # and measured (the pose skipped would leave it at 0)


def run_on_the_controllers_clock(axis: int, target: float, late_every: int, coast: bool,
                                 seconds: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """period_clock robot_state at one profile a period: the controller triggers the profiler at each STATE, the
    pose reaches the compensator by the next STATE, except every late_every-th, one period later; each STATE is
    answered at once and its answer applied over the next period. Without a pose, coast=True answers on the
    model (ModalController.coast); coast=False answers zero, as the compensator did before."""
    rng = np.random.default_rng(5)
    arm = Arm(ArmModel())
    modal = ModalController(design(damping=SIM_DAMPING, reference_shaping="zvdd",
                                   loop_delay_s=2 * PERIOD + ArmModel().delay_s), speed_limit=0.05)
    reference = np.zeros(6)
    reference[axis] = target
    commanded, answer = np.zeros(6), np.zeros(6)
    in_flight: list[tuple[int, PeriodPose]] = []
    times, positions = [], []
    for k in range(int(seconds / PERIOD)):
        t = k * PERIOD
        commanded += answer  # the answer to the last STATE, applied over this period
        ready = [pose for due, pose in in_flight if due <= k]
        in_flight = [(due, pose) for due, pose in in_flight if due > k]
        answer = np.zeros(6)
        if ready:
            fused = fuse_period(ready, modal.arm_velocity)
            modal.update(fused.stamp, fused.value, fused.variance, reference, tick=t)
            answer = np.round(modal.limit(np.full(6, 0.05)) * PERIOD * 1e6) * 1e-6
        elif coast and modal.coast(reference, t) is not None:
            answer = np.round(modal.limit(np.full(6, 0.05)) * PERIOD * 1e6) * 1e-6
        truth = arm.position  # the profile this STATE triggered
        late = late_every and k % late_every == late_every - 1
        in_flight.append((k + 1 + late, PeriodPose(t, int(t * 1e9), truth + rng.normal(0, NOISE), NOISE ** 2)))
        times.append(t)
        positions.append(truth[axis])
        arm.command = commanded.copy()
        for _ in range(TICKS):
            arm.advance(TICK)
    return np.array(times), np.array(positions)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_on_the_controllers_clock_a_late_pose_does_not_hold_up_the_planned_step(axis: int) -> None:
    """One pose in five a period late: the law answers those periods on its model, so the ZVDD feedforward
    keeps its timing and the barely damped y does not ring; answering zero instead stretches the plan."""
    coasting = step_metrics(*run_on_the_controllers_clock(axis, 1e-3, late_every=5, coast=True), 1e-3)
    on_time = step_metrics(*run_on_the_controllers_clock(axis, 1e-3, late_every=0, coast=True), 1e-3)
    waiting = step_metrics(*run_on_the_controllers_clock(axis, 1e-3, late_every=5, coast=False), 1e-3)
    assert coasting["SettlingTime"] <= 0.3 and coasting["RiseTime"] <= 0.15 and coasting["Overshoot"] <= 2.0
    assert on_time["SettlingTime"] <= 0.3 and on_time["Overshoot"] <= 2.0
    assert waiting["SettlingTime"] > coasting["SettlingTime"] or waiting["Overshoot"] > 2.0


def test_on_the_controllers_clock_the_grid_follows_the_ticks_after_coasting() -> None:
    """A faster profiler's newest pose wanders by up to a period against the ticks, and a stall leaves STATEs
    without poses (coasts). Each STATE advances the model one period on the ticks' grid, and the estimate stays
    on the measurements through every stall."""
    rng = np.random.default_rng(3)
    modal = ModalController(design(period_s=0.004, loop_delay_s=0.0166), speed_limit=0.05)
    arm_at = np.zeros(6)
    worst = 0.0
    for k in range(1500):
        tick = k * 0.004
        if 300 <= k % 500 < 303:  # a stall: three STATEs without a pose
            assert modal.coast(np.zeros(6), tick) is not None
            continue
        stamp = tick - rng.choice([0.9e-3, 1.2e-3, 2.4e-3, 3.5e-3])
        modal.update(stamp, arm_at + rng.normal(0, 5e-6, 6), np.full(6, 25e-12), np.zeros(6), tick=tick)
        worst = max(worst, float(np.max(np.abs(modal.position - arm_at))))
    assert worst < 50e-6, worst


def fast_steps_approach_share(*layers: str) -> float:
    """The reference_approach_share the compensator runs with, config/fast_steps.yaml's layers applied in turn
    over the node's default."""
    from conftest import ROOT
    from profile_pose_ros.nodes.parameters import defaults
    from profile_pose_ros.nodes.pd_compensator import NODE_NAME, PARAMETERS
    from profile_pose_ros.tools.param_files import node_parameters

    values = defaults(PARAMETERS)
    for layer in layers:
        values.update(node_parameters(ROOT / "config" / layer, NODE_NAME, declared=set(values)))
    return values["reference_approach_share"]


def test_each_rates_fast_steps_layer_hands_the_approach_what_its_mf_allows() -> None:
    """Table IV's Mf by the estimate is read one fused pose a control period. Read per 4 ms, less of a faster
    end shows in the post-target spectrum than read per 12 ms: fast_steps_250hz.yaml's smaller approach
    share lets x and z rise sooner at 250 Hz with every Mf above the paper's, where the same share at 12 ms
    takes z 2 mm's Mf below it (which is why the 83.3 Hz layer keeps a larger one)."""
    from profile_pose_ros.tools.experiment import PAPER_IMPROVEMENT, step_metrics as table_iv_metrics, table_iv_reading

    at_83, at_250 = fast_steps_approach_share("fast_steps.yaml"), fast_steps_approach_share(
        "fast_steps.yaml", "fast_steps_250hz.yaml")
    assert at_250 < at_83

    def read(axis: int, size: float, period_s: float, share: float) -> dict:
        """Table IV's metrics of a planned step, read as the experiment reads the estimate at this period."""
        t, y, _ = planned_step(axis, 0.0, size, period_s, seconds=1.6, approach_share=share)
        return table_iv_metrics(*table_iv_reading(t, y, np.ones_like(y), period_s), size)

    def mf_above_paper(axis: int, size: float, closed_loop: dict) -> float:
        open_loop = table_iv_metrics(*open_loop_step(axis, size), size)["Mf_um"]
        return 100 * (1 - closed_loop["Mf_um"] / open_loop) - PAPER_IMPROVEMENT["xyz"[axis]][round(size * 1e3)][2]

    for axis in (0, 2):
        for size in (1e-3, 2e-3):
            fast = read(axis, size, 0.004, at_250)
            above_paper, rise = mf_above_paper(axis, size, fast), fast["rise_time_s"]
            assert above_paper >= 0.5 and rise <= 0.125, (axis, size, above_paper, rise)
            assert rise < read(axis, size, 0.004, at_83)["rise_time_s"] - 0.003
    assert mf_above_paper(2, 2e-3, read(2, 2e-3, PERIOD, at_250)) < 0.0
    # and the 83.3 Hz layer's share leaves z 2 mm's Mf read per 12 ms clear of the paper's, so that the
    # estimate's noise on top does not take it below (the node's 0.14 sat at it)
    assert mf_above_paper(2, 2e-3, read(2, 2e-3, PERIOD, at_83)) >= 0.5
    assert mf_above_paper(2, 2e-3, read(2, 2e-3, PERIOD, 0.14)) < 0.2
