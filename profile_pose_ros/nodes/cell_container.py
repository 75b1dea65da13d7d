"""cell_container: profiler_driver, pose_estimator, pd_compensator and motoplus_bridge composed in one
process, the loop's topics handed over in-process (local_topics.py), for a cell PC short of CPU at the
paper's 83.3 Hz: less CPU than four processes, increments sent sooner. At 1 kHz on two cores the four
nodes sharing one interpreter lock do worse than four processes (docs/performance.md).

Each node keeps its name, parameters, topics, services and /diagnostics, so the parameter files, the
bringup's checks, bags and `ros2 param` work as with four processes; `profile`, `pose_with_covariance`
and `correction` still reach every other subscriber over DDS. What changes: a profile is estimated,
turned into a correction and stored for the bridge's next answer in the driver's link thread, without
a queue or a wake-up between the nodes; the container's own thread serves the bridge's sent-increment
notes, the compensator's stale-pose watchdog and every node's timers and services. The price: one
process, so a crash in one node takes the others down with it (the bridge's controller then holds
still and ends the session, as for any lost connection), and the four share one GIL.

    cell_container --ros-args --params-file config/cell.yaml
"""
from __future__ import annotations

import sys
import time

from ..core.model.gauge import GaugeError
from .direct_input import serve_ready
from .local_topics import LocalTopics
from .motoplus_bridge import MotoPlusBridgeNode
from .pd_compensator import PdCompensatorNode
from .pose_estimator import PoseEstimatorNode
from .process_tuning import LOOP_SWITCH_INTERVAL_S
from .profiler_driver import ProfilerDriverNode
from .run import StopRequest, run_nodes

NAME = "cell_container"
HOUSEKEEPING_PERIOD = 0.05  # s: every node's timers, services and parameter requests (direct_input.py)


def spin_composed(executor, nodes: list, stop: StopRequest) -> None:
    """The container's thread: the bridge's sent increments (its guard condition) as they come, the
    compensator's watchdog at its deadline, the executor's other work every HOUSEKEEPING_PERIOD."""
    bridge = next(node for node in nodes if isinstance(node, MotoPlusBridgeNode))
    compensator = next(node for node in nodes if isinstance(node, PdCompensatorNode))
    due = time.monotonic()
    while executor.context.ok() and not stop.is_set():
        watchdog_in = compensator.direct_input.tick_due - time.monotonic()
        bridge.pump(max(0.0, min(due - time.monotonic(), watchdog_in)))
        compensator.pump(0.0)  # no inputs of its own here: runs the watchdog if due
        if time.monotonic() >= due:
            serve_ready(executor)
            due = time.monotonic() + HOUSEKEEPING_PERIOD


def main(args=None) -> int:
    local = LocalTopics()
    # Takers first, so that the driver's first profile finds its way; the bridge first of all, so that it
    # is also the first destroyed (STOP), then the driver (no more profiles), then the rest.
    factories = [lambda: MotoPlusBridgeNode(local=local), lambda: PdCompensatorNode(local=local),
                 lambda: PoseEstimatorNode(local=local), lambda: ProfilerDriverNode(local=local)]
    return run_nodes(factories, NAME, args, startup_errors=(ValueError, OSError, GaugeError), spin=spin_composed,
                     destroy_order=lambda nodes: [nodes[0], nodes[3], nodes[2], nodes[1]],
                     switch_interval=LOOP_SWITCH_INTERVAL_S)


if __name__ == "__main__":
    sys.exit(main())
