"""profile_pose_node_benchmark: the pose_estimator node under load, over real DDS between processes.

For each rate (83.3 Hz, the paper's control rate, and 1 kHz, the profiler's maximum) a fresh
pose_estimator process receives rendered 3200-point profiles from this process for the given duration.
Reported: poses received / profiles sent, latency from the profile's stamp (set just before publishing)
to the pose's arrival here (median, p99, max), the node's CPU share of one core, its resident memory
each second (peak and growth), and the profiles it reported lost or rejected in its diagnostics.
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time

import numpy as np

from ..core import Gauge, render_profile, sample_pose
from ..resources import DEFAULT_GAUGE, config_path
from . import processes
from .node_process import NodeProcess
from .report import run_dir, summary, table, write_json


class LoadRun(NodeProcess):
    """One rate: a node process, a publisher thread at the rate, and a receiver."""

    def __init__(self, gauge: Gauge, rate_hz: float, seconds: float, out_dir, seed: int) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import PointCloud2

        from ..nodes.messages import cloud_from_points

        super().__init__("pose_estimator", "profile_pose_ros.nodes.pose_estimator", ["-p", f"gauge_file:={gauge.source}"],
                         "node_benchmark", 1 + (os.getpid() + int(rate_hz)) % 200,
                         out_dir / f"pose_estimator_{rate_hz:g}Hz.log")
        self.rate_hz, self.seconds = rate_hz, seconds
        rng = np.random.default_rng(seed)
        self.messages = [cloud_from_points(render_profile(gauge, *sample_pose(gauge, rng), noise_std=5e-6, rng=rng),
                                           PointCloud2().header.stamp, "profiler") for _ in range(200)]
        self.publisher = self.node.create_publisher(PointCloud2, "profile", qos_profile_sensor_data)
        self.latencies: list[float] = []
        self.diagnostics: list = []
        self.subscribe_fast(PoseStamped, "pose", self._on_pose, 1000)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 100)
        self.sent = 0
        self.samples: list[dict] = []

    def _on_pose(self, msg) -> None:
        arrival = time.time_ns()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.latencies.append((arrival - stamp) * 1e-9)

    def _publish(self, msg) -> None:
        now = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 1_000_000_000)
        self.publisher.publish(msg)

    def run(self) -> dict:
        if not self.spin_until(lambda: self.publisher.get_subscription_count() > 0, 30.0):
            raise RuntimeError("pose_estimator did not subscribe")
        deadline = time.monotonic() + 30.0
        while not self.latencies and time.monotonic() < deadline:  # warm up until one pose comes back
            self._publish(self.messages[0])
            self.spin_until(lambda: bool(self.latencies), 0.2)
        if not self.latencies:
            raise RuntimeError("pose_estimator never answered")
        self.spin_until(lambda: False, 0.5)
        self.latencies.clear()
        self.diagnostics.clear()
        pid = self.process.pid

        def publish_at_rate() -> None:
            period = 1.0 / self.rate_hz
            start = time.monotonic()
            k = 0
            while k * period < self.seconds:
                target = start + k * period
                delay = target - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                self._publish(self.messages[k % len(self.messages)])
                self.sent += 1
                k += 1

        cpu_start, wall_start = processes.cpu_seconds(pid), time.monotonic()
        publisher = threading.Thread(target=publish_at_rate, daemon=True)
        publisher.start()
        next_sample = wall_start
        while publisher.is_alive():
            self.fast_inputs[0].pump(0.005)  # poses, timestamped as they are taken
            if time.monotonic() >= next_sample:
                self.samples.append({"t": time.monotonic() - wall_start, **processes.memory_kib(pid)})
                self.executor.spin_once(timeout_sec=0.0)  # diagnostics
                next_sample += 1.0
        self.spin_until(lambda: len(self.latencies) >= self.sent, 2.0)  # drain what is in flight
        cpu = processes.cpu_seconds(pid) - cpu_start
        wall = time.monotonic() - wall_start
        self.samples.append({"t": wall, **processes.memory_kib(pid)})
        self.spin_until(lambda: False, 1.2)  # one more diagnostics period
        def reported(key: str) -> list[float]:
            return [float(kv.value) for a in self.diagnostics for s in a.status for kv in s.values if kv.key == key]

        lost = int(max(reported("profiles_lost"), default=0))
        callback_ms = reported("mean_processing_ms")
        rss = [s["VmRSS"] / 1024 for s in self.samples]
        return {"rate_hz": self.rate_hz, "seconds": self.seconds, "sent": self.sent, "received": len(self.latencies),
                "delivered": len(self.latencies) / max(1, self.sent), "latency_ms": summary(np.array(self.latencies) * 1e3),
                "cpu_share": cpu / wall, "peak_rss_mib": max(s["VmHWM"] for s in self.samples) / 1024,
                "rss_first_mib": rss[0], "rss_last_mib": rss[-1], "rss_growth_mib": rss[-1] - rss[0],
                "rss_per_second_mib": rss, "node_reported_lost": lost,
                "node_callback_ms": float(np.median(callback_ms)) if callback_ms else float("nan")}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[83.3, 1000.0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--quick", action="store_true", help="3 s per rate (for tests)")
    parser.add_argument("--gauge", default=str(config_path(DEFAULT_GAUGE)))
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    seconds = 3.0 if args.quick else args.seconds
    gauge = Gauge.from_yaml(args.gauge)
    out = run_dir(args.out, "node-benchmark")
    results, rows = [], []
    for k, rate in enumerate(args.rates):
        print(f"{rate:g} Hz for {seconds:g} s ...", flush=True)
        run = LoadRun(gauge, rate, seconds, out, seed=k)
        try:
            r = run.run()
        finally:
            run.close()
        results.append(r)
        lat = r["latency_ms"]
        rows.append([f"{rate:g} Hz", f"{r['received']}/{r['sent']}", f"{100 * r['delivered']:.2f} %", lat["median"],
                     lat["p99"], lat["max"], f"{100 * r['cpu_share']:.1f} %", r["peak_rss_mib"], r["rss_growth_mib"],
                     str(r["node_reported_lost"]), r["node_callback_ms"]])
    print(table(["rate", "poses/profiles", "delivered", "latency median (ms)", "p99", "max", "node CPU",
                 "peak RSS (MiB)", "RSS growth (MiB)", "lost (node)", "callback (ms)"], rows,
                "pose_estimator under load (separate processes, DDS on this host)"))
    write_json(out / "node_benchmark.json", {"runs": results})
    print(f"results: {out / 'node_benchmark.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
