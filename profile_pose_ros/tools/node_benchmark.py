"""profile_pose node-benchmark: the pose_estimator node under load, over real DDS between processes.

For each rate (83.3 Hz, the paper's control rate, and 1 kHz, the profiler's maximum) a fresh
pose_estimator process receives rendered 3200-point profiles from this process for the given duration.
Reported: poses received / profiles sent, latency from the profile's stamp (set just before publishing)
to the pose's arrival here (median, p99, max), the node's CPU share of one core, its resident memory
each second (peak and growth), and the profiles it reported lost or rejected in its diagnostics.

Beside each rate's run, the same load goes into a null node first (tools/null_node.py: the estimator's
way in and out, no estimation), so the table shows what this machine's rclpy, DDS and scheduling cost
any node, measured in the same minutes as the estimator (`--rounds N` alternates them N times, for a
machine whose speed drifts); `--no-baseline` leaves it out. The last column is the estimator's own
stamp-to-publish p99 per diagnostics window (quietest / median / worst): what the node gives in the
machine's quiet seconds and in its worst, without the DDS hops on either side.

Arrival is timed twice: when DDS delivered the pose into this process (the reader's reception time,
stamped by DDS's receive thread: the node's latency, what any subscriber could have) and when this
client's Python thread took it (that plus this client's own wake-up on a loaded machine).
"""
from __future__ import annotations

import argparse
import os
import sys
import subprocess
import time

import numpy as np

from ..core import Gauge, render_profile, sample_pose
from ..core.timing.sequence_gaps import SequenceGaps
from ..resources import DEFAULT_GAUGE, config_path
from . import processes
from .node_process import NodeProcess
from .report import run_dir, summary, table, write_json


def rendered_profiles(gauge: Gauge, seed: int, count: int) -> list:
    from sensor_msgs.msg import PointCloud2

    from ..nodes.messages import cloud_from_points

    rng = np.random.default_rng(seed)
    return [cloud_from_points(render_profile(gauge, *sample_pose(gauge, rng), noise_std=5e-6, rng=rng),
                              PointCloud2().header.stamp, "profiler") for _ in range(count)]


def publish_stamped(publisher, msg) -> None:
    """Stamp with the time of publishing (the latency's start) and publish."""
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(time.time_ns(), 1_000_000_000)
    publisher.publish(msg)


def publisher_main(domain_id: int, rate_hz: float, seconds: float, seed: int, gauge_file: str) -> int:
    """The load process: renders profiles, says "ready", publishes at the rate after "go", prints the count."""
    import rclpy
    from rclpy.context import Context
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    messages = rendered_profiles(Gauge.from_yaml(gauge_file), seed, 200)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node("node_benchmark_load", context=context)
    publisher = node.create_publisher(PointCloud2, "profile", qos_profile_sensor_data)
    deadline = time.monotonic() + 30.0
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)  # discovery only; nothing is measured yet
    for k in range(20):  # until the subscriber has matched this writer too (best effort drops before)
        publish_stamped(publisher, messages[k])
        time.sleep(0.02)
    print("ready", flush=True)
    sys.stdin.readline()
    period = 1.0 / rate_hz
    start = time.monotonic()
    sent = 0
    while sent * period < seconds:
        delay = start + sent * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        publish_stamped(publisher, messages[sent % len(messages)])
        sent += 1
    time.sleep(0.5)  # let the last best-effort samples leave before the writer is destroyed
    node.destroy_node()
    rclpy.shutdown(context=context)
    print(f"sent {sent}", flush=True)
    return 0


NODES = {  # the node under load: (label, console script or None, module)
    "pose_estimator": ("pose_estimator", "pose_estimator", "profile_pose_ros.nodes.pose_estimator"),
    "null": ("null node (floor)", None, "profile_pose_ros.tools.null_node"),
}


