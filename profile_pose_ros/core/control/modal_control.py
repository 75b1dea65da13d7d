"""A model-based alternative to the PD law: per axis, a Kalman filter on a model of the arm's 10 Hz mode and
of the loop's delays, and a linear-quadratic (LQR) feedback of that state, so the loop damps the mode
instead of only not exciting it.

Why: the PD law behind a ZVD shaper sends nothing at 10 Hz, but it adds no damping either. On an axis
whose mode barely decays (sim_cell's y: zeta 0.01 at small amplitude, the paper's open-loop 0.13), any
bump the loop does not cause (an increment the controller lost, a late answer, a knock on the arm) rings
for seconds. Damping it takes the mode's state, and the mode is 10 Hz behind 23 ms of delay (an answer
is applied at the controller's next period, then the arm's command-to-motion delay): a PD on the measured
velocity acts a quarter of a cycle late. The filter here predicts the mode through those delays; the LQR
gain (scipy's discrete Riccati solver) trades the mode's energy against the size of each increment.

The model, per axis, one control period T apart (pose k measured at t_k, its increment applied at the
controller's next period; the arm follows the command after `loop_delay` - T more):

    p'' = w^2 (c(t - loop_delay) + d - p) - 2 zeta w p'

c is the commanded offset (the sum of the increments sent), d an unknown offset the filter estimates:
increments the controller lost or never got, rounding to its 1 um unit, a model that is off. Without d a
lost increment would be a permanent error (the filter would believe the arm was sent there).
State: [p, v, c_(k-a-1) .. c_(k-1), d] with a = floor(loop_delay / T); the input is the next increment.
A new reference can be reached along a planned command (reference_shaping "zvdd"): a ramp at
FEEDFORWARD_SPEED_SHARE of the speed limit, convolved with the ZVDD shaper of each axis's mode, sent as
feedforward increments, so the mode is brought to the target without ringing in about 1.5 of its periods.
ZVDD rather than the shorter ZVD: it tolerates the model's frequency 20 % off; on a barely damped axis
(LIGHTLY_DAMPED) one derivative more, on a well damped one (WELL_DAMPED) one less (docs/robot_side.md). Off
the barely damped axes the last approach_share of the step (0.14 in the node) comes along a minimum-jerk
approach of approach_s (0.32 s) started with the ramp: the arm then passes 90 % of the step slowly, and what
Table IV's post-rise spectrum (Mf) measures is that slow end, not the ramp's deceleration (docs/robot_side.md
has the figures). A barely damped axis plans through ZVDDD, half a period longer, and its Mf is the ring the
feedback damps: no approach there. The model runs the same increments into a
reference state (the arm as the model expects it to move), and the LQR feeds back only the estimated state's
difference from it: what the model misses, a disturbance, the ringing of a mode that is off its model. The
plan starts at rest where the arm is being commanded, so a ringing arm is damped, and a new reference is
planned from the last one's end. The default, "lag", is the feedback alone towards a reference passed through
a first-order filter that starts where the arm is: it waits for that filter (several time constants to
settle); a planned step needs every increment to arrive in its period (docs/robot_side.md has the figures).
One pose per control period drives the law: the first pose at least a period after the one that started
the previous period, less half the poses' spacing (the median of the last SPACING_WINDOW intervals). A
cell that triggers the profiler each period has one pose a period; a profiler on its own faster clock
(1 kHz beside a 4 ms controller) has several, and the others are not used; its periods then follow a
grid at exactly T (its stamps say nothing of the controller's phase), else a profiler 1-1.5x faster than
the controller started a period with every pose. (A pose half a period after the last must not start a
new period: at 1 kHz the filter would run two periods for every one of the controller's. Measuring the
poses between into the state sharpens the state's position but does not hold the arm stiller:
docs/design_notes.md.) A gap of more than MAX_GAP periods, or time going backwards,
restarts.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from statistics import median

import numpy as np
from scipy.linalg import expm, solve_discrete_are

from .compensator import zero_vibration_impulses

MAX_GAP = 4  # periods without a pose after which the filter starts again
# The feedforward plans its ramp at this share of the speed limit: the feedback keeps the rest for corrections.
FEEDFORWARD_SPEED_SHARE = 0.8
REFERENCE_SHAPINGS = ("zvdd", "lag")
# Below this damping ratio an axis's plan goes through one zero derivative more (ZVDDD, half a period longer):
# what a shaper leaves of the mode when the model's frequency is off rings there for seconds, beyond what the
# feedback damps within a 0.3 s settle (with the frequency 20 % low ZVDD leaves 5.6 % of the vibration, ZVDDD
# 2.1 %). A well damped axis damps its own remainder within a cycle.
LIGHTLY_DAMPED = 0.1
# At or above this damping ratio the ramp goes through the shorter ZVD (one period, not one and a half): what
# it leaves of the mode with the model's frequency 20 % off decays within a cycle, and the half period it
# saves is what lets a planned step both rise within 0.15 s and end slowly (approach_share)
WELL_DAMPED = 0.3
EFFORT_PERIOD_S = 0.012  # the period ModalDesign.effort is given for (the paper's 83.3 Hz cell)
SPACING_WINDOW = 15  # recent intervals between poses whose median is the poses' spacing
ONE_POSE_A_PERIOD = 0.98  # poses this close to a period apart (median): one a period, triggered by the controller


@dataclass(frozen=True)
class ModalDesign:
    """Per axis (x y z rx ry rz): the mode's natural frequency (Hz) and damping ratio, the LQR's effort
    weight (larger: smaller increments, less of the estimate's noise in the arm, slower; on an increment of an
    EFFORT_PERIOD_S period, the same loop at any period: effort_at_period), the filter's
    acceleration noise ((m/s^2)^2/Hz) and the offset's random walk (m per period); and for all axes the
    control period, the delay from a pose's stamp to the arm moving on its increment, and the reference
    filter's time constant (s)."""

    frequency_hz: tuple[float, ...]
    damping: tuple[float, ...]
    effort: tuple[float, ...]
    acceleration_psd: tuple[float, ...]
    offset_walk: tuple[float, ...]
    period_s: float = 0.012
    loop_delay_s: float = 0.012 + 0.0106
    reference_time_constant_s: float = 0.25
    reference_shaping: str = "lag"
    # planned steps on an axis not barely damped: this share of a step arrives along a minimum-jerk approach of
    # approach_s (from the same start), the rest along the shaped ramp (module docstring)
    approach_share: float = 0.0
    approach_s: float = 0.3

    def check(self) -> None:
        per_axis = (self.frequency_hz, self.damping, self.effort, self.acceleration_psd, self.offset_walk)
        if any(len(v) != 6 for v in per_axis):
            raise ValueError("modal control: six values per axis for frequency, damping, effort, "
                             "acceleration_psd and offset_walk")
        if not all(0 < f <= 100 for f in self.frequency_hz) or not all(0 <= z < 1 for z in self.damping):
            raise ValueError("modal control: mode frequency in (0, 100] Hz and damping in [0, 1)")
        if min(self.effort) <= 0 or min(self.acceleration_psd) <= 0 or min(self.offset_walk) <= 0:
            raise ValueError("modal control: effort, acceleration_psd and offset_walk must be > 0")
        if not (0 < self.period_s <= 0.1 and self.period_s <= self.loop_delay_s <= 0.5):
            raise ValueError(f"modal control: period in (0, 0.1] s and loop_delay in [period, 0.5] s (an "
                             f"increment is applied at the next period at the earliest), got {self.period_s}, "
                             f"{self.loop_delay_s}")
        if not 0 < self.reference_time_constant_s <= 10:
            raise ValueError("modal control: reference_time_constant in (0, 10] s")
        if not (0 <= self.approach_share < 1 and 0 < self.approach_s <= 2):
            raise ValueError("modal control: approach_share in [0, 1) and approach in (0, 2] s")
        if self.reference_shaping not in REFERENCE_SHAPINGS:
            raise ValueError(f"modal control: reference_shaping is one of {', '.join(REFERENCE_SHAPINGS)}, "
                             f"not {self.reference_shaping!r}")


