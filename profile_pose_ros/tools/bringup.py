"""profile_pose_bringup: bring a cell up without launch files: sim_cell (or, with --hardware, nothing: the
real devices) and the four nodes, each its own process, with one parameter file; logs and the exact
commands under runs/<timestamp>/; "ready" only once every node reports and profiles, poses and
corrections flow; Ctrl-C (or SIGTERM) stops them bridge first (it sends STOP), cell last, and leaves no
process behind. Each node is this process's own child: the installed executable the ament index finds
(what `ros2 run` would run, without its wrapper, which would swallow the stop), the venv's console
script otherwise. --namespace puts a second cell beside the first without cross-talk.
--composed runs the four nodes in one cell_container process (nodes/cell_container.py); --pairs in two,
profiler_estimator and compensator_bridge (a profiler faster than the controller: docs/user_guide.md).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from ..nodes.run import StopRequest
from ..resources import config_path
from .graph import Graph, free_ports
from .report import run_dir

DISCOVERY_RANGES = ("LOCALHOST", "SUBNET", "OFF", "SYSTEM_DEFAULT")
NODES = ("profiler_driver", "pose_estimator", "pd_compensator", "motoplus_bridge")
ALIVE_TOPICS = {"profile": "sensor_msgs/msg/PointCloud2", "pose": "geometry_msgs/msg/PoseStamped",
                "correction": "geometry_msgs/msg/TwistStamped"}  # each must carry messages before "ready"


FRAME_PARAMETERS = {"sim_cell": {"gauge_frame": "gauge"}, "profiler_driver": {"frame_id": "profiler"},
                    "pose_estimator": {"profiler_frame": "profiler", "gauge_frame": "gauge"},
                    "pd_compensator": {"gauge_frame": "gauge", "base_frame": "base"},
                    "motoplus_bridge": {"base_frame": "base"}}


def prefixed_frames(prefix: str) -> dict[str, dict[str, str]]:
    """Each node's frame parameters with `prefix` before the standard names (cell2/profiler, cell2/gauge,
    cell2/base), so two cells' poses and TF never share a frame; {} for no prefix."""
    if not prefix:
        return {}
    return {node: {name: prefix + frame for name, frame in frames.items()} for node, frames in FRAME_PARAMETERS.items()}