class LoadRun(NodeProcess):
    """One rate: a node process, a publisher thread at the rate, and a receiver."""

    def __init__(self, gauge: Gauge, rate_hz: float, seconds: float, out_dir, seed: int,
                 node_params: tuple[str, ...] = (), node: str = "pose_estimator") -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import PointCloud2

        _, executable, module = NODES[node]
        params = ["-p", f"gauge_file:={gauge.source}", *(a for p in node_params for a in ("-p", p))]
        super().__init__(executable, module, params if node == "pose_estimator" else [],
                         "node_benchmark", 1 + (os.getpid() + int(rate_hz)) % 200,
                         out_dir / f"{node}_{rate_hz:g}Hz.log")
        self.node_kind = node
        self.rate_hz, self.seconds, self.seed, self.gauge_file = rate_hz, seconds, seed, gauge.source
        self.messages = rendered_profiles(gauge, seed, 5)  # for the warm-up
        self.publisher = self.node.create_publisher(PointCloud2, "profile", qos_profile_sensor_data)
        self.latencies: list[float] = []  # to DDS's delivery here
        self.taken_latencies: list[float] = []  # to this thread taking it
        self.pose_gaps = SequenceGaps()  # poses the node published that never reached this client
        self.diagnostics: list = []
        self.subscribe_fast(PoseStamped, "pose", self._on_pose, 1000, with_info=True)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 100)
        self.sent = 0
        self.samples: list[dict] = []

    def _on_pose(self, msg, info: dict) -> None:
        taken = time.time_ns()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.latencies.append((info["received_timestamp"] - stamp) * 1e-9)
        self.pose_gaps.update(info.get("publication_sequence_number"))
        self.taken_latencies.append((taken - stamp) * 1e-9)

    def _publish(self, msg) -> None:
        publish_stamped(self.publisher, msg)

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

        # The load comes from its own process, as a profiler driver's would: a publisher thread in this
        # process would hold the GIL while serialising profiles and delay the poses being timed here.
        load = subprocess.Popen([sys.executable, "-m", __spec__.name, "--publisher", str(self.domain_id),
                                 str(self.rate_hz), str(self.seconds), str(self.seed), self.gauge_file],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                env=dict(os.environ, ROS_DOMAIN_ID=str(self.domain_id)))
        if load.stdout.readline().strip() != "ready":
            raise RuntimeError("the load publisher did not start")
        self.spin_until(lambda: False, 0.5)  # discard the load process's warm-up poses
        self.latencies.clear()
        self.taken_latencies.clear()
        self.pose_gaps = SequenceGaps()
        cpu_start, wall_start = processes.cpu_seconds(pid), time.monotonic()
        load.stdin.write("go\n")
        load.stdin.flush()
        next_sample = wall_start
        while load.poll() is None:
            self.direct_inputs[0].pump(0.005)  # poses, timestamped as they are taken
            if time.monotonic() >= next_sample:
                self.samples.append({"t": time.monotonic() - wall_start, **processes.memory_kib(pid)})
                self.executor.spin_once(timeout_sec=0.0)  # diagnostics
                next_sample += 1.0
        self.sent = int(load.stdout.read().split()[-1])
        self.spin_until(lambda: len(self.latencies) >= self.sent, 2.0)  # drain what is in flight
        cpu = processes.cpu_seconds(pid) - cpu_start
        wall = time.monotonic() - wall_start
        self.samples.append({"t": wall, **processes.memory_kib(pid)})
        self.spin_until(lambda: False, 1.2)  # one more diagnostics period
        # one dict per diagnostics window of the node (the null node publishes none)
        windows = [{kv.key: kv.value for kv in s.values} for a in self.diagnostics for s in a.status]

        def reported(key: str) -> list[float]:
            return [float(w[key]) for w in windows if key in w]

        # The node's own stamp -> publish p99 per window (pose_estimator's trigger_to_pose), over the windows
        # that saw at least half the usual count (not the run's first and last): what the node gives in the
        # machine's quiet seconds and in its worst.
        counted = [(float(w["trigger_to_pose_ms_n"]), float(w["trigger_to_pose_ms_p99"]))
                   for w in windows if "trigger_to_pose_ms_p99" in w]
        usual = median_or_nan([n for n, _ in counted])
        own_p99 = [p99 for n, p99 in counted if n >= 0.5 * usual]
        lost = int(max(reported("profiles_lost"), default=0))
        rss = [s["VmRSS"] / 1024 for s in self.samples]
        return {"node": self.node_kind, "rate_hz": self.rate_hz, "seconds": self.seconds, "sent": self.sent,
                "received": len(self.latencies),
                "delivered": len(self.latencies) / max(1, self.sent),
                "latency_ms": summary(np.array(self.latencies) * 1e3),
                "latency_taken_ms": summary(np.array(self.taken_latencies) * 1e3),
                "cpu_share": cpu / wall, "peak_rss_mib": max(s["VmHWM"] for s in self.samples) / 1024,
                "rss_first_mib": rss[0], "rss_last_mib": rss[-1], "rss_growth_mib": rss[-1] - rss[0],
                "rss_per_second_mib": rss, "node_reported_lost": lost,
                "poses_lost_to_client": self.pose_gaps.missed,
                "node_callback_ms": median_or_nan(reported("mean_processing_ms")),
                "node_callback_cpu_ms": median_or_nan(reported("mean_processing_cpu_ms")),
                "node_window_p99_ms": own_p99}


def median_or_nan(values: list[float]) -> float:
    """The median of what was reported (NaNs left out), NaN if nothing was."""
    values = [v for v in values if not np.isnan(v)]
    return float(np.median(values)) if values else float("nan")


