"""The suite run in parallel (scripts/test.sh): a test marked `alone` has the machine to itself (conftest._Turns)
and a waiting one is not starved by the other workers' tests; each worker keeps to DDS domains of its own."""
from __future__ import annotations

import fcntl
import threading

import pytest

from conftest import _Turns, wait_for
from profile_pose_ros.tools.processes import domain_range, fresh_domain_id


def can_take(turns: _Turns, which: str, mode: int) -> bool:
    handle = getattr(turns, which)
    try:
        fcntl.flock(handle, mode | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    fcntl.flock(handle, fcntl.LOCK_UN)
    return True


def test_an_alone_test_waits_for_the_running_one_and_holds_back_the_next(tmp_path) -> None:
    running, alone, probe = _Turns(tmp_path), _Turns(tmp_path), _Turns(tmp_path)  # three workers
    inside, leave = threading.Event(), threading.Event()

    def alone_test() -> None:
        with alone.turn(alone=True):
            inside.set()
            leave.wait(30.0)

    with running.turn(alone=False):
        assert can_take(probe, "lock", fcntl.LOCK_SH)  # tests run side by side
        waiter = threading.Thread(target=alone_test)
        waiter.start()
        # the alone test waits at the gate's far side: no new test may start, though one still runs
        assert wait_for(lambda: not can_take(probe, "gate", fcntl.LOCK_EX))
        assert not inside.is_set()
    assert inside.wait(10.0)
    assert not can_take(probe, "lock", fcntl.LOCK_SH)  # nothing starts beside it
    leave.set()
    waiter.join(10.0)
    assert can_take(probe, "gate", fcntl.LOCK_EX) and can_take(probe, "lock", fcntl.LOCK_SH)


def test_a_worker_keeps_to_its_domains_and_a_malformed_range_says_what_it_expects(monkeypatch) -> None:
    monkeypatch.setenv("PROFILE_POSE_DOMAIN_IDS", "101-110")
    assert {fresh_domain_id() for _ in range(30)} == set(range(101, 111))
    assert domain_range("") == (1, 200)
    for wrong in ("101", "a-b", "5-3", "0-233", "-1-4"):
        with pytest.raises(ValueError, match="PROFILE_POSE_DOMAIN_IDS"):
            domain_range(wrong)
