"""profile_pose_bringup as a user runs it: two namespaced simulated cells side by side without cross-talk,
Ctrl-C stopping each cleanly with no process left, and a node that cannot start reported."""
from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

from conftest import ROOT
from profile_pose_ros.tools import processes

SUFFIX = f"_{os.getpid()}"  # names of this run only: a leftover of another run cannot confuse the checks
CELLS = ("cell_a" + SUFFIX, "cell_b" + SUFFIX)


def bringup(domain_id: int, out: Path, *args: str) -> subprocess.Popen:
    command = processes.executable("profile_pose_bringup", "profile_pose_ros.tools.bringup") + [
        "--domain-id", str(domain_id), "--out", str(out), *args]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def node_processes(marker: str) -> list[int]:
    """Processes whose command line mentions `marker` (e.g. the namespace remap)."""
    found = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                if marker in (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                    found.append(int(proc.name))
            except OSError:
                pass
    return found


def stamp(msg) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


def test_two_namespaced_cells_side_by_side_without_cross_talk(ros, tmp_path) -> None:
    """The second cell runs its four nodes composed (cell_container): the same names, topics and
    diagnostics, and its in-process hand-over keeps to its own namespace too."""
    cells = {ns: bringup(ros.domain_id, tmp_path / ns, "--namespace", ns, *(["--composed"] if ns == CELLS[1] else []))
             for ns in CELLS}
    try:
        client = ros.node("cross_talk_check")
        profiles = {ns: set() for ns in CELLS}
        poses = {ns: [] for ns in CELLS}
        counters: dict[str, int] = {}  # "<ns>/<node>/<key>" -> newest value from /diagnostics
        for ns in CELLS:
            client.create_subscription(PointCloud2, f"/{ns}/profile", lambda m, ns=ns: profiles[ns].add(stamp(m)),
                                       qos_profile_sensor_data)
            client.create_subscription(PoseStamped, f"/{ns}/pose", lambda m, ns=ns: poses[ns].append(stamp(m)), 1000)

        def on_diagnostics(msg) -> None:
            for status in msg.status:
                node = status.name.split(":")[0]
                for kv in status.values:
                    if kv.key in ("profiles_published", "profiles_received"):
                        counters[f"{node}/{kv.key}"] = int(kv.value)
        client.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 100)
        published = lambda ns: counters.get(f"{ns}/profiler_driver/profiles_published", 0)  # noqa: E731
        assert ros.spin_until(lambda: all(len(poses[ns]) >= 200 and published(ns) >= 300
                                          and f"{ns}/pose_estimator/profiles_received" in counters for ns in CELLS),
                              180.0), {ns: (len(profiles[ns]), len(poses[ns]), p.poll()) for ns, p in cells.items()}
        for ns, other in (CELLS, CELLS[::-1]):
            assert len(set(poses[ns]) & profiles[ns]) > 100  # poses of this cell's profiles ...
            assert not set(poses[ns]) & profiles[other]  # ... and of none of the other cell's
            # each estimator takes only its own driver's profiles (cross-talk would double what it receives)
            assert counters[f"{ns}/pose_estimator/profiles_received"] <= published(ns) + 100, counters
        # Ctrl-C: each bringup stops its nodes and exits cleanly; nothing of it is left running
        for ns, process in cells.items():
            process.send_signal(signal.SIGINT)
        for ns, process in cells.items():
            output = process.communicate(timeout=60)[0]
            assert process.returncode == 0, output
            assert "ready in" in output and "stopped" in output
            left = node_processes(f"__ns:=/{ns}")
            assert left == [], (output, [Path(f"/proc/{pid}/cmdline").read_bytes()[:300] for pid in left])
    finally:
        for process in cells.values():
            if process.poll() is None:
                process.kill()  # its nodes get SIGTERM from the kernel (processes.start)
                process.wait()


def test_a_node_that_cannot_start_is_reported_and_everything_stops(ros, tmp_path) -> None:
    """The cell's file, then one that overrides it (as a calibration's file is given after the cell's)."""
    params = tmp_path / "bad.yaml"
    params.write_text("/**/pose_estimator:\n  ros__parameters:\n    gauge_file: /no/such/gauge.yaml\n")
    process = bringup(ros.domain_id, tmp_path, "--params-file", str(ROOT / "config" / "cell.yaml"),
                      "--params-file", str(params), "--namespace", "broken_cell" + SUFFIX)
    output = process.communicate(timeout=120)[0]
    assert process.returncode == 1, output
    assert "pose_estimator exited" in output
    assert node_processes("__ns:=/broken_cell" + SUFFIX) == []


