"""Do the driver's stamps follow the trigger? sim_cell and profiler_driver (and pose_estimator) started
afresh many times, each its own process, optionally under CPU load and with the links dropped on a
schedule; every `profile` and `pose` stamp is checked: strictly increasing, and each gap a whole number
of trigger periods within a tolerance.

    python -m profile_pose_ros.tools.stamp_check --starts 100 --load 2
    python -m profile_pose_ros.tools.stamp_check --starts 1 --seconds 75 --fault profiler --every 150
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time

import numpy as np

from ..nodes.messages import cdr_stamp_ns, stamp_ns
from .graph import Graph, free_ports
from .report import run_dir, table, write_json

FAULTS = {  # --fault -> sim_cell's parameter that drops the link every N triggers
    "profiler": "close_after_frames",
    "mcu": "mcu_close_after_triggers",
    "mcu_reboot": "mcu_reboot_after_triggers",
}


def gap_flaws(stamps_ns: list[int], period_s: float, tolerance_s: float) -> dict:
    """Consecutive stamps: how many repeat or go back, and how many gaps are not a whole number of periods
    within tolerance_s (the arrival order is the publish order, so nothing is sorted)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    gaps = np.diff(stamps) * 1e-9
    periods = np.round(gaps / period_s)
    off = np.abs(gaps - periods * period_s)
    bad = (gaps > 0) & (off > tolerance_s)
    return {"stamps": int(stamps.size), "repeated": int(np.sum(gaps == 0)), "decreasing": int(np.sum(gaps < 0)),
            "not_whole_periods": int(np.sum(bad)), "worst_off_ms": float(off[gaps > 0].max() * 1e3) if np.any(gaps > 0)
            else 0.0, "bad_gaps_ms": [round(float(g) * 1e3, 3) for g in gaps[bad | (gaps <= 0)][:10]]}


