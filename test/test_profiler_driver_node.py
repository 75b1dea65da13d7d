"""profiler_driver against sim_cell's devices (in this process, on loopback), with real rclpy."""
from __future__ import annotations

import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from profile_pose_ros.core import render_profile
from profile_pose_ros.nodes.diagnostics import ERROR
from profile_pose_ros.nodes.messages import points_from_cloud
from profile_pose_ros.nodes.profiler_driver import ProfilerDriverNode
from profile_pose_ros.sim.cell import SensorNoise, SimCell
from profile_pose_ros.sim.motion import ScriptedMotion, pose_from_vector
from profile_pose_ros.sim.profiler_device import ProfilerDevice
from profile_pose_ros.sim.trigger_mcu import TriggerMcu

MOTION = dict(sine_amplitude=np.array([2e-3, 1e-3, 1e-3, 2e-3, 1e-3, 2e-3]),
              sine_frequency=np.array([0.5, 0.7, 0.3, 0.4, 0.6, 0.2]))


class Rig:
    """sim_cell's devices and a profiler_driver node talking to them, and everything it published."""

    def __init__(self, ros, gauge, profiler_port: int = 0, mcu_port: int = 0, **driver_params) -> None:
        self.ros, self.gauge = ros, gauge
        self.truth: dict[int, object] = {}  # stamp (ns) -> Truth
        self.start_cell(profiler_port, mcu_port)
        params = {"port": self.cell.profiler.port, "serial_url": self.cell.mcu.url, "diagnostics_period": 0.2,
                  **driver_params}
        self.driver = ros.add(ProfilerDriverNode(
            context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))
        self.profiles: list[tuple[float, PointCloud2]] = []
        listener = ros.node("listener")
        qos = QoSProfile(depth=2000, reliability=ReliabilityPolicy.BEST_EFFORT)
        listener.create_subscription(PointCloud2, "profile", lambda m: self.profiles.append((time.monotonic(), m)),
                                     qos)

    def start_cell(self, profiler_port: int = 0, mcu_port: int = 0) -> None:
        motion = ScriptedMotion(*pose_from_vector([0.0, 0.0, 0.45, np.pi, 0.0, 0.0]), **MOTION)
        self.cell = SimCell(self.gauge, motion, ProfilerDevice(port=profiler_port), TriggerMcu(port=mcu_port),
                            SensorNoise(noise_std=0.0), on_truth=self._on_truth).start()

    def _on_truth(self, truth) -> None:
        self.truth[truth.time_ns] = truth

    @property
    def link(self):
        return self.driver.link

    def wait_ready(self, timeout: float = 15.0, settled: float = 0.0) -> None:
        """Streaming, the MCU's clock trained, and the counters ready to be paired by the next trigger.
        `settled`: and the clock map this many seconds of samples old, its drift known well enough that
        its error bound stays under the driver's (just after 2 s it is at the bound's edge)."""
        link = self.link
        assert self.ros.spin_until(lambda: link.state == "streaming" and link.stamps_trusted
                                   and link.trigger.clock.span >= settled and link.matcher.pairing, timeout), (
            link.state, link.last_error, link.trigger.state, link.trigger.last_error, link.trigger.reopens,
            link.matcher.offset, link.counters)

    def run(self, rate_hz: float, triggers: int, timeout: float = 30.0) -> None:
        self.cell.run_clock(rate_hz, triggers)
        counters = self.link.counters

        def done() -> bool:  # every frame decided on: published, or one of the link's counted drops
            return (counters.published + counters.dropped + counters.discarded + counters.late_lines
                    + counters.unconfirmed + counters.untimed) >= triggers
        assert self.ros.spin_until(done, timeout), (counters, self.cell.profiler.trigger_count)
        assert self.cell.join_clock(5.0)  # its last truth is recorded after its profile went out
        self.ros.spin_until(lambda: len(self.profiles) >= counters.published, 2.0)

    def check_published_against_truth(self, stamp_tolerance: float = 2e-3) -> int:
        """Every published profile is the one its stamp's trigger produced, point for point."""
        stamps = np.array(sorted(self.truth))
        for _, msg in self.profiles:
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            nearest = stamps[np.argmin(np.abs(stamps - stamp))]
            assert abs(nearest - stamp) < stamp_tolerance * 1e9
            truth = self.truth[nearest]
            expected = render_profile(self.gauge, truth.rotation, truth.translation, noise_std=0.0)
            got = points_from_cloud(msg)
            np.testing.assert_array_equal(np.isnan(got[:, 1]), np.isnan(expected[:, 1]))
            ok = np.isfinite(expected[:, 1])
            np.testing.assert_allclose(got[ok], expected[ok], atol=1e-7)
        return len(self.profiles)

    def close(self) -> None:
        self.cell.close()