def test_a_killed_bringup_leaves_no_node_behind(ros, tmp_path) -> None:
    ns = "killed_cell" + SUFFIX
    process = bringup(ros.domain_id, tmp_path, "--namespace", ns)
    client = ros.node("killed_cell_watch")
    poses = []
    client.create_subscription(PoseStamped, f"/{ns}/pose", poses.append, 100)
    assert ros.spin_until(lambda: poses, 120.0)
    assert len(node_processes(f"__ns:=/{ns}")) == 5
    process.kill()
    process.wait()
    assert ros.spin_until(lambda: not node_processes(f"__ns:=/{ns}"), 30.0), [
        (Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[:2], Path(f"/proc/{pid}/status").read_text()[:200])
        for pid in node_processes(f"__ns:=/{ns}")]


HANGING_NODE = """
import sys, time
from rclpy.node import Node
from profile_pose_ros.nodes import process_tuning, run

class Hangs(Node):
    def __init__(self):
        super().__init__("hangs")
        print("up", flush=True)

    def destroy_node(self):
        while True:  # a teardown that never returns
            time.sleep(0.01)

process_tuning.SHUTDOWN_GRACE_S = 1.0
sys.exit(run.run_node(Hangs, "hangs"))
"""


def test_a_node_whose_teardown_hangs_is_gone_after_the_grace() -> None:
    import sys

    from profile_pose_ros.tools.processes import fresh_domain_id

    process = subprocess.Popen([sys.executable, "-c", HANGING_NODE], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=dict(os.environ, ROS_DOMAIN_ID=str(fresh_domain_id())))
    try:
        assert process.stdout.readline().strip() == "up"
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=30.0)
    finally:
        process.kill()
    assert process.returncode != 0 and "destroy_node" in stderr, stderr  # where it hung, in its log


def test_a_namespace_and_a_frame_prefix_keep_cells_apart(ros) -> None:
    """sim_cell's topics are relative like every other (a namespace separates them), and --frame-prefix gives
    every node's frames one prefix that must agree across the nodes."""
    from rclpy.parameter import Parameter

    from profile_pose_ros.nodes import motoplus_bridge, pd_compensator, pose_estimator, profiler_driver
    from profile_pose_ros.nodes import sim_cell
    from profile_pose_ros.tools.bringup import FRAME_PARAMETERS, prefixed_frames

    sim = ros.add(sim_cell.SimCellNode(context=ros.context, namespace="cell_x", parameter_overrides=[
        Parameter(name, value=0) for name in ("profiler_port", "mcu_port", "robot_port")]))
    assert {sim.truth_pub.topic_name, sim.applied_pub.topic_name} == {"/cell_x/sim/ground_truth",
                                                                       "/cell_x/sim/robot_increment"}
    frames = prefixed_frames("cell_x/")
    assert frames["profiler_driver"]["frame_id"] == frames["pose_estimator"]["profiler_frame"] == "cell_x/profiler"
    assert frames["pose_estimator"]["gauge_frame"] == frames["pd_compensator"]["gauge_frame"] == "cell_x/gauge"
    assert frames["pd_compensator"]["base_frame"] == frames["motoplus_bridge"]["base_frame"] == "cell_x/base"
    assert prefixed_frames("") == {}
    modules = {"sim_cell": sim_cell, "profiler_driver": profiler_driver, "pose_estimator": pose_estimator,
               "pd_compensator": pd_compensator, "motoplus_bridge": motoplus_bridge}
    for node, names in FRAME_PARAMETERS.items():  # every frame parameter exists, with the standard default
        params = {p.name: p.default for p in modules[node].PARAMETERS}
        assert all(params[name] == default for name, default in names.items()), node


def test_the_ports_a_cell_is_given_are_all_different() -> None:
    # a port closed before the next is asked for can be handed out again: one bringup's profiler and robot
    # controller were once given the same port, and its sim_cell could not start (asked one at a time, 300
    # ports here repeat a few)
    from profile_pose_ros.tools.graph import free_ports

    ports = free_ports(300)
    assert len(set(ports)) == len(ports)
