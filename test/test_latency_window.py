"""The nodes' own stage timing (core/timing/latency_window.py) and loss counting (core/timing/sequence_gaps.py)."""
import numpy as np
from hypothesis import given, settings, strategies as st

from profile_pose_ros.core.timing.latency_window import LatencyWindow, pooled
from profile_pose_ros.core.timing.sequence_gaps import SequenceGaps


def test_a_window_reports_and_starts_afresh() -> None:
    window = LatencyWindow("trigger_to_pose_ms")
    assert window.report() == {"trigger_to_pose_ms_n": 0}
    for ms in range(1, 101):
        window.add(ms * 1e-3)
    report = window.report()
    assert report["trigger_to_pose_ms_n"] == 100 and report["trigger_to_pose_ms_max"] == 100.0
    assert report["trigger_to_pose_ms_p99"] == 100.0 and report["trigger_to_pose_ms_median"] == 50.5
    assert window.report() == {"trigger_to_pose_ms_n": 0}


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=300), min_size=1, max_size=12))
def test_the_worst_windows_p99_bounds_the_whole_runs(windows) -> None:
    reports = []
    for values in windows:
        window = LatencyWindow("k")
        for v in values:
            window.add(v)
        reports.append(window.report())
    everything = np.concatenate([np.asarray(v) for v in windows]) * 1e3
    run = pooled(reports, "k")
    assert run["n"] == len(everything) and run["max"] == everything.max()
    assert run["p99"] >= np.percentile(everything, 99, method="higher") - 1e-9
    assert min(np.median(v) for v in windows) * 1e3 - 1e-9 <= run["median"] <= max(np.median(v) for v in windows) * 1e3 + 1e-9


def test_no_reports_pool_to_nothing() -> None:
    assert pooled([{"k_n": 0}], "k") == {"n": 0}


def test_sequence_gaps_count_what_was_never_taken() -> None:
    gaps = SequenceGaps()
    assert gaps.update(40) == 0  # first message: what came before may predate this reader
    assert gaps.update(41) == 0
    assert gaps.update(45) == 3  # 42, 43, 44 overwritten in the queue or lost on the way
    assert gaps.update(None) == 0  # a middleware without sequence numbers: nothing known
    assert gaps.update(6) == 0  # a restarted writer: 1..5 may predate matching it (discovery, not loss)
    assert gaps.update(9) == 2
    assert (gaps.missed, gaps.writers) == (5, 2)
