"""sim_cell, profiler_driver and pose_estimator, each its own process, started afresh under CPU load and
with their links dropped: every `profile` and `pose` stamp follows the trigger (tools/stamp_check.py)."""
from __future__ import annotations

import pytest

from profile_pose_ros.devices.profiler_link import LinkSettings
from profile_pose_ros.sim.robot_controller import TICK_S
from profile_pose_ros.tools.stamp_check import FAULTS, busy_processes, gap_flaws, one_start

PERIOD = 0.012  # sim_cell's default control period, which triggers the profiler
# The driver publishes a stamp only while the clock map bounds its error, either way, within max_stamp_error
# (its default here): two neighbours' gap is then within twice that of a whole number of periods.
TOLERANCE = 2 * LinkSettings().max_stamp_error


ENOUGH = 60  # stamps per topic, each run: the map may vouch for few at first on a loaded runner; wait for them


def assert_periodic(run: dict) -> None:
    """Every gap a whole number of periods, but where the controller's trigger itself stepped: when its task
    misses ticks (its clock overran, or the application's cycle came late) its period (STATE and trigger, one
    task) starts that many ticks later. The controller's own record of its trigger's spacing, on its clock, is
    the witness: no more such steps in the stamps than it made, and every gap a whole number of ticks."""
    reported = str(run["cell"].get("robot_trigger_steps", "0"))
    steps = int(reported) if reported.isdigit() else 0
    for topic in ("profiles", "poses"):
        flaws = gap_flaws(run[topic], PERIOD, TOLERANCE)
        assert flaws["stamps"] >= ENOUGH, (topic, flaws, run["driver"])
        assert flaws["repeated"] == flaws["decreasing"] == 0, (topic, str(flaws), run["driver"])
        ticks = gap_flaws(run[topic], TICK_S, TOLERANCE)  # every gap, not only those a flaw report lists
        assert flaws["not_whole_periods"] <= steps and ticks["not_whole_periods"] == 0, (
            topic, str(flaws), str(ticks), run["cell"], run["driver"])


# each test loads a core with a busy process beside its graph: with no other test beside it
pytestmark = pytest.mark.alone


@pytest.fixture
def cpu_load():
    load = busy_processes(1)
    yield
    for process in load:
        process.kill()
        process.wait()


def test_fresh_starts_under_load_stamp_every_profile_a_whole_number_of_periods_apart(tmp_path, cpu_load) -> None:
    for start in range(3):
        assert_periodic(one_start(tmp_path / f"start{start}", 3.0, True, {}, {}, at_least=ENOUGH))


@pytest.mark.parametrize("fault, every, seconds", [("profiler", 100, 5.0), ("mcu", 300, 9.0),
                                                   ("mcu_reboot", 300, 9.0)])
def test_stamps_stay_periodic_across_reconnects_and_mcu_restarts(tmp_path, cpu_load, fault, every,
                                                                 seconds) -> None:
    run = one_start(tmp_path, seconds, True, {FAULTS[fault]: every}, {}, at_least=ENOUGH)
    assert_periodic(run)
    happened = {"profiler": "profiler_closes", "mcu": "mcu_closes", "mcu_reboot": "mcu_reboots"}[fault]
    assert int(run["cell"][happened]) >= 2, run["cell"]
    if fault != "profiler":  # each MCU restart forgets the pairing and the clock map: both made again
        assert int(run["driver"]["pairings"]) >= 3, run["driver"]
