"""How a node process is tuned, all in one place: the GIL's switch interval, the start-up heap frozen out of
the collector's way, a watchdog on shutdown, and real-time scheduling asked for by parameter.

Real-time scheduling: on a 2-core cell PC the profile → pose → correction → increment chain shares the
cores with everything else; under the normal scheduler a profile that arrives while another process runs
waits for its time slice, which is what the loop's p99 latency is made of. With `realtime_priority` > 0 every thread of
the node's process (the spin loop, the DDS receive threads, the bridge's socket thread) runs SCHED_FIFO
at that priority, so a message that arrives preempts ordinary work at once. The threads block in waits
between messages, and the kernel's RT throttling (sched_rt_runtime_us) keeps 5 % of each core for the
rest even if one did not. It needs CAP_SYS_NICE or an rtprio limit (e.g. `@robot - rtprio 60` in
/etc/security/limits.conf); refused, the node runs on under the normal scheduler and says so.
"""
from __future__ import annotations

import faulthandler
import gc
import os
import sys
from contextlib import contextmanager

from .parameters import Param

# CPython hands the GIL over every 5 ms by default. A node process has threads with deadlines beside its
# spin loop (the bridge's socket thread answering each STATE, the driver's serial thread stamping trigger
# lines), and a thread woken by its socket would wait up to that long: 1 ms keeps them prompt.
LOOP_SWITCH_INTERVAL_S = 1e-3
# sim_cell's device threads must meet a 1 kHz profiler's deadlines while its clock thread renders.
SIM_SWITCH_INTERVAL_S = 2e-4
SHUTDOWN_GRACE_S = 10.0  # from the stop request to the process gone, whatever hangs


def shorten_switch_interval(seconds: float) -> None:
    """At most `seconds` between GIL hand-overs (never longer than what the process already has)."""
    sys.setswitchinterval(min(sys.getswitchinterval(), seconds))


def freeze_startup_heap() -> None:
    """What start-up built (modules, compiled kernels, rclpy's types: ~10^5 objects) lives as long as the
    process; frozen, the collector never walks it again (a full collection over it lasts tens of profiles
    at 1 kHz); what the node allocates from now on is collected as usual."""
    gc.collect()
    gc.freeze()


@contextmanager
def exit_if_shutdown_hangs():
    """rcl's node teardown has been seen to spin for minutes at 100 % CPU holding the GIL (all five nodes
    stopping at once after their bringup was killed). faulthandler's watchdog is a C thread: past the grace
    it prints where the process hung (to the log) and exits, so no node outlives its cell; destroy_node()
    has done what matters by then (the bridge's STOP, the bag closed)."""
    faulthandler.dump_traceback_later(SHUTDOWN_GRACE_S, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()

REALTIME_PARAMETERS = [
    Param("realtime_priority", 0, "SCHED_FIFO priority (1-98) for every thread of this node's process once it is "
          "up; 0: the normal scheduler. Needs CAP_SYS_NICE or an rtprio limit; if refused the node runs on and "
          "its diagnostics say so (docs/performance.md).", 0, 98, read_only=True),
]


def set_realtime(priority: int) -> str:
    """Every current thread of this process to SCHED_FIFO `priority` (threads started later by them
    inherit it); a description of the outcome for the log and the diagnostics."""
    if priority <= 0:
        return "normal scheduler"
    threads = sorted(int(tid) for tid in os.listdir("/proc/self/task"))
    try:
        for tid in threads:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:  # EPERM without CAP_SYS_NICE or an rtprio limit
        for tid in threads:  # all or none: half the threads real-time would only reorder the waits
            try:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            except OSError:
                pass
        return f"normal scheduler: SCHED_FIFO {priority} refused ({exc.strerror}; needs CAP_SYS_NICE or an rtprio limit)"
    return f"SCHED_FIFO {priority} on {len(threads)} threads"


def realtime_from_parameters(nodes: list) -> str | None:
    """Apply the `realtime_priority` of the process's nodes (composed, the highest asked: it applies to
    every thread); the outcome, or None if no node declares it."""
    asked = [int(node.get_parameter("realtime_priority").value)
             for node in nodes if node.has_parameter("realtime_priority")]
    return set_realtime(max(asked)) if asked else None
