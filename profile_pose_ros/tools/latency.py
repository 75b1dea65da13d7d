"""profile_pose latency: the loop's latency budget on the simulated cell, stage by stage.

Every message of the chain carries the profile's trigger time as its stamp (profile -> pose ->
correction -> the bridge's `~/increment`), and DDS gives each message's publish time (source timestamp),
so each stage's latency is publish time - trigger time: trigger -> profile published (exposure,
transfer, driver), -> pose published, -> correction published, -> increment sent to the controller
(the bridge publishes `~/increment` right after the TCP send). The loop is closed and holding still.
At 1 kHz the profiler has its own trigger clock beside the 250 Hz controller, as a fast profiler would.

Two observers. `nodes` (the default): each node times its own stage (stamp -> publish, or -> TCP send)
and reports per diagnostics window (core/timing/latency_window.py); this client takes nothing at the loop's
rate, so it measures the graph without loading it. The p99 is then the worst window's, an upper bound
of the run's p99. `dds`: this client subscribes to every stage and takes DDS's publish times, an
outside view that costs the graph about a third of a core at 1 kHz.
"""
from __future__ import annotations

import argparse
import sys
from typing import Callable

import numpy as np

from ..core.estimation.result import REFINE_MODELS
from ..core.timing.latency_window import pooled
from .config_files import CELL_CONTROL_LAW, add_control_law_option
from .experiment import Experiment, add_layout_options, control_hz, layout_from
from .graph import Graph, cpu_percent
from .report import run_dir, summary, table, write_json

STAGES = (("profile", "profile", "sensor_msgs/msg/PointCloud2"),
          ("pose", "pose", "geometry_msgs/msg/PoseStamped"),
          ("correction", "correction", "geometry_msgs/msg/TwistStamped"),
          ("increment sent", "/motoplus_bridge/increment", "geometry_msgs/msg/TwistStamped"))
NODE_STAGES = {"profile": ("profiler_driver", "trigger_to_profile_ms"),  # stage -> who times it, and its key
               "pose": ("pose_estimator", "trigger_to_pose_ms"),
               "correction": ("pd_compensator", "trigger_to_correction_ms"),
               "increment sent": ("motoplus_bridge", "trigger_to_send_ms")}


def subscribe_latency(node, topic: str, msgtype: str, qos, sink: Callable[[float], None]):
    """A raw subscription handing sink() each message's publish time - its stamp (the trigger time), in ms."""
    from ..nodes.bag_common import message_class
    from ..nodes.messages import cdr_stamp_ns

    return node.create_subscription(
        message_class(msgtype), topic,
        lambda data, info: sink((info["source_timestamp"] - cdr_stamp_ns(data)) * 1e-6), qos, raw=True)


class NodeReports:
    """Every diagnostics report of the stages' nodes while `recording` (the nodes observer)."""

    def __init__(self, graph: Graph) -> None:
        self.graph = graph
        self.recording = False
        self.windows: dict[str, list[dict]] = {name: [] for name in NODE_STAGES}
        graph.diagnostics_listeners.append(self._on_report)

    def _on_report(self, status: str, values: dict) -> None:
        if not self.recording:
            return
        for stage, (node, key) in NODE_STAGES.items():
            if self.graph.is_from(status, node) and f"{key}_n" in values:
                self.windows[stage].append(values)

    def summaries(self, clear: bool = False) -> dict[str, dict]:
        """Each stage's windows pooled (p99: the worst window's); clear: start collecting afresh."""
        out = {stage: pooled(self.windows[stage], key) for stage, (_, key) in NODE_STAGES.items()}
        if clear:
            for windows in self.windows.values():
                windows.clear()
        return out