@pytest.fixture
def rig_factory(ros, gauge):
    rigs = []

    def make(**kwargs) -> Rig:
        rigs.append(Rig(ros, gauge, **kwargs))
        return rigs[-1]

    yield make
    for rig in rigs:
        rig.close()


def test_every_profile_is_stamped_with_its_trigger_or_dropped(rig_factory) -> None:
    rig = rig_factory()
    rig.wait_ready(settled=4.0)
    rig.run(200.0, 200)
    c = rig.link.counters
    # every profile published with its trigger's time, or dropped because the clock map could not vouch for
    # it (or its trigger's line came too late): never one with a stamp it could not vouch for, none lost.
    # How many are dropped depends on the runner's load (the simulated MCU answers PINGs from this process):
    # 0 on a quiet machine, 167 of 200 in one CI run, 1 late line in another.
    assert (c.published + c.unconfirmed + c.late_lines, c.dropped, c.bad_frames, c.unsynced) == (200, 0, 0, 0)
    assert c.published > 0
    # paired with the right trigger: the profile is the one rendered at that trigger's pose (it moves)
    assert rig.check_published_against_truth(stamp_tolerance=1e-3) == c.published
    clock = rig.link.trigger.clock  # a few seconds of samples fix the slope
    assert abs(clock.drift_ppm - 300.0) < 50.0  # the simulated MCU's resonator (sharing this process's GIL)


# Tests of counting, not of stamp quality, run the driver with a USB serial adapter's stamp bound (3 ms, as
# config/hardware.yaml) and count the profiles the MCU clock map could not vouch for: how many that is
# depends on how soon a loaded runner's map converges (21 to 213 of ~400 seen in clean-clone CI runs).
COUNTING = {"max_stamp_error": 3e-3}


def test_drop_count_equals_the_devices(rig_factory) -> None:
    rig = rig_factory(**COUNTING)
    rig.cell.profiler.faults.drop_fraction = 0.03
    rig.wait_ready()
    rig.run(200.0, 400)
    assert rig.cell.profiler.frames_dropped > 0
    c = rig.link.counters
    assert c.dropped == rig.cell.profiler.frames_dropped
    assert c.published + c.unconfirmed == 400 - rig.cell.profiler.frames_dropped and c.published > 0


def test_damaged_frames_are_counted_and_never_published(rig_factory) -> None:
    rig = rig_factory(**COUNTING)
    rig.cell.profiler.faults.corrupt_fraction = 0.1
    rig.wait_ready()
    rig.run(150.0, 300)
    c = rig.link.counters
    assert rig.cell.profiler.frames_corrupted > 0 and c.bad_frames >= rig.cell.profiler.frames_corrupted
    # every trigger accounted for; a trigger line that missed sync_timeout on a loaded machine is a counted
    # drop of its own (late_lines: seen once in a clean-clone CI run, 1 of 300), never a published profile
    assert c.published + c.dropped + c.late_lines + c.unconfirmed == 300 and c.late_lines <= 3 and c.published > 0
    rig.check_published_against_truth()


