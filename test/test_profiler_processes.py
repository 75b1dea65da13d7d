"""sim_cell, profiler_driver and pose_estimator as their own processes (profile_pose profiler-check)."""
from __future__ import annotations

from profile_pose_ros.tools.graph import Graph
from profile_pose_ros.tools.profiler_check import CheckRun


def test_three_processes_give_poses_of_the_true_trigger(tmp_path) -> None:
    graph = Graph(tmp_path, client_name="profiler_check_test")
    try:
        # a queue for every profile: the counts below are exact on a CI runner that stalls the estimator
        # for a few hundred ms (the default depth rides out a 20 ms stall at 1 kHz, not that)
        r = CheckRun(graph, rate_hz=83.333, seconds=3.0, noise_std=0.0, drop_fraction=0.03, seed=4,
                     queue_depth=250).run()
    finally:
        graph.close()
    assert r["triggers"] == 250, r
    assert r["sim_frames_dropped"] > 0 and r["driver_profiles_dropped"] == r["sim_frames_dropped"], r
    # every profile the profiler sent is published or refused under a count that says why: a runner that stalls
    # the driver can leave a few trigger times unbounded (dropped_unconfirmed_stamp), never a profile unaccounted
    refused = sum(r[key] for key in ("driver_discarded", "driver_dropped_late_line", "driver_dropped_unconfirmed",
                                     "driver_dropped_out_of_order", "driver_dropped_untimed"))
    assert r["driver_published"] + refused == 250 - r["sim_frames_dropped"] and r["driver_unsynced"] == 0, r
    assert refused <= 25, r
    assert r["estimator_published"] == r["driver_published"] and r["poses_without_truth"] == 0, r
    # a profile paired with the wrong trigger would be off by the motion between cycles (tens of um)
    assert r["position_error_um"]["max"] < 2.0 and r["rotation_error_urad"]["max"] < 10.0
    # stamps: the trigger's time, not the arrival's (which is a millisecond or more later); the 50 us
    # figure is measured by the command on a quiet machine, not asserted on a shared CI runner
    assert r["stamp_error_us"]["median"] < 300.0
