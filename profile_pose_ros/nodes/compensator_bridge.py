"""compensator_bridge: pd_compensator and motoplus_bridge in one process, the compensator answering the
controller's clock (period_clock robot_state) from the bridge's socket thread.

With a profiler faster than the controller, the correction a STATE needs is made from the poses that came
since the previous STATE. As two processes that is a round trip (robot_state out, the correction back) of two
publishes and two wake-ups, inside the controller's period; composed, each STATE reaches the compensator as a
call in the socket thread that received it, the poses of the period are fused and the law runs there, and the
increment leaves right after (local_topics.py carries `robot_state`, `correction` and `lost_increment`; all
still go over DDS to any other subscriber). Poses come over DDS from the estimator (profiler_estimator, or
pose_estimator), taken by this process's main thread with the compensator's watchdog; the bridge's sent
increments are published there too. Each node keeps its name, parameters and /diagnostics (docs/performance.md has the figures).

    compensator_bridge --ros-args --params-file config/cell.yaml -p pd_compensator.period_clock:=robot_state
"""
from __future__ import annotations

import sys
import time

from .direct_input import serve_ready
from .local_topics import LocalTopics
from .motoplus_bridge import MotoPlusBridgeNode
from .pd_compensator import PdCompensatorNode
from .process_tuning import LOOP_SWITCH_INTERVAL_S
from .run import StopRequest, run_nodes

NAME = "compensator_bridge"
HOUSEKEEPING_PERIOD = 0.05  # s: both nodes' timers, services and parameter requests (direct_input.py)


def spin_pair(executor, nodes: list, stop: StopRequest) -> None:
    """The main thread: poses (and the watchdog at its deadline) as they come, the bridge's sent increments
    after each, the executor's other work every HOUSEKEEPING_PERIOD."""
    bridge, compensator = nodes
    due = time.monotonic()
    while executor.context.ok() and not stop.is_set():
        compensator.pump(max(0.0, due - time.monotonic()))
        bridge.pump(0.0)
        if time.monotonic() >= due:
            serve_ready(executor)
            due = time.monotonic() + HOUSEKEEPING_PERIOD


def main(args=None) -> int:
    local = LocalTopics(carried=("correction", "robot_state", "lost_increment"))
    # The bridge first, so that it is also the first destroyed (STOP to the controller).
    factories = [lambda: MotoPlusBridgeNode(local=local), lambda: PdCompensatorNode(local=local)]
    return run_nodes(factories, NAME, args, startup_errors=(ValueError, OSError), spin=spin_pair,
                     switch_interval=LOOP_SWITCH_INTERVAL_S)


if __name__ == "__main__":
    sys.exit(main())