def shaper_derivatives(damping: float) -> int:
    """The planned ramp's shaper per the mode's damping: ZVD (1), ZVDD (2) or, barely damped, ZVDDD (3)."""
    return 3 if damping < LIGHTLY_DAMPED else 1 if damping >= WELL_DAMPED else 2


def minimum_jerk(s: np.ndarray) -> np.ndarray:
    """0 -> 1 over s in [0, 1] with zero velocity and acceleration at both ends."""
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)


def shaped_step_increments(step: float, impulses, speed: float, period_s: float, approach_share: float = 0.0,
                           approach_s: float = 0.0, lead_s: float = 0.0) -> np.ndarray:
    """Per-period increments (the first applied at once) that move a command by `step`, convolved with the
    shaper's (delay, gain) impulses and sampled at the period boundaries, which the controller joins by
    straight lines. The move: (1 - approach_share) of the step along a ramp, at least one period long, and
    the rest along a minimum-jerk approach of approach_s from the same start. Its speed never exceeds
    `speed` (the ramp leaves the approach its peak speed; the gains are positive and sum to 1) but in the
    first increment, which also carries the move's first lead_s (the time the step waited for its period)."""
    share = approach_share if approach_s > 0 else 0.0
    ramp_speed = speed - (1.875 * share * abs(step) / approach_s if share else 0.0)  # minimum jerk's peak speed
    if share and ramp_speed <= 0:
        raise ValueError("modal control: the approach alone exceeds the planned speed")
    duration = max((1.0 - share) * abs(step) / ramp_speed if ramp_speed > 0 else 0.0, period_s)
    end = max(delay for delay, _ in impulses) + max(duration, approach_s if share else 0.0)
    t = lead_s + np.arange(1, int(np.ceil((end - lead_s) / period_s - 1e-9)) + 1) * period_s
    command = step * sum(gain * ((1.0 - share) * np.clip((t - delay) / duration, 0.0, 1.0)
                                 + (share * minimum_jerk((t - delay) / approach_s) if share else 0.0))
                         for delay, gain in impulses)
    return np.diff(command, prepend=0.0)