def measure(rate_hz: float, seconds: float, out, refine_model: str, noise: float, skip: tuple[str, ...] = (),
            observer: str = "nodes", composed: bool = False, control_law: str = CELL_CONTROL_LAW,
            estimator_in_driver: bool = False, compensator_in_bridge: bool = False, period_clock: str = "pose") -> dict:
    from rclpy.qos import qos_profile_sensor_data

    controller_hz = control_hz(rate_hz)
    graph = Graph(out / f"logs_{rate_hz:g}hz", client_name="profile_pose_latency")
    latencies: dict[str, list[float]] = {name: [] for name, *_ in STAGES}
    recording = [False]
    reports = NodeReports(graph)
    try:
        exp = Experiment(graph, controller_hz, noise, refine_model=refine_model,
                         profile_rate_hz=rate_hz if abs(rate_hz - controller_hz) > 1 else None, composed=composed,
                         estimator_in_driver=estimator_in_driver, compensator_in_bridge=compensator_in_bridge,
                         compensator={"control_law": control_law, "period_clock": period_clock})
        for name, topic, msgtype in STAGES:
            if name in skip or observer != "dds":
                continue

            def on_latency(ms: float, name=name) -> None:
                if recording[0]:
                    latencies[name].append(ms)
            qos = qos_profile_sensor_data if name == "profile" else 1000
            subscribe_latency(graph.node, topic, msgtype, qos, on_latency)
        exp.close_loop()
        exp.stop_streams()
        exp.wait(1.0)  # the nodes' next reports start windows that hold only the measured time
        cpu_before = graph.cpu_seconds()
        periods_before = answered_periods(exp)
        recording[0] = reports.recording = True
        for _ in range(int(round(seconds / 0.5))):
            exp.reference(np.zeros(3))  # again and again: a reference lost before discovery matched would
            exp.wait(0.5)               # leave the compensator sending zeros
        recording[0] = reports.recording = False
        periods = {k: v - periods_before[k] for k, v in answered_periods(exp).items()}
        periods["controller"] = round(seconds * controller_hz)
        cpu = graph.cpu_seconds()
        cpu_share = cpu_percent(cpu_before, cpu, seconds)
        diagnostics = {k: dict(v) for k, v in exp.diagnostics.items()}
        exp.bridge(arm=False)
    finally:
        graph.close()
    stages = ({name: summary(v) for name, v in latencies.items()} if observer == "dds"
              else reports.summaries())
    return {"rate_hz": rate_hz, "control_hz": controller_hz, "seconds": seconds, "refine_model": refine_model,
            "control_law": control_law,
            "observer": observer, "composed": composed, "stages_ms": stages, "cpu_percent": cpu_share,
            "periods": periods,
            "diagnostics": diagnostics}


def answered_periods(exp: Experiment) -> dict[str, int]:
    """The bridge's armed controller periods so far, and those answered by a correction from a pose at most one
    period old when the increment left (its newest report)."""
    return {"armed": int(exp.value("motoplus_bridge", "armed_periods", "0") or 0),
            "answered": int(exp.value("motoplus_bridge", "answered_within_a_period", "0") or 0)}


def print_table(results: list[dict]) -> None:
    rows = []
    for r in results:
        for name, s in r["stages_ms"].items():
            if s.get("n"):
                rows.append((f"{r['rate_hz']:g} Hz", f"trigger -> {name}", str(s["n"]), f"{s['median']:.3f}",
                             f"{s['p99']:.3f}", f"{s['max']:.3f}"))
            else:
                rows.append((f"{r['rate_hz']:g} Hz", f"trigger -> {name}", "0", "-", "-", "-"))
    observer = results[0]["observer"] if results else "dds"
    print(table(("profile rate", "stage", "messages", "median ms", "p99 ms", "max ms"), rows,
                "latency from the trigger (stamps) to each stage's publish / send time"
                + (" (timed by the nodes: median of the windows' medians, p99 the worst window's)"
                   if observer == "nodes" else " (DDS publish times seen by this client)")))
    for r in results:
        p = r["periods"]
        print(f"controller periods at {r['rate_hz']:g} Hz: {p['controller']}, armed {p['armed']}, answered by a "
              f"correction from a pose at most one period old {p['answered']} "
              f"({100.0 * p['answered'] / max(p['controller'], p['armed'], 1):.1f} %; the counts are the bridge's "
              f"0.5 s reports, the periods the measured time's)")
        print(f"CPU at {r['rate_hz']:g} Hz (% of one core): "
              + ", ".join(f"{name} {value:.0f}" for name, value in r["cpu_percent"].items()))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[83.333, 1000.0], help="profile rates (Hz)")
    parser.add_argument("--seconds", type=float, default=20.0, help="measured time per rate")
    parser.add_argument("--refine-model", default="corners", choices=REFINE_MODELS)
    parser.add_argument("--noise", type=float, default=5e-6)
    parser.add_argument("--observer", default="nodes", choices=["nodes", "dds"],
                        help="nodes: each node's own timing, from its diagnostics (no load from this client); "
                             "dds: this client subscribes to every stage")
    parser.add_argument("--skip", nargs="*", default=[], help="stages not to subscribe to (dds observer)")
    add_layout_options(parser)
    add_control_law_option(parser)
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)
    out = run_dir(args.out, "latency")
    results = []
    for rate in args.rates:
        print(f"measuring at {rate:g} Hz for {args.seconds:g} s, {args.control_law} law (logs in {out})", flush=True)
        results.append(measure(rate, args.seconds, out, args.refine_model, args.noise, tuple(args.skip),
                               args.observer, control_law=args.control_law, period_clock=args.period_clock,
                               **layout_from(args)))
    print_table(results)
    write_json(out / "latency.json", {"results": results})
    print(f"results: {out / 'latency.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