def discovery_range(requested: str | None, environ: dict) -> str:
    """DDS discovery stays on this machine unless told otherwise (--discovery-range, or
    ROS_AUTOMATIC_DISCOVERY_RANGE already set): nothing on the cell network sees or feeds the graph."""
    value = (requested or environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST").upper()
    if value not in DISCOVERY_RANGES:
        raise ValueError(f"discovery range must be one of {', '.join(DISCOVERY_RANGES)}, not {value!r}")
    return value


class Bringup:
    def __init__(self, out: Path, params_file: Path | list[Path], namespace: str = "", hardware: bool = False,
                 record: bool = False, domain_id: int | None = None, composed: bool = False,
                 frame_prefix: str = "", pairs: bool = False) -> None:
        self.out, self.hardware, self.record, self.composed, self.pairs = out, hardware, record, composed, pairs
        self.frames = prefixed_frames(frame_prefix)
        self.graph = Graph(out, domain_id=domain_id, client_name="bringup", namespace=namespace,
                           params_file=params_file)
        self.seen: dict[str, int] = {topic: 0 for topic in ALIVE_TOPICS}

    def start(self) -> None:
        g = self.graph
        if self.record:  # first: subscribed before the others publish, and closed last
            g.start("bag_recorder", {"output": str(self.out / "bag")})
        driver, bridge = {}, {}
        if not self.hardware:  # ports of its own: several simulated cells side by side
            profiler, mcu, robot = free_ports(3)
            g.start("sim_cell", {"profiler_port": profiler, "mcu_port": mcu, "robot_port": robot,
                                 **self.frames.get("sim_cell", {})})
            driver = {"port": profiler, "serial_url": f"socket://127.0.0.1:{mcu}"}
            bridge = {"port": robot}
        params = {node: {**own, **self.frames.get(node, {})} for node, own in zip(NODES, (driver, {}, {}, bridge))}
        if self.composed:
            g.start_composed(params)
        else:  # the bridge's process last: stopped first (STOP)
            g.start_nodes({n: params[n] for n in NODES[:2]}, "profiler_estimator" if self.pairs else None)
            g.start_nodes({n: params[n] for n in NODES[2:]}, "compensator_bridge" if self.pairs else None)
        self._watch_topics()

    def _watch_topics(self) -> None:
        from rclpy.qos import qos_profile_sensor_data

        from ..nodes.bag_common import message_class

        self._subscriptions = []
        for topic, msgtype in ALIVE_TOPICS.items():
            def count(_data, topic=topic) -> None:
                self.seen[topic] += 1
            qos = qos_profile_sensor_data if topic == "profile" else 10
            self._subscriptions.append(self.graph.node.create_subscription(
                message_class(msgtype), topic, count, qos, raw=True))

    def missing(self) -> list[str]:
        """What is not up yet: nodes without diagnostics, topics without messages, an unconnected bridge."""
        g = self.graph
        nodes = [n for n in NODES + (() if self.hardware else ("sim_cell",)) if not g.reported(n)]
        topics = [f"topic {t}" for t, n in self.seen.items() if n == 0]
        # a node's first report may predate its first message: wait for one that counts them (the status
        # line printed at "ready" reads these rates)
        rates = [f"{n} rate report" for n in ("profiler_driver", "pose_estimator")
                 if g.reported(n) and not float(g.diagnostic(n, "rate_hz", "0") or 0) > 0]
        bridge = g.diagnostic("motoplus_bridge", "state", "")
        # disarmed, the bridge holds no connection (the controller's one slot stays free until ~/start)
        up = bridge in ("disarmed", "connected", "arming", "armed")
        link = [] if up else [f"robot controller link ({bridge or 'no report'})"]
        return nodes + topics + rates + link

    def wait_ready(self, timeout: float) -> float:
        start = time.monotonic()
        if not self.graph.spin_until(lambda: not self.missing(), timeout):
            raise RuntimeError(f"not ready after {timeout:g} s, missing: {', '.join(self.missing())}; "
                               f"logs in {self.out}")
        for subscription in self._subscriptions:  # profiles at 1 kHz are not this process's business
            self.graph.node.destroy_subscription(subscription)
        return time.monotonic() - start

    def status(self) -> str:
        g = self.graph
        return (f"profiler {float(g.diagnostic('profiler_driver', 'rate_hz', '0') or 0):.1f} Hz, "
                f"poses {float(g.diagnostic('pose_estimator', 'rate_hz', '0') or 0):.1f} Hz, "
                f"bridge {g.diagnostic('motoplus_bridge', 'state', '?')}")

    def close(self) -> None:
        self.graph.close()  # reverse start order: bridge (STOP) first, the cell and the recorder last


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hardware", action="store_true", help="no sim_cell: the nodes talk to the real devices")
    parser.add_argument("--params-file", action="append", help="default: config/cell.yaml (simulated), "
                        "config/hardware.yaml; again for more files, each overriding the ones before (e.g. the cell's "
                        "file, then profile_pose_calibrate's calibration.yaml)")
    parser.add_argument("--namespace", default="", help="e.g. cell2: every node and topic under /cell2")
    parser.add_argument("--frame-prefix", default="", help="e.g. cell2/: frames cell2/profiler, cell2/gauge, "
                        "cell2/base (overrides the parameter file's frame names)")
    parser.add_argument("--record", action="store_true", help="also record the cell's topics (bag_recorder)")
    parser.add_argument("--composed", action="store_true", help="the four nodes in one cell_container process")
    parser.add_argument("--pairs", action="store_true", help="the four nodes in two processes: profiler_estimator "
                        "and compensator_bridge (a profiler faster than the controller)")
    parser.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: the environment's, else 0)")
    parser.add_argument("--discovery-range", type=str.upper, choices=DISCOVERY_RANGES,
                        help="ROS_AUTOMATIC_DISCOVERY_RANGE for every node (default: the environment's, else "
                             "LOCALHOST: the graph is invisible to the cell network)")
    parser.add_argument("--ready-timeout", type=float, default=90.0)
    parser.add_argument("--duration", type=float, help="stop by itself after this long (s) once ready")
    parser.add_argument("--out", default="runs")
    args = parser.parse_args(argv)

    params_file = [Path(f) for f in args.params_file] if args.params_file else [config_path(
        "hardware.yaml" if args.hardware else "cell.yaml")]
    domain_id = args.domain_id if args.domain_id is not None else int(os.environ.get("ROS_DOMAIN_ID", "0"))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = discovery = discovery_range(args.discovery_range, os.environ)
    out = run_dir(args.out, f"bringup{'-' + args.namespace.strip('/') if args.namespace else ''}")
    stop = StopRequest().install()
    if args.composed and args.pairs:
        parser.error("--composed and --pairs are two layouts: choose one")
    cell = Bringup(out, params_file, args.namespace, args.hardware, args.record, domain_id, args.composed,
                   args.frame_prefix, args.pairs)
    code = 0
    try:
        cell.start()
        print(f"starting {'the real cell' if args.hardware else 'the simulated cell'} with {', '.join(map(str, params_file))} "
              f"(domain {domain_id}, discovery {discovery}{', namespace /' + args.namespace.strip('/') if args.namespace else ''}); "
              f"logs in {out}", flush=True)
        ready_s = cell.wait_ready(args.ready_timeout)
        print(f"ready in {ready_s:.1f} s: {cell.status()}; Ctrl-C stops the cell", flush=True)
        deadline = time.monotonic() + args.duration if args.duration else float("inf")
        next_status = time.monotonic() + 10.0
        while not stop.is_set() and time.monotonic() < deadline:
            cell.graph.spin_until(stop.is_set, min(1.0, max(0.0, deadline - time.monotonic())))
            if time.monotonic() >= next_status:
                print(cell.status(), flush=True)
                next_status += 10.0
    except RuntimeError as exc:  # a node died or the cell did not come up
        print(f"profile_pose_bringup: {exc}", file=sys.stderr)
        code = 1
    finally:
        print("stopping: bridge first (STOP), the cell last", flush=True)
        cell.close()
    print(f"stopped; logs in {out}" + (f", bag in {out / 'bag'}" if args.record else ""))
    return code


if __name__ == "__main__":
    sys.exit(main())