def _held_input(frequency_hz: float, damping: float, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(e^(A s), integral of e^(A t) B over [0, s]) for the mode driven by a command held for s."""
    w = 2 * np.pi * frequency_hz
    block = np.zeros((3, 3))
    block[:2, :2] = [[0.0, 1.0], [-w * w, -2 * damping * w]]
    block[1, 2] = w * w
    e = expm(block * seconds)
    return e[:2, :2], e[:2, 2]


def axis_model(frequency_hz: float, damping: float, period_s: float, loop_delay_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) over one period for the state [p, v, c_(k-a-1) .. c_(k-1)] and the input 'next increment'."""
    a = int(np.floor(loop_delay_s / period_s + 1e-9))
    delta = loop_delay_s - a * period_s  # the older command acts over the first delta of the period
    phi_rest, g_new = _held_input(frequency_hz, damping, period_s - delta)
    phi_first, g_first = _held_input(frequency_hz, damping, delta)
    n = 2 + a + 1
    A = np.zeros((n, n))
    A[:2, :2] = phi_rest @ phi_first
    A[:2, 2] = phi_rest @ g_first  # c_(k-a-1)
    A[:2, 3] += g_new  # c_(k-a)
    for i in range(2, n - 1):
        A[i, i + 1] = 1.0  # the history moves on
    A[n - 1, n - 1] = 1.0  # the newest command: c_k = c_(k-1) + increment
    B = np.zeros(n)
    B[n - 1] = 1.0
    return A, B


def effort_at_period(effort: float, period_s: float) -> float:
    """The LQR's weight on one increment at `period_s` for an effort given at EFFORT_PERIOD_S. Summed over a
    second, the mode's energy counts once a period and an increment is the velocity times the period, so the
    weight that asks for the same velocities, the same loop, grows as 1 / period^2. Taken as it is, an effort
    tuned at 12 ms made the 4 ms loop a far more aggressive one, which passed more of the estimate's noise to
    the arm and rang the barely damped y further when the model was off (docs/robot_side.md)."""
    return effort * (EFFORT_PERIOD_S / period_s) ** 2


def lqr_gain(A: np.ndarray, B: np.ndarray, frequency_hz: float, effort: float) -> np.ndarray:
    """Gain K (increment = -K e) minimising the sum of p^2 + (v / w)^2 (the mode's energy, in m^2) and
    effort * increment^2."""
    q = np.zeros_like(A)
    q[0, 0], q[1, 1] = 1.0, (2 * np.pi * frequency_hz) ** -2
    b = B[:, None]
    P = solve_discrete_are(A, b, q, np.array([[effort]]))
    return np.linalg.solve(np.array([[effort]]) + b.T @ P @ b, b.T @ P @ A)[0]


class ModalController:
    """Six axes, each its own model, filter and gain. update() takes a pose's base-frame 6-vector, its
    variances and the reference, and returns the velocity to publish (the bridge integrates it over the
    period into the increment)."""

    def __init__(self, design: ModalDesign, speed_limit=np.inf) -> None:
        design.check()
        self.design = design
        self.speed_limit = np.broadcast_to(np.asarray(speed_limit, dtype=float), (6,)).copy()
        self.impulses = [zero_vibration_impulses(f, z, derivatives=shaper_derivatives(z))
                         for f, z in zip(design.frequency_hz, design.damping)]
        self.approach_share = [design.approach_share if z >= LIGHTLY_DAMPED else 0.0 for z in design.damping]
        T = design.period_s
        models = [axis_model(f, z, T, design.loop_delay_s) for f, z in zip(design.frequency_hz, design.damping)]
        n = models[0][0].shape[0]
        self.n = n
        self.gain = np.array([lqr_gain(A, B, f, effort_at_period(r, T)) for (A, B), f, r
                              in zip(models, design.frequency_hz, design.effort)])  # (6, n)
        # the filter's model: the n states above and the offset d, which enters wherever a command does
        self.A_plan = np.array([A for A, _ in models])  # the reference state's model: no offset
        self.A = np.zeros((6, n + 1, n + 1))
        for i, (A, _) in enumerate(models):
            self.A[i, :n, :n] = A
            self.A[i, :2, n] = A[:2, 2] + A[:2, 3]
            self.A[i, n, n] = 1.0
        q = np.asarray(design.acceleration_psd)[:, None, None] * np.array([[T ** 3 / 3, T ** 2 / 2], [T ** 2 / 2, T]])
        self.W = np.zeros((6, n + 1, n + 1))
        self.W[:, :2, :2] = q
        self.W[:, n, n] = np.asarray(design.offset_walk) ** 2
        self.skipped = 0  # poses within a period that another pose started: not used (over the node's life)
        self.waited = 0.0  # how long the reference had waited for the period being run (update, coast)
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next pose starts the filter (after a stale spell, a restart)."""
        self.time: float | None = None  # when the current period started (a pose's stamp, or on the grid)
        self.last_stamp: float | None = None  # of any pose
        self.intervals: deque[float] = deque(maxlen=SPACING_WINDOW)
        self.x = np.zeros((6, self.n + 1))
        self.P = np.zeros((6, self.n + 1, self.n + 1))
        self.reference_filtered: np.ndarray | None = None
        self._forget_plan()
        self.velocity = np.zeros(6)
        self.pending = np.zeros(6)  # the increment asked for at the last pose: the next period's input
        self.started_period = False  # the last update started a period: self.pending is that period's
        self.coasted = 0  # periods carried by the model alone since the last pose
        self.history: deque[tuple[float, np.ndarray]] = deque(maxlen=2 * MAX_GAP + 2)  # (time, position) a period
        self.last_tick: float | None = None  # the controller's tick of the last period (update/coast with a tick)
        self.ages: deque[float] = deque(maxlen=SPACING_WINDOW)  # tick - the newest pose's stamp, a STATE

    def _forget_plan(self) -> None:
        self.plan_state: np.ndarray | None = None  # (6, n): the reference state, commands absolute
        self.planned = np.zeros(6)  # where the plan ends: the last reference planned for
        self.feedforward = np.zeros((6, 0))  # increments still to send, one column a period
        self.pending_feedforward = np.zeros(6)  # the feedforward part of self.pending

    @property
    def position(self) -> np.ndarray:
        return self.x[:, 0].copy()

    @property
    def arm_velocity(self) -> np.ndarray:
        """The arm's estimated velocity (not the correction's: that is self.velocity)."""
        return self.x[:, 1].copy()

    def update(self, time: float, z: np.ndarray, variance: np.ndarray, reference: np.ndarray | None,
               tick: float | None = None, waited: float = 0.0) -> np.ndarray:
        """The velocity for this pose (zero without a reference: the pose is only measured). tick: the
        controller's tick that began this period (the compensator's period_clock robot_state, one fused pose
        a STATE): then the ticks, not the poses' stamps, say how many periods passed (_update_on_tick).
        waited: how long the reference has waited for this period (s, on the caller's clock; see _plan_towards)."""
        self.waited = waited
        if tick is not None:
            return self._update_on_tick(time, z, variance, reference, tick)
        T = self.design.period_s
        spacing = T  # the poses' median spacing: measured below whenever a period is under way
        if self.time is not None:
            gap = (time - self.time) / T
            if time < self.last_stamp or gap > MAX_GAP + 0.5:
                self.reset()  # time went backwards (a replayed bag, a restarted clock) or a long gap
            else:
                self.intervals.append(min(time - self.last_stamp, T))
                self.last_stamp = time
                spacing = median(self.intervals)
                if gap < 1.0 - 0.5 * spacing / T:
                    self.skipped += 1  # this period has its pose: this one has no increment of its own
                    self.started_period = False
                    return self.velocity
        if self.time is None:
            self.last_stamp = time
            self._start(time, z, variance)
        else:
            # whole periods: stamp jitter is not the arm's time
            periods = max(1, int(round((time - self.time) / T)))
            for _ in range(periods):
                self._predict()  # the periods after the first had no fresh increment from us
            # One pose a period (the controller triggers the profiler): its stamp is the controller's tick, and
            # the period starts there. A profiler on its own clock: its stamps say nothing of the controller's
            # phase, and the periods go on at exactly T. (Taking the stamp there let a profiler 1-1.5x faster
            # than the controller start a period with every pose, each up to half a spacing early: the model
            # ran up to 1.5x fast. Pulling a grid towards such stamps drifts it, as the stamps that start a
            # period are chosen by where the grid is.)
            self.time = time if spacing >= ONE_POSE_A_PERIOD * T else self.time + periods * T
            self._measure(z, variance)
        return self._measured(reference)

    def _update_on_tick(self, time: float, z: np.ndarray, variance: np.ndarray, reference: np.ndarray | None,
                        tick: float) -> np.ndarray:
        """One STATE, one period of the model: each STATE's answer is one increment, however the poses before
        it are spaced (a faster profiler's newest pose wanders by up to a period against the ticks; a STATE read
        late and the next on time come well under a period apart). The period's measurement time is the tick
        less the poses' median age at their STATE, a grid the ticks keep in step: a pose earlier than half a
        period before it belongs to a period the model already passed (coast()) and is measured by its
        difference from the estimate of its own time. A grid placed by the poses' own stamps can end up half a
        period off them after a few coasts: every later pose then counts as late, its innovation is taken a
        period or two behind, and the filter, measured that much in the past, rings up until it overflows."""
        T = self.design.period_s
        if self.time is not None and (time < self.last_stamp or self.last_tick is not None and (
                tick <= self.last_tick or tick - self.last_tick > (MAX_GAP + 0.5) * T)):
            self.reset()  # time went backwards (a replayed bag, a restarted controller) or a long gap
        self.ages.append(tick - time)
        if self.time is None:
            self.last_stamp, self.last_tick = time, tick
            self._start(time, z, variance)
        else:
            self._advance_to(tick)
            self.last_stamp = max(self.last_stamp, time)
            if time < self.time - 0.5 * T:
                innovation = self._innovation_at(time, z)
                if innovation is None:  # older than the history holds: nothing to measure it against
                    self.coasted = 0
                    return self._law(reference)
                z = self.x[:, 0] + innovation
            self._measure(z, variance)
        return self._measured(reference)

    def _measured(self, reference: np.ndarray | None) -> np.ndarray:
        """A period that had its pose: remembered for the late poses to come, and the law run on it."""
        self.coasted = 0
        self.history.append((self.time, self.x[:, 0].copy()))
        return self._law(reference)

    def _advance_to(self, tick: float) -> None:
        """The model through the periods up to `tick` (one unless STATEs went unanswered, or the first tick
        after poses on their own clock), on the ticks' grid."""
        T = self.design.period_s
        periods = 1 if self.last_tick is None else max(1, int(round((tick - self.last_tick) / T)))
        for _ in range(periods):
            self._predict()
        self.last_tick = tick
        self.time = tick - median(self.ages) if self.ages else self.time + periods * T

    def coast(self, reference: np.ndarray | None, tick: float, waited: float = 0.0) -> np.ndarray | None:
        """The controller's period began at `tick` and no pose has come since the last (period_clock
        robot_state): the model carries the state one period and the law runs on it, so a planned step's
        feedforward leaves in its own period however late the estimate is. None once the filter has no state
        to carry (not started, or MAX_GAP periods without a pose: it starts again from the next one)."""
        self.waited = waited
        if self.time is None or self.coasted >= MAX_GAP or self.last_tick is not None and tick <= self.last_tick:
            return None
        self._advance_to(tick)
        self.coasted += 1
        self.history.append((self.time, self.x[:, 0].copy()))
        return self._law(reference)

    def lost(self, motion: np.ndarray, answered: float) -> None:
        """The controller never applied `motion` (m, rad per axis) of the answer to its period at `answered`
        (that STATE's tick or trigger on this clock). The model's commands since then are lowered by it, so the
        feedback acts on what the controller applied and makes the loss up as the LQR weighs it, the mode
        damped; untold, the filter learns a loss only as a slow drift of its offset. Not resent (the plan still
        counts it as sent, so the feedback would make it up as well), nor planned again through the shaper with
        the plan moved back (the plan would then carry the loss's own unshaped kick and ring with it):
        docs/robot_side.md."""
        motion = np.asarray(motion, dtype=float)
        if self.time is None or motion.shape != (6,) or not np.all(np.isfinite(motion)):
            return
        latest = self.last_tick if self.last_tick is not None else self.time
        # the answer's increment joined the commands at the period after `answered`, and each period since moved
        # it one slot older: the slots from there to the newest hold it (all the command slots, 2 .. n-1, at most)
        periods_ago = max(0, int(round((latest - answered) / self.design.period_s)) - 1)
        newest = self.n - 1
        self.x[:, max(2, newest - periods_ago):newest + 1] -= motion[:, None]

    def _innovation_at(self, time: float, z: np.ndarray) -> np.ndarray | None:
        """z's difference from the filter's position estimate of the period nearest its time (None: no longer
        held). Carried to now through the model, as the periods since added only the model's own motion."""
        for when, position in reversed(self.history):
            if abs(when - time) <= 0.5 * self.design.period_s:
                return z - position
        return None

    def _law(self, reference: np.ndarray | None) -> np.ndarray:
        self.started_period = reference is not None
        if reference is None:
            self.velocity, self.pending = np.zeros(6), np.zeros(6)
            self._forget_plan()
            return self.velocity
        if self.design.reference_shaping == "lag":
            return self._control(reference)
        return self._control_planned(reference)

    # ---------------------------------------------------------------- the filter
    def _start(self, time: float, z: np.ndarray, variance: np.ndarray) -> None:
        self.time = time
        n = self.n
        self.x[:] = 0.0
        self.x[:, 0] = z
        self.x[:, n] = z  # the arm at rest where it is measured: commands 0, offset = the position
        self.P[:] = 0.0
        self.P[:, 0, 0] = variance
        self.P[:, 1, 1] = 1e-4
        self.P[:, n, n] = variance

    def _predict(self) -> None:
        self.x = np.einsum("aij,aj->ai", self.A, self.x)
        self.x[:, self.n - 1] += self.pending
        self.pending = np.zeros(6)
        if self.plan_state is not None:
            self.plan_state = np.einsum("aij,aj->ai", self.A_plan, self.plan_state)
            self.plan_state[:, self.n - 1] += self.pending_feedforward
        self.pending_feedforward = np.zeros(6)
        self.P = self.A @ self.P @ self.A.transpose(0, 2, 1) + self.W

    def _measure(self, z: np.ndarray, variance: np.ndarray) -> None:
        s = self.P[:, 0, 0] + variance
        k = self.P[:, :, 0] / s[:, None]  # (6, n+1)
        self.x += k * (z - self.x[:, 0])[:, None]
        self.P -= k[:, :, None] * self.P[:, 0, :][:, None, :]

    # ---------------------------------------------------------------- the law
    def _control(self, reference: np.ndarray) -> np.ndarray:
        n, T = self.n, self.design.period_s
        position = self.x[:, 0]
        if self.reference_filtered is None:
            self.reference_filtered = position.copy()
        self.reference_filtered += (reference - self.reference_filtered) * (
            1.0 - np.exp(-T / self.design.reference_time_constant_s))
        r = self.reference_filtered
        error = np.empty((6, n))
        error[:, 0] = position - r
        error[:, 1] = self.x[:, 1]
        error[:, 2:] = self.x[:, 2:n] + (self.x[:, n] - r)[:, None]
        self.pending = -np.einsum("ai,ai->a", self.gain, error)
        self.velocity = self.pending / T
        return self.velocity

    def _control_planned(self, reference: np.ndarray) -> np.ndarray:
        n, T = self.n, self.design.period_s
        commanded = self.x[:, n - 1] + self.x[:, n]  # where the arm is being sent: newest command + offset
        if self.plan_state is None:  # start at rest there
            self.plan_state = np.repeat(commanded[:, None], n, axis=1)
            self.plan_state[:, 1] = 0.0
            self.planned = commanded.copy()
        self._plan_towards(reference)
        u = self.feedforward[:, 0].copy() if self.feedforward.shape[1] else np.zeros(6)
        self.feedforward = self.feedforward[:, 1:]
        error = np.empty((6, n))
        error[:, :2] = self.x[:, :2] - self.plan_state[:, :2]
        error[:, 2:] = self.x[:, 2:n] + self.x[:, n][:, None] - self.plan_state[:, 2:]
        self.pending_feedforward = u
        self.pending = u - np.einsum("ai,ai->a", self.gain, error)
        self.velocity = self.pending / T
        return self.velocity

    def _plan_towards(self, reference: np.ndarray) -> None:
        """Add to the feedforward the shaped move from where the plan ends to `reference`. On a well damped
        axis the move is planned as if it had begun when the reference came (up to a period before this one:
        its first increment carries the wait), so a step takes as long after its reference whatever the phase
        of the controller's period it came in; planned from this period it starts 0-1 period late, half a
        period on average. The unshaped sliver that first increment carries decays within a cycle there; on a
        less damped axis it would ring past the settle (docs/robot_side.md), so those wait."""
        step = reference - self.planned
        if not np.any(step):
            return
        speed = FEEDFORWARD_SPEED_SHARE * self.speed_limit
        d = self.design
        lead = min(max(self.waited, 0.0), d.period_s)
        moves = [shaped_step_increments(s, imp, v, d.period_s, share, d.approach_s, lead if z >= WELL_DAMPED else 0.0)
                 if s else np.zeros(0)
                 for s, imp, v, share, z in zip(step, self.impulses, speed, self.approach_share, d.damping)]
        length = max(self.feedforward.shape[1], max(len(m) for m in moves))
        feedforward = np.zeros((6, length))
        feedforward[:, :self.feedforward.shape[1]] = self.feedforward
        for axis, move in enumerate(moves):
            feedforward[axis, :len(move)] += move
        self.feedforward, self.planned = feedforward, reference.copy()

    def limit(self, max_speed: np.ndarray) -> np.ndarray:
        """The velocity within a per-axis limit; the filter is told what was really asked for, and what
        the limit took off the feedforward is sent in the next period instead."""
        self.speed_limit = np.broadcast_to(np.asarray(max_speed, dtype=float), (6,)).copy()
        self.velocity = np.clip(self.velocity, -max_speed, max_speed)
        T = self.design.period_s
        self.pending = self.velocity * T
        sent = np.clip(self.pending_feedforward, -self.speed_limit * T, self.speed_limit * T)
        if np.any(sent != self.pending_feedforward):
            if not self.feedforward.shape[1]:
                self.feedforward = np.zeros((6, 1))
            self.feedforward[:, 0] += self.pending_feedforward - sent
            self.pending_feedforward = sent
        return self.velocity
