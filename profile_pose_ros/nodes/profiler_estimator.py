"""profiler_estimator: profiler_driver and pose_estimator in one process, for a profiler faster than the
controller (1 kHz beside a 4 ms controller) on a cell PC short of CPU.

Each profile is estimated in the driver's link thread as it is read (the newest of each read: local_topics.py)
and only the pose goes over DDS at the profile rate; `profile` reaches other subscribers (a recorder,
`ros2 topic echo`) at the driver's `profile_decimation`. Over two processes this saves the 1 kHz PointCloud2
hop (a publish, a wake-up and a take, the largest message of the loop) and one process's DDS threads; the
compensator and the bridge stay processes of their own, so the loop's remaining rate is the controller's.
Both nodes keep their names, parameters, topics and /diagnostics, so config/cell.yaml and the bringup's checks
work unchanged (docs/performance.md has the figures, beside the four-process graph and cell_container).

    profiler_estimator --ros-args --params-file config/cell.yaml
"""
from __future__ import annotations

import sys

from ..core.model.gauge import GaugeError
from .local_topics import LocalTopics
from .pose_estimator import PoseEstimatorNode
from .process_tuning import LOOP_SWITCH_INTERVAL_S
from .profiler_driver import ProfilerDriverNode
from .run import run_nodes

NAME = "profiler_estimator"


def main(args=None) -> int:
    local = LocalTopics(carried=("profile",))
    # The estimator first, so that the driver's first profile finds it; the driver is destroyed first (no more
    # profiles), then the estimator.
    factories = [lambda: PoseEstimatorNode(local=local), lambda: ProfilerDriverNode(local=local)]
    return run_nodes(factories, NAME, args, startup_errors=(ValueError, OSError, GaugeError),
                     destroy_order=lambda nodes: list(reversed(nodes)), switch_interval=LOOP_SWITCH_INTERVAL_S)


if __name__ == "__main__":
    sys.exit(main())
