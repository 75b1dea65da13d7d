"""realtime_priority: every thread of a loop node's process runs SCHED_FIFO when it may, and the node
runs on under the normal scheduler, saying so, when it may not."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from profile_pose_ros.nodes.process_tuning import set_realtime
from profile_pose_ros.tools.graph import Graph

SCHED_FIFO, SCHED_OTHER = 1, 0
CHILD = """
import os, threading
from profile_pose_ros.nodes.process_tuning import set_realtime
worker = threading.Thread(target=threading.Event().wait, daemon=True)  # a thread started before
worker.start()
print(set_realtime(7))
print(sorted({os.sched_getscheduler(int(t)) for t in os.listdir('/proc/self/task')}))
"""


def thread_policies(pid: int) -> set[int]:
    """The scheduling policy of every thread of a process (field 41 of /proc/<pid>/task/<tid>/stat)."""
    out = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        out.add(int(task.joinpath("stat").read_text().rsplit(")", 1)[1].split()[38]))
    return out


def child(preexec=None) -> list[str]:
    done = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60,
                          preexec_fn=preexec)
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_priority_zero_leaves_the_scheduler_alone() -> None:
    assert set_realtime(0) == "normal scheduler" and os.sched_getscheduler(0) == SCHED_OTHER


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root (or CAP_SYS_NICE) to grant SCHED_FIFO")
def test_every_thread_becomes_fifo_when_allowed_and_none_when_refused() -> None:
    granted, policies = child()
    assert granted.startswith("SCHED_FIFO 7 on ") and policies == f"[{SCHED_FIFO}]"

    def unprivileged() -> None:  # a new user namespace: no CAP_SYS_NICE where it counts, so the kernel refuses
        import ctypes

        if ctypes.CDLL(None, use_errno=True).unshare(0x10000000) != 0:  # CLONE_NEWUSER
            raise OSError(ctypes.get_errno(), "unshare(CLONE_NEWUSER)")

    refused, policies = child(unprivileged)
    assert refused.startswith("normal scheduler: SCHED_FIFO 7 refused") and policies == f"[{SCHED_OTHER}]"


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root (or CAP_SYS_NICE) to grant SCHED_FIFO")
def test_a_node_started_with_a_priority_runs_fifo_and_reports_it(tmp_path) -> None:
    graph = Graph(tmp_path, client_name="realtime_test")
    try:
        process = graph.start("pose_estimator", {"realtime_priority": 5, "diagnostics_period": 0.2})
        assert graph.spin_until(lambda: graph.diagnostic("pose_estimator", "scheduling") != "", 60.0)
        assert graph.diagnostic("pose_estimator", "scheduling").startswith("SCHED_FIFO 5 on ")
        assert thread_policies(process.pid) == {SCHED_FIFO}
    finally:
        graph.close()