def pooled(parts: list[tuple[dict, list[float], list[float]]]) -> dict:
    """One node's rounds at one rate as one run: latencies pooled, counts summed, memory at its worst."""
    results = [result for result, _, _ in parts]
    sent, received = sum(r["sent"] for r in results), sum(r["received"] for r in results)
    return {"node": results[0]["node"], "rate_hz": results[0]["rate_hz"],
            "seconds": sum(r["seconds"] for r in results), "sent": sent, "received": received,
            "delivered": received / max(1, sent),
            "latency_ms": summary(np.concatenate([lat for _, lat, _ in parts]) * 1e3),
            "latency_taken_ms": summary(np.concatenate([taken for _, _, taken in parts]) * 1e3),
            "cpu_share": float(np.mean([r["cpu_share"] for r in results])),
            "peak_rss_mib": max(r["peak_rss_mib"] for r in results),
            "rss_growth_mib": max(r["rss_growth_mib"] for r in results),
            "node_reported_lost": sum(r["node_reported_lost"] for r in results),
            "poses_lost_to_client": sum(r["poses_lost_to_client"] for r in results),
            "node_callback_ms": median_or_nan([r["node_callback_ms"] for r in results]),
            "node_callback_cpu_ms": median_or_nan([r["node_callback_cpu_ms"] for r in results]),
            "node_window_p99_ms": [p99 for r in results for p99 in r["node_window_p99_ms"]],
            "rounds": results}


def window_p99s(values: list[float]) -> str:
    """quietest / median / worst of the node's per-window p99s, or a dash (the null node reports none)."""
    if not values:
        return "—"
    return f"{min(values):.2f} / {float(np.median(values)):.2f} / {max(values):.2f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[83.3, 1000.0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--quick", action="store_true", help="3 s per rate (for tests)")
    parser.add_argument("--gauge", default=str(config_path(DEFAULT_GAUGE)))
    parser.add_argument("--out", default="runs")
    parser.add_argument("--no-baseline", dest="baseline", action="store_false",
                        help="skip the null node runs beside the estimator's")
    parser.add_argument("--rounds", type=int, default=1,
                        help="split each rate's time into this many alternating null/estimator runs, pooled "
                             "(1: one run of the whole time each, which also shows memory over the whole time)")
    parser.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="a pose_estimator parameter (repeatable), e.g. queue_depth:=20")
    parser.add_argument("--publisher", nargs=5, metavar=("DOMAIN", "RATE", "SECONDS", "SEED", "GAUGE"),
                        help=argparse.SUPPRESS)  # internal: the load process
    args = parser.parse_args(argv)
    if args.publisher:
        domain, rate, secs, seed, gauge_file = args.publisher
        return publisher_main(int(domain), float(rate), float(secs), int(seed), gauge_file)
    seconds = 3.0 if args.quick else args.seconds
    gauge = Gauge.from_yaml(args.gauge)
    out = run_dir(args.out, "node-benchmark")
    results, rows, notes = [], [], []
    nodes = ["null", "pose_estimator"] if args.baseline else ["pose_estimator"]
    rounds = 1 if args.quick else args.rounds
    for k, rate in enumerate(args.rates):
        parts: dict[str, list] = {node: [] for node in nodes}
        for round_index in range(rounds):
            # Alternate which node goes first, so a slow spell of the machine falls on both alike.
            for node in (nodes if round_index % 2 == 0 else nodes[::-1]):
                print(f"{rate:g} Hz, {NODES[node][0]}, round {round_index + 1}/{rounds}: {seconds / rounds:g} s ...",
                      flush=True)
                run = LoadRun(gauge, rate, seconds / rounds, out, seed=k, node_params=tuple(args.param), node=node)
                try:
                    parts[node].append((run.run(), run.latencies, run.taken_latencies))
                finally:
                    run.close()
        by_node = {node: pooled(parts[node]) for node in nodes}
        for node, r in by_node.items():
            results.append(r)
            lat = r["latency_ms"]
            rows.append([f"{rate:g} Hz", NODES[node][0], f"{r['received']}/{r['sent']}",
                         f"{100 * r['delivered']:.2f} %", lat["median"], lat["p99"], lat["max"],
                         r["latency_taken_ms"]["p99"], f"{100 * r['cpu_share']:.1f} %", r["peak_rss_mib"],
                         r["rss_growth_mib"], str(r["node_reported_lost"]), str(r["poses_lost_to_client"]),
                         # the null node reports no callback time
                         "—" if np.isnan(r["node_callback_ms"]) else r["node_callback_ms"],
                         window_p99s(r["node_window_p99_ms"])])
        if len(by_node) == 2:
            floor, ours = by_node["null"]["latency_ms"], by_node["pose_estimator"]["latency_ms"]
            notes.append(f"{rate:g} Hz: the estimator adds {ours['median'] - floor['median']:+.3f} ms to the floor's "
                         f"median latency and {ours['p99'] - floor['p99']:+.3f} ms to its p99 "
                         f"({rounds} alternating round{'s' if rounds > 1 else ''} each)")
    print(table(["rate", "node", "poses/profiles", "delivered", "latency median (ms)", "p99", "max", "p99 taken",
                 "node CPU", "peak RSS (MiB)", "RSS growth (MiB)", "lost before node", "lost after", "callback (ms)",
                 "own p99 per window (ms)"], rows, "pose_estimator under load (separate processes, DDS on this host)"))
    for note in notes:
        print(note)
    write_json(out / "node_benchmark.json", {"runs": results})
    print(f"results: {out / 'node_benchmark.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
