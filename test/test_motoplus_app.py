"""The MotoPlus application (firmware/motoplus/mpcl_app.c) on the host layer, its interpolation clock
ticked by hand: how it spreads a step, what it does when the controller is not ready or refuses a motion
call, a configuration it must refuse, and the sanitizer-built fuzzer (which must also catch a broken
controller)."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import time

import pytest

from profile_pose_ros.core.wire import motoplus_protocol as mp
from profile_pose_ros.sim import motoplus_app
from profile_pose_ros.sim.motoplus_app import HostApplication
from profile_pose_ros.sim.robot_controller import DEFAULT_LIMITS, configuration
from test_robot_controller import HELLO, Client

pytestmark = pytest.mark.skipif(motoplus_app.compiler() is None, reason="no C compiler")

SERVO_ON = 50073  # MPCL_IO_SERVO_ON
FUZZ = (*motoplus_app.SOURCES, "host/mpcl_fuzz.c")


def wait_for(condition, timeout: float = 5.0) -> bool:
    """The socket task is a real thread: wait (on the local clock) until it has acted."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.001)
    return condition()


@pytest.fixture
def app():
    application = HostApplication(configuration(DEFAULT_LIMITS, 3), port=0)
    application.port = application.start()
    yield application
    application.stop()


def ticks(app: HostApplication, count: int) -> list[tuple[int, ...]]:
    return [app.tick((0,) * 6, timeout_s=1.0) for _ in range(count)]


def armed(app: HostApplication) -> Client:
    """A client armed, and the clock one cycle before a period starts (the period's cycle is the one that
    brings the count to a multiple of 3)."""
    client = Client(app.port)
    client.send(HELLO)
    assert wait_for(lambda: app.status().armed), app.status().stats.last_fault
    ticks(app, (2 - app.status().cycles) % 3)
    return client


def test_a_periods_step_is_spread_evenly_over_its_cycles(app) -> None:
    client = armed(app)
    client.send(mp.Correction((90, -91, 0, 0, 0, 100)))
    assert wait_for(lambda: app.status().pending)
    moved = ticks(app, 3)
    assert [m[0] for m in moved] == [30, 30, 30]
    assert [m[1] for m in moved] == [-31, -30, -30]
    assert [m[5] for m in moved] == [34, 33, 33]  # one period's step, never faster than step / period
    assert app.status().offset[:2] == [90, -91]


def test_a_controller_that_stops_being_ready_faults_the_session_and_moves_nothing(app) -> None:
    client = armed(app)
    app.set_io(SERVO_ON, False)
    client.send(mp.Correction((50,) + (0,) * 5))
    assert wait_for(lambda: app.status().pending)
    assert all(m == (0,) * 6 for m in ticks(app, 6))
    fault = client.next(mp.Fault)
    assert fault.body.code == mp.FAULT_ALARM and not app.status().armed
    assert wait_for(lambda: not app.status().connected)  # the socket task lets the faulted peer go
    client = Client(app.port)  # and a HELLO while it is not ready is refused
    client.send(HELLO)
    assert client.next(mp.Fault).body.code == mp.FAULT_ALARM


def test_a_refused_motion_call_latches_a_fault_until_a_new_hello(app) -> None:
    client = armed(app)
    app.set_motion_error(-1)
    client.send(mp.Correction((60,) + (0,) * 5))
    assert wait_for(lambda: app.status().pending)
    moved = ticks(app, 3)
    assert moved == [(0,) * 6] * 3 and app.status().motion_errors == 1
    assert client.next(mp.Fault).body.code == mp.FAULT_ALARM and not app.status().armed


@pytest.mark.parametrize("offset, value, said", [(0, 0, r"max_step\[x\] = 0"),
                                                  (14, 2 ** 31 - 1, r"max_speed\[z\] = 2147483647"),
                                                  (18, 10 ** 6, "max_watchdog 1000000 ms"),
                                                  (19, 0, "0 cycles")])
def test_a_configuration_outside_its_ranges_is_refused_with_an_alarm(offset, value, said) -> None:
    config = configuration(DEFAULT_LIMITS, 3)
    config[offset] = value
    application = HostApplication(config, port=0)
    with pytest.raises(RuntimeError, match=said):
        application.start()
    application.stop()


def test_two_controllers_side_by_side_listen_on_ports_of_their_own() -> None:
    """Port 0 on the PC: any free one (the configured D100 is the controller's, not the simulation's)."""
    first, second = (HostApplication(configuration(DEFAULT_LIMITS, 3), port=0) for _ in range(2))
    try:
        ports = first.start(), second.start()
        assert ports[0] != ports[1] and 50241 not in ports
    finally:
        first.stop()
        second.stop()


def test_a_peer_from_another_address_is_closed_at_once() -> None:
    application = HostApplication(configuration(DEFAULT_LIMITS, 3, bridge_address="127.0.0.2"), port=0)
    port = application.start()
    try:
        stranger = Client(port)  # from 127.0.0.1
        with pytest.raises(ConnectionError):
            stranger.send(HELLO)
            stranger.next()
        assert wait_for(lambda: application.status().stats.refused_peers == 1)
        assert not application.status().armed
    finally:
        application.stop()


def fuzz(tmp_path, streams: int, source=None) -> tuple[subprocess.CompletedProcess, dict]:
    binary = motoplus_app.build("mpcl_fuzz", FUZZ, motoplus_app.sanitizers(tmp_path), source=source)
    run = subprocess.run([str(binary), str(streams), "7"], capture_output=True, text=True, timeout=600)
    return run, json.loads(run.stdout)


def test_fuzzed_streams_never_move_beyond_the_controllers_limits(tmp_path) -> None:
    run, result = fuzz(tmp_path, 20000)
    assert run.returncode == 0 and result["violations"] == 0, result["first_violation"]
    assert run.stderr == ""  # no sanitizer report
    # the streams reach every rule: sessions armed, steps clamped, and each fault the application raises
    assert result["sessions"] > 5000 and result["clamped_periods"] > 1000 and result["moving_cycles"] > 10000
    codes = result["faults_by_code"]
    assert all(codes[code] > 0 for code in (mp.FAULT_SEQUENCE_GAP, mp.FAULT_WATCHDOG, mp.FAULT_LIMIT,
                                            mp.FAULT_PROTOCOL, mp.FAULT_NOT_ARMED, mp.FAULT_ALARM)), codes


@pytest.mark.parametrize("rule, file, broken, said", [
    ("the clamp", "mpcl_session.c", ("s->cut = mpcl_clamp(increment, s->step);", "s->cut = 0;"),
     "cycle share|period step"),
    ("narrowing", "mpcl_session.c", ("h->max_step[i] < 1 || h->max_step[i] > c->max_step[i]", "h->max_step[i] < 1"),
     "widened session step"),
    ("readiness", "mpcl_session.c", ("if (!ready) {\n        fault(", "if (0) {\n        fault("), "not ready"),
    ("the offset's bookkeeping", "mpcl_app.c", ("    if (!app.session.armed || app.session.close) drop_remaining();", ""),
     "reported offset")])
def test_the_fuzzer_catches_a_controller_that_breaks_a_rule(tmp_path, rule, file, broken, said) -> None:
    source = tmp_path / "motoplus"
    shutil.copytree(motoplus_app.firmware_dir(), source)
    session = source / file
    text = session.read_text()
    assert broken[0] in text, rule
    session.write_text(text.replace(broken[0], broken[1]))
    run, result = fuzz(tmp_path, 5000, source)
    assert run.returncode == 1 and result["violations"] > 0 and re.search(said, result["first_violation"]), result