def test_reconnects_within_a_second_when_the_device_closes(rig_factory) -> None:
    rig = rig_factory(**COUNTING)
    rig.cell.profiler.faults.close_after_frames = 60
    rig.wait_ready()
    rig.run(100.0, 400)
    c = rig.link.counters
    assert rig.cell.profiler.closes >= 5 and c.connections >= 6
    # every frame accounted for: published, or dropped, late or with a stamp the clock map could not confirm
    assert c.dropped == rig.cell.profiler.frames_unsent
    assert c.published + c.dropped + c.late_lines + c.unconfirmed == 400
    assert c.late_lines <= 4 and c.published > 0
    # A reconnect to the same device keeps the pairing: no trigger pause. A pairing that failed is rightly
    # done again (seen once, a clean-clone CI run on a loaded machine: 2 pairings): the first profile after
    # arming lost to a close (the two counts disagree), or the MCU too slow to acknowledge a command.
    retried = c.unacknowledged_pairings + rig.link.matcher.disagreements
    assert c.resyncs == 1 + retried, (c, rig.link.matcher.disagreements, rig.link.last_error)
    # Timed by the device, from its drop to the driver's next connection: the gaps between profiles also
    # hold the in-process trigger clock's pace, which a loaded runner slows (60 triggers at 100 Hz once
    # took 3.1 s and left a 1.77 s gap with every reconnect fast).
    delays = rig.cell.profiler.server.reconnect_delays
    assert len(delays) >= rig.cell.profiler.closes - 1 and max(delays) < 1.0, (delays, c)
    rig.check_published_against_truth()


def test_streams_again_after_the_cell_restarts(rig_factory) -> None:
    rig = rig_factory()
    rig.wait_ready()
    rig.run(100.0, 50)
    ports = rig.cell.profiler.port, rig.cell.mcu.port
    rig.cell.close()
    rig.ros.spin_until(lambda: rig.link.state != "streaming", 5.0)
    rig.start_cell(*ports)  # a new process would have a new trigger count and MCU: the same here
    restarted = time.monotonic()
    rig.wait_ready()
    before = rig.link.counters.published
    rig.cell.run_clock(100.0, 100)
    # published by the driver and received by the listener (DDS hands it over a moment after the count)
    assert rig.ros.spin_until(lambda: rig.link.counters.published > before
                              and any(t >= restarted for t, _ in rig.profiles), 5.0)
    assert rig.link.counters.connections == 2
    rig.ros.spin_until(lambda: rig.link.counters.published >= before + 100, 10.0)
    assert rig.cell.join_clock(5.0)
    # a profile that beats the new MCU's READY to the driver is dropped (counted), never published with
    # its receive time or a stale pairing
    assert rig.link.counters.unsynced == 0
    rig.check_published_against_truth()


def test_serial_garbage_is_counted_and_stamps_stay_synced(rig_factory) -> None:
    rig = rig_factory()
    rig.cell.mcu.faults.garbage_fraction = 0.2
    rig.wait_ready(settled=4.0)
    rig.run(100.0, 150)
    assert rig.link.trigger.bad_lines > 0
    c = rig.link.counters
    assert c.unsynced == 0 and c.published + c.unconfirmed == 150 and c.unconfirmed <= 15
    rig.check_published_against_truth()


def test_silent_mcu_stops_the_profiles_with_an_error_and_they_resume_with_trigger_stamps(rig_factory) -> None:
    """A profile without its trigger's time is never stamped with its arrival time: 150 ms late on the
    wire, it would look fresh to every staleness check downstream."""
    rig = rig_factory()
    rig.wait_ready()
    rig.cell.mcu.faults.silent = True
    rig.cell.profiler.faults.delay_s = 0.15
    rig.cell.run_clock(100.0, 0)
    diagnostics = []
    rig.ros.nodes[-1].create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 50)
    link = rig.link
    assert rig.ros.spin_until(lambda: link.trigger.state == "silent", 10.0)
    published_while_silent = link.counters.published
    assert rig.ros.spin_until(lambda: link.counters.untimed > 50, 10.0), link.counters
    assert link.counters.published == published_while_silent and link.counters.unsynced == 0
    said = lambda: any(s.level == ERROR and "not published" in s.message for a in diagnostics for s in a.status)  # noqa
    assert rig.ros.spin_until(said, 5.0)
    rig.cell.mcu.faults.silent = False
    assert rig.ros.spin_until(lambda: link.counters.published > published_while_silent + 50, 10.0)
    assert link.state == "streaming" and link.counters.unsynced == 0
    rig.cell.stop_clock()
    rig.ros.spin_until(lambda: len(rig.profiles) >= link.counters.published, 2.0)
    rig.check_published_against_truth()
