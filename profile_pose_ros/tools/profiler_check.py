"""profile_pose profiler-check: sim_cell + profiler_driver + pose_estimator, each its own process, checked
against /sim/ground_truth.

The profiler moves (sines on every axis) so that a profile paired with the wrong trigger shows as a pose
error. Reported per rate: profile stamps minus true trigger times (median, max), pose errors against
the truth at the pose's stamp, profiles and poses delivered, and the drops sim_cell made against the
drops the driver counted.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from ..nodes.messages import cdr_stamp_ns, pose_difference, stamp_ns
from .graph import Graph, cpu_percent, free_ports
from .report import nearest_stamp, run_dir, summary, table, write_json

SINES = {"sine_amplitude": [2e-3, 1e-3, 1e-3, 2e-3, 1e-3, 2e-3], "sine_frequency": [0.5, 0.7, 0.3, 0.4, 0.6, 0.2]}
class CheckRun:
    def __init__(self, graph: Graph, rate_hz: float, seconds: float, noise_std: float, drop_fraction: float,
                 seed: int = 0, watch_profiles: bool = False, baudrate: int = 1_000_000,
                 queue_depth: int = 5) -> None:
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import PointCloud2

        self.graph, self.rate_hz = graph, rate_hz
        self.triggers = int(round(rate_hz * seconds))
        profiler_port, mcu_port = free_ports(2)
        graph.start("sim_cell", {"profiler_port": profiler_port, "mcu_port": mcu_port, "trigger_rate": 0.0,
                                 "robot_enabled": False, "mcu_baudrate": baudrate,
                                 "noise_std": noise_std, "drop_fraction": drop_fraction, "seed": seed,
                                 "diagnostics_period": 0.5, **SINES})
        graph.start("profiler_driver", {"port": profiler_port, "serial_url": f"socket://127.0.0.1:{mcu_port}",
                                        "baudrate": baudrate, "diagnostics_period": 0.5})
        graph.start("pose_estimator", {"diagnostics_period": 0.5, "queue_depth": queue_depth})
        self.truth: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.profile_stamps: list[int] = []
        self.poses: list[tuple[int, np.ndarray, np.ndarray]] = []
        node = graph.node
        node.create_subscription(PoseStamped, "sim/ground_truth", self._on_truth, 5000)
        if watch_profiles:  # else the poses' stamps (copied from their profiles) stand for them: less load
            node.create_subscription(PointCloud2, "profile", self._on_profile, qos_profile_sensor_data, raw=True)
        node.create_subscription(PoseStamped, "pose", self._on_pose, 5000)
        self.baseline: dict[str, int] = {}

    def _on_truth(self, msg) -> None:
        self.truth[stamp_ns(msg.header.stamp)] = msg.pose  # converted when compared: keep up at 1 kHz

    def _on_profile(self, raw: bytes) -> None:
        self.profile_stamps.append(cdr_stamp_ns(raw))  # the stamp only: no need to decode 3200 points here

    def _on_pose(self, msg) -> None:
        self.poses.append((stamp_ns(msg.header.stamp), msg.pose))

    @property
    def diagnostics(self) -> dict:
        return self.graph.diagnostics

    def value(self, node: str, key: str, default: str = "0") -> str:
        return self.graph.diagnostic(node, key, default)

    def run(self) -> dict:
        """Start the cell's clock once the driver streams, run `triggers` cycles, then compare."""
        g = self.graph
        if not g.spin_until(lambda: self.value("profiler_driver", "trigger_state", "") == "ok"
                            and self.value("profiler_driver", "state", "") == "streaming", 60.0):
            raise RuntimeError(f"the driver never connected; see {g.log_dir}")
        if not g.spin_until(lambda: self.value("pose_estimator", "gauge", "") != "", 60.0):
            raise RuntimeError("pose_estimator did not come up")
        self._warm_up()
        cpu_start = g.cpu_seconds()
        wall_start = time.monotonic()
        self._start_clock()
        expected = lambda: self.count("sim_cell/triggers") >= self.triggers  # noqa: E731
        g.spin_until(expected, self.triggers / self.rate_hz + 30.0)
        last = lambda: len(self.truth) and self.poses and max(p[0] for p in self.poses[-5:]) >= max(self.truth)  # noqa
        g.spin_until(last, 5.0)
        wall = time.monotonic() - wall_start
        self.cpu_percent = cpu_percent(cpu_start, g.cpu_seconds(), wall)
        g.spin_until(self._counts_settled(), 15.0)  # every node's last diagnostics, however late on a busy PC
        return self._compare()

    def _counts_settled(self, quiet_s: float = 1.2):
        """A condition: true once no count has changed for quiet_s (over two diagnostics periods): on a busy
        PC a node's last diagnostics can come later than any fixed wait."""
        state = {"counts": None, "since": time.monotonic()}

        def settled() -> bool:
            counts = tuple(self.value(*key.split("/"), "") for key in self.COUNTS)
            if counts != state["counts"]:
                state["counts"], state["since"] = counts, time.monotonic()
            return time.monotonic() - state["since"] >= quiet_s
        return settled

    def _warm_up(self, triggers: int = 40, bursts: int = 10) -> None:
        """Bursts of triggers until poses come out (DDS discovery between the nodes is complete), then every
        count starts from here: a profile lost because a subscriber had not matched yet is not a loss."""
        g = self.graph
        for _ in range(bursts):
            fired = int(self.value("sim_cell", "triggers", "0"))
            g.set_parameters("sim_cell", {"trigger_rate": 50.0, "max_triggers": triggers})
            g.spin_until(lambda: int(self.value("sim_cell", "triggers", "0")) >= fired + triggers, 10.0)
            if len(self.poses) >= 3:
                break
        else:
            raise RuntimeError(f"{len(self.poses)} poses during the warm-up; the nodes say: "
                               f"{ {k: v.get('last_error', v.get('state', '')) for k, v in self.diagnostics.items()} }")
        g.spin_until(lambda: False, 1.2)  # the rest of the warm-up, and a diagnostics period
        self.baseline = {k: int(self.value(*k.split("/"))) for k in self.COUNTS}
        self.truth.clear()
        self.poses.clear()
        self.profile_stamps.clear()

    COUNTS = ("sim_cell/triggers", "sim_cell/frames_dropped", "profiler_driver/profiles_dropped",
              "profiler_driver/profiles_published", "profiler_driver/unsynced_profiles",
              "profiler_driver/discarded_while_pairing", "profiler_driver/dropped_late_trigger_line",
              "profiler_driver/dropped_unconfirmed_stamp", "profiler_driver/dropped_out_of_order",
              "profiler_driver/dropped_untimed",
              "pose_estimator/poses_published",
              "pose_estimator/profiles_rejected", "pose_estimator/profiles_lost")

    def count(self, key: str) -> int:
        """A counter from the nodes' diagnostics, since the warm-up."""
        return int(self.value(*key.split("/"))) - self.baseline.get(key, 0)

    def _start_clock(self) -> None:
        self.graph.set_parameters("sim_cell", {"trigger_rate": self.rate_hz, "max_triggers": self.triggers})

    def _compare(self) -> dict:
        truth_stamps = np.array(sorted(self.truth))
        stamps = np.array(self.profile_stamps or [p[0] for p in self.poses], dtype=np.int64)
        idx = np.searchsorted(truth_stamps, stamps)
        lo = truth_stamps[np.clip(idx - 1, 0, len(truth_stamps) - 1)]
        hi = truth_stamps[np.clip(idx, 0, len(truth_stamps) - 1)]
        nearest = np.where(np.abs(stamps - lo) <= np.abs(hi - stamps), lo, hi)
        stamp_error_us = (stamps - nearest) * 1e-3
        np.savez_compressed(self.graph.log_dir / "stamp_errors.npz", profile_stamp_ns=stamps,
                            stamp_error_us=stamp_error_us)
        position, rotation, unmatched = [], [], 0
        for stamp, pose in self.poses:
            best = nearest_stamp(truth_stamps, stamp, int(0.5e9 / self.rate_hz))
            if best is None:
                unmatched += 1
                continue
            position_error, rotation_error = pose_difference(pose, self.truth[best])
            position.append(position_error)
            rotation.append(rotation_error)
        span = (truth_stamps[-1] - truth_stamps[0]) * 1e-9 if len(truth_stamps) > 1 else float("nan")
        return {
            "rate_hz": self.rate_hz, "achieved_rate_hz": (len(truth_stamps) - 1) / span,
            "cpu_percent_of_one_core": self.cpu_percent,
            "triggers": len(self.truth), "profiles": len(stamps), "poses": len(self.poses),
            "stamp_error_us": summary(np.abs(stamp_error_us)), "stamp_bias_us": float(np.median(stamp_error_us)),
            "position_error_um": summary(np.array(position) * 1e6),
            "rotation_error_urad": summary(np.array(rotation) * 1e6), "poses_without_truth": unmatched,
            "sim_frames_dropped": self.count("sim_cell/frames_dropped"),
            "driver_profiles_dropped": self.count("profiler_driver/profiles_dropped"),
            "driver_published": self.count("profiler_driver/profiles_published"),
            "estimator_published": self.count("pose_estimator/poses_published"),
            "driver_unsynced": self.count("profiler_driver/unsynced_profiles"),
            "driver_discarded": self.count("profiler_driver/discarded_while_pairing"),
            "driver_dropped_late_line": self.count("profiler_driver/dropped_late_trigger_line"),
            "driver_dropped_unconfirmed": self.count("profiler_driver/dropped_unconfirmed_stamp"),
            "driver_dropped_out_of_order": self.count("profiler_driver/dropped_out_of_order"),
            "driver_dropped_untimed": self.count("profiler_driver/dropped_untimed"),
            "estimator_rejected": self.count("pose_estimator/profiles_rejected"),
            "estimator_lost": self.count("pose_estimator/profiles_lost"),
            "driver_serial_latency_us": float(self.value("profiler_driver", "serial_latency_us", "nan")),
            "driver_mcu_drift_ppm": float(self.value("profiler_driver", "mcu_clock_drift_ppm", "nan")),
        }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[83.333, 1000.0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--noise", type=float, default=0.0, help="profile depth noise (m); 0 shows exactness")
    parser.add_argument("--drop", type=float, default=0.0, help="fraction of frames sim_cell drops")
    parser.add_argument("--watch-profiles", action="store_true",
                        help="also subscribe to `profile` (else stamps are checked on the poses, which copy them)")
    parser.add_argument("--baudrate", type=int, default=1_000_000, help="the MCU's serial rate (both sides)")
    parser.add_argument("--queue-depth", type=int, default=5, help="pose_estimator's profile queue")
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    out = run_dir(args.out, "profiler-check")
    results, rows = [], []
    for k, rate in enumerate(args.rates):
        print(f"{rate:g} Hz for {args.seconds:g} s ...", flush=True)
        graph = Graph(out / f"{rate:g}Hz", client_name="profiler_check")
        try:
            r = CheckRun(graph, rate, args.seconds, args.noise, args.drop, seed=k, watch_profiles=args.watch_profiles,
                         baudrate=args.baudrate, queue_depth=args.queue_depth).run()
        finally:
            graph.close()
        results.append(r)
        s, p, q = r["stamp_error_us"], r["position_error_um"], r["rotation_error_urad"]
        rows.append([f"{rate:g} Hz", f"{r['profiles']}/{r['triggers']}", f"{r['poses']}", s["median"], s["max"],
                     p["median"], p["max"], q["median"], q["max"],
                     f"{r['sim_frames_dropped']}/{r['driver_profiles_dropped']}", str(r["driver_unsynced"])])
    print(table(["rate", "profiles/triggers", "poses", "|stamp err| median (us)", "max", "position err median (um)",
                 "max", "rotation err median (urad)", "max", "drops sim/driver", "unsynced"], rows,
                f"sim_cell -> profiler_driver -> pose_estimator (noise {args.noise * 1e6:g} um, "
                f"drop {100 * args.drop:g} %)"))
    write_json(out / "profiler_check.json", {"noise_std": args.noise, "drop_fraction": args.drop, "runs": results})
    print(f"results: {out / 'profiler_check.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