def busy_processes(count: int) -> list[subprocess.Popen]:
    """`count` processes that spin a core each: the machine busy, as a PC running other work is."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]


def one_start(log_dir, seconds: float, estimator: bool, cell_params: dict, driver_params: dict,
              at_least: int = 0) -> dict:
    """Start the cell and the driver (and the estimator), record `seconds` of stamps after the first profile,
    and on until each topic has `at_least` stamps (for at most 30 s more): a loaded machine's clock map may
    vouch for few stamps at first, and a check of few stamps checks little."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    graph = Graph(log_dir, client_name="stamp_check")
    profiles: list[int] = []
    poses: list[int] = []
    try:
        profiler_port, mcu_port, robot_port = free_ports(3)
        graph.start("sim_cell", {"profiler_port": profiler_port, "mcu_port": mcu_port, "robot_port": robot_port,
                                 "diagnostics_period": 0.5, **cell_params})
        graph.start("profiler_driver", {"port": profiler_port, "serial_url": f"socket://127.0.0.1:{mcu_port}",
                                        "diagnostics_period": 0.5, **driver_params})
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT)
        graph.node.create_subscription(PointCloud2, "profile", lambda raw: profiles.append(cdr_stamp_ns(raw)), qos,
                                       raw=True)
        if estimator:
            graph.start("pose_estimator", {"diagnostics_period": 0.5, "queue_depth": 100})
            graph.node.create_subscription(PoseStamped, "pose", lambda m: poses.append(stamp_ns(m.header.stamp)),
                                           5000)
        if not graph.spin_until(lambda: profiles, 60.0):
            raise RuntimeError(f"no profile within 60 s; see {log_dir}")
        first = time.monotonic()
        graph.spin_until(lambda: time.monotonic() - first >= seconds and len(profiles) >= at_least and (
            not estimator or len(poses) >= at_least), seconds + 30.0)
        # the counts below witness the stamps recorded: read them from diagnostics sent after the last one (every
        # 0.5 s), or a trigger step in the last half second shows in the stamps and not yet in its witness
        ended = time.monotonic()
        graph.spin_until(lambda: all(graph.reported_at(node) > ended for node in ("sim_cell", "profiler_driver")),
                         5.0)
        driver = {key: graph.diagnostic("profiler_driver", key, "?") for key in
                  ("pairings", "connections", "trigger_port_reopens", "unsynced_profiles", "discarded_while_pairing",
                   "dropped_late_trigger_line", "dropped_unconfirmed_stamp")}
        cell = {key: graph.diagnostic("sim_cell", key, "?") for key in
                ("profiler_closes", "mcu_closes", "mcu_reboots", "late_signals", "robot_clock_overruns",
                 "robot_trigger_steps")}
    finally:
        graph.close()
    return {"profiles": profiles, "poses": poses, "driver": driver, "cell": cell}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--starts", type=int, default=12, help="fresh starts of sim_cell and the driver")
    parser.add_argument("--seconds", type=float, default=6.0, help="recorded after each start's first profile")
    parser.add_argument("--load", type=int, default=2, help="CPU-spinning processes beside the graph")
    parser.add_argument("--no-estimator", action="store_true", help="check `profile` only")
    parser.add_argument("--fault", choices=sorted(FAULTS), help="drop this link every --every triggers")
    parser.add_argument("--every", type=int, default=150, help="triggers between two drops of the link")
    parser.add_argument("--period", type=float, default=0.012, help="the trigger period (s): sim_cell's "
                        "control_period")
    parser.add_argument("--tolerance-ms", type=float, default=0.2, help="allowed distance of a gap from a whole "
                        "number of periods")
    parser.add_argument("--max-stamp-error", type=float, help="the driver's max_stamp_error (s; default: its own)")
    parser.add_argument("--out", default="runs", help="where the run's directory goes")
    args = parser.parse_args(argv)
    out = run_dir(args.out, "stamp-check")
    cell_params = {"control_period": args.period}
    if args.fault:
        cell_params[FAULTS[args.fault]] = args.every
    load = busy_processes(args.load)
    results, rows = [], []
    try:
        for start in range(args.starts):
            driver_params = {} if args.max_stamp_error is None else {"max_stamp_error": args.max_stamp_error}
            run = one_start(out / f"start{start:03d}", args.seconds, not args.no_estimator, cell_params, driver_params)
            checks = {topic: gap_flaws(run[topic], args.period, args.tolerance_ms * 1e-3)
                      for topic in ("profiles", "poses") if run[topic]}
            results.append({"start": start, "checks": checks, "driver": run["driver"], "cell": run["cell"]})
            flaws = {topic: c["repeated"] + c["decreasing"] + c["not_whole_periods"] for topic, c in checks.items()}
            rows.append([str(start), *(f"{checks[t]['stamps']} / {flaws[t]}" if t in checks else "-"
                                       for t in ("profiles", "poses")),
                         f"{max(c['worst_off_ms'] for c in checks.values()):.3f}",
                         run["driver"]["pairings"], run["driver"]["unsynced_profiles"],
                         run["driver"]["dropped_unconfirmed_stamp"],
                         " ".join(f"{k}={v}" for k, v in run["cell"].items() if v not in ("0", "?"))])
            print(table(["start", "profiles / flaws", "poses / flaws", "worst off (ms)", "pairings", "untimed",
                         "unconfirmed", "cell"], rows[-1:]), flush=True)
    finally:
        for process in load:
            process.kill()
            process.wait()
    totals = {topic: {key: sum(r["checks"][topic][key] for r in results if topic in r["checks"])
                      for key in ("stamps", "repeated", "decreasing", "not_whole_periods")}
              for topic in ("profiles", "poses")}
    print(table(["start", "profiles / flaws", "poses / flaws", "worst off (ms)", "pairings", "untimed",
                 "unconfirmed", "cell"], rows, title=f"\n{args.starts} starts, load {args.load}, fault "
                 f"{args.fault or 'none'}"))
    for topic, total in totals.items():
        print(f"{topic}: {total['stamps']} stamps, {total['repeated']} repeated, {total['decreasing']} decreasing, "
              f"{total['not_whole_periods']} gaps not a whole number of periods (±{args.tolerance_ms} ms)")
    write_json(out / "stamp_check.json", {"args": vars(args), "totals": totals, "starts": results})
    print(f"written: {out / 'stamp_check.json'}")
    return 0 if all(t["repeated"] + t["decreasing"] + t["not_whole_periods"] == 0 for t in totals.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
