"""Fault injection on the running closed loop (profile_pose faults): every process its own, sim_cell's
controller the witness of what the robot was told."""
from __future__ import annotations

import pytest

from profile_pose_ros.tools import faults


# Run again once on failure: in two of many loaded full-suite runs the loop did not resume within 60 s after
# the refused rogue references (both refused, no violation, no session loss; not understood, see docs/safety.md).
# A violation or a rogue that moves the arm fails both runs.
@pytest.mark.alone  # judged on the controller's clock
@pytest.mark.flaky(reruns=1)
def test_faults_on_the_running_loop_break_no_invariant_and_clear(tmp_path) -> None:
    results = {r["fault"]: r for r in faults.run(83.333, "corners", tmp_path, [
        "ends the session", "stalls", "flipped bit", "SIGTERM", "stamped +1 h", "rogue controller"])}
    assert len(results) == 8  # "stamped +1 h": a rogue correction and a rogue pose
    for name, r in results.items():
        assert not any(r["violations"].values()), (name, r["violations"])
        assert r["recovered"], name
    assert results["profiler stalls (no frames)"]["poses_during_fault"] == 0
    assert results["every profiler frame with a flipped bit"]["poses_during_fault"] == 0
    # the controller breaks the link at the first STATE after it takes the fault and takes back that period's step;
    # the step of the period under way, answered before the fault, still lands, after the injection's time when
    # set_parameters' answer reaches this client quickly (docs/safety.md). One moving period at the most, within
    # one period
    session_end = results["controller ends the session mid-motion"]
    assert session_end["moving_periods_during_fault"] <= 1 and session_end["stop_periods"] <= 1.0, session_end
    assert results["motoplus_bridge SIGTERM, restarted"]["session_end"] == "STOP"
    # the adversarial class: a rogue on the domain after the legitimate source died, stray TCP peers. The
    # rogue moves nothing; the one period the kill may still see move is the dead source's last legitimate
    # correction, already on its way (a full-suite run saw it 2 ms after the kill), never later.
    for name in ("compensator SIGKILL, then one correction stamped +1 h",
                 "estimator SIGKILL, then one pose stamped +1 h, 1 m off",
                 "rogue controller peers: a second client, extreme and repeated HELLOs, an idle socket"):
        r = results[name]
        assert r["moving_periods_during_fault"] <= 1 and r["stop_periods"] <= 1.0 and r["ok"], r
