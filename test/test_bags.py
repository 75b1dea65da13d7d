"""Bags without ROS (BagWriter, recovery) and the bag_recorder / bag_player nodes with real rclpy."""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from profile_pose_ros.bags import BagError, BagWriter, bag_info, read_messages, recover
from profile_pose_ros.bags.reader import typestore
from profile_pose_ros.tools import processes
from profile_pose_ros.tools.graph import MODULES, ros_params

STRING = "std_msgs/msg/String"


def string_bytes(text: str) -> bytes:
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String

    return bytes(typestore().serialize_cdr(String(data=text), STRING))


def texts(bag, topics=None) -> list[str]:
    return [typestore().deserialize_cdr(d, t).data for _, t, _, d in read_messages(bag, topics)]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_splits_by_size_and_duration_into_one_bag_read_back_in_order(tmp_path, storage) -> None:
    for name, limits in (("by_size", {"max_bytes": 3000}), ("by_duration", {"max_duration_s": 0.5})):
        writer = BagWriter(tmp_path / name, storage=storage, **limits)
        writer.add_topic("/a", STRING)
        writer.add_topic("/b", STRING)
        for i in range(400):
            writer.write("/a" if i % 3 else "/b", 10 ** 9 + i * 10 ** 7, string_bytes(f"message {i:04d}" + "x" * 20))
        writer.close()
        info = bag_info(tmp_path / name)
        assert len(info.files) >= 4, info.files
        assert info.message_count == 400 and info.topics["/b"].count == 134 and info.topics["/a"].count == 266
        assert texts(tmp_path / name) == [f"message {i:04d}" + "x" * 20 for i in range(400)]
        assert abs(info.duration_ns - 399 * 10 ** 7) <= 1
        if storage == "mcap":
            assert foxglove_count(tmp_path / name) == 400


def test_zstd_chunks_an_empty_bag_and_refusals(tmp_path) -> None:
    writer = BagWriter(tmp_path / "z", compression="zstd")
    writer.add_topic("/a", STRING)
    for i in range(50):
        writer.write("/a", 10 ** 9 + i, string_bytes("y" * 1000))
    writer.close()
    assert texts(tmp_path / "z") == ["y" * 1000] * 50
    assert sum(f.stat().st_size for f in (tmp_path / "z").glob("*.mcap")) < 50 * 1000 / 5

    metadata = yaml.safe_load((tmp_path / "z" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["ros_distro"] == "jazzy"  # as rosbag2 writes it (rosbags wrote its own name)
    empty = BagWriter(tmp_path / "empty")
    empty.close()
    assert bag_info(tmp_path / "empty").message_count == 0 and texts(tmp_path / "empty") == []

    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp_path / "z")
    with pytest.raises(BagError, match="no message definition"):
        BagWriter(tmp_path / "x").add_topic("/a", "no_such_pkg/msg/Nothing")
    with pytest.raises(BagError, match="compression needs the mcap"):
        BagWriter(tmp_path / "y", storage="sqlite3", compression="zstd")


KILLED_WRITER = """
import os, sys
from profile_pose_ros.bags import BagWriter
from profile_pose_ros.bags.reader import typestore
from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String
string_bytes = lambda text: bytes(typestore().serialize_cdr(String(data=text), "std_msgs/msg/String"))
writer = BagWriter(sys.argv[1], storage=sys.argv[2], max_bytes=4000)
writer.add_topic("/a", "std_msgs/msg/String")
for i in range(300):
    writer.write("/a", 10**9 + i * 10**6, string_bytes(f"m{i}"))
    if i == 249:
        writer.flush()
os.kill(os.getpid(), 9)
"""


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_killed_writer_leaves_everything_up_to_its_last_flush(tmp_path, storage) -> None:
    bag = tmp_path / "killed"
    result = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(bag), storage], timeout=120)
    assert result.returncode == -signal.SIGKILL
    with pytest.raises(BagError, match="recover"):
        bag_info(bag)
    assert recover(bag)
    got = texts(bag)
    assert got[:250] == [f"m{i}" for i in range(250)]  # all up to the flush; what followed may be cut
    assert got == [f"m{i}" for i in range(len(got))]
    assert recover(bag) == []  # a closed bag is left as it is
    if storage == "mcap":
        assert foxglove_count(bag) == len(got)
        # the recovered split keeps the recording's zstd chunks (it came back uncompressed, ten times larger)
        from profile_pose_ros.bags.writer import _mcap_compression
        assert {_mcap_compression(path) for path in bag.glob("*.mcap")} == {"zstd"}


def foxglove_count(bag) -> int:
    """Messages in the bag's MCAP files as Foxglove's own reader (the `mcap` library) sees them, after
    checking the ros2 profile, the summary and the schemas."""
    from mcap.reader import make_reader

    total = 0
    for path in sorted(bag.glob("*.mcap")):
        with path.open("rb") as stream:
            reader = make_reader(stream)
            assert reader.get_header().profile == "ros2"
            summary = reader.get_summary()
            assert all(s.encoding == "ros2msg" and s.data for s in summary.schemas.values())
            assert all(c.message_encoding == "cdr" for c in summary.channels.values())
            count = sum(1 for _ in reader.iter_messages())
            assert count == summary.statistics.message_count
            total += count
    return total


# ---------------------------------------------------------------------- the nodes
def start_node(ros, tmp_path, executable: str, params: dict) -> subprocess.Popen:
    command = processes.executable(executable, MODULES[executable]) + ["--ros-args", *ros_params(params)]
    return processes.start(command, ros.domain_id, tmp_path / f"{executable}.log")


def recorder_value(ros, key: str) -> dict:
    """Newest value of the recorder's /diagnostics, kept up to date by a subscription made here."""
    from diagnostic_msgs.msg import DiagnosticArray

    latest: dict = {}

    def on_diagnostics(msg) -> None:
        for status in msg.status:
            if status.name.startswith("bag_recorder"):
                latest.update({kv.key: kv.value for kv in status.values})

    ros.node("diagnostics_watch").create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)
    return latest


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGKILL])
def test_recorder_keeps_every_message_on_sigint_and_up_to_the_last_flush_on_sigkill(ros, tmp_path,
                                                                                   stop_signal) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    bag = tmp_path / "bag"
    recorder = start_node(ros, tmp_path, "bag_recorder", {
        "output": str(bag), "topics": ["chatter", "latched"], "flush_period": 0.2, "diagnostics_period": 0.1,
        "discovery_period": 0.1})
    try:
        node = ros.node("talker")
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        chatter = node.create_publisher(String, "chatter", reliable)
        latched = node.create_publisher(String, "latched", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        latched.publish(String(data="configuration"))  # before the recorder subscribes: transient local
        status = recorder_value(ros, "messages")
        assert ros.spin_until(lambda: chatter.get_subscription_count() and latched.get_subscription_count(), 30.0)
        for i in range(200):
            chatter.publish(String(data=f"c{i}"))
        assert ros.spin_until(lambda: status.get("messages_flushed") == "201", 30.0), status
        for i in range(200, 230):  # after the flush: SIGINT keeps them, SIGKILL may lose them
            chatter.publish(String(data=f"c{i}"))
        if stop_signal == signal.SIGINT:
            assert ros.spin_until(lambda: status.get("messages") == "231", 30.0), status
        recorder.send_signal(stop_signal)
        recorder.wait(30.0)
    finally:
        processes.stop(recorder)
    if stop_signal == signal.SIGKILL:
        assert recover(bag)
    info = bag_info(bag)
    chatter_texts = texts(bag, ["/chatter"])
    assert texts(bag, ["/latched"]) == ["configuration"]
    assert chatter_texts[:200] == [f"c{i}" for i in range(200)]
    if stop_signal == signal.SIGINT:
        assert chatter_texts == [f"c{i}" for i in range(230)]
    assert info.topics["/latched"].qos[0].durability.name == "TRANSIENT_LOCAL"
    assert info.topics["/chatter"].qos[0].reliability.name == "RELIABLE"


def test_player_keeps_timing_rate_offset_filter_and_loops(ros, tmp_path) -> None:
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from profile_pose_ros.nodes.bag_player import BagPlayerNode

    bag = tmp_path / "bag"
    writer = BagWriter(bag)
    writer.add_topic("/a", STRING)
    writer.add_topic("/b", STRING)
    for i in range(20):  # /a every 0.1 s over 1.9 s, /b once at the start
        writer.write("/a", 10 ** 9 + i * 10 ** 8, string_bytes(f"a{i}"))
    writer.write("/b", 10 ** 9, string_bytes("b"))
    writer.close()

    received: list[tuple[float, str]] = []
    listener = ros.node("listener")
    for topic in ("/a", "/b"):
        listener.create_subscription(String, topic, lambda m: received.append((time.monotonic(), m.data)), 100)

    def play(until=None, **params):
        received.clear()
        overrides = [Parameter("bag", value=str(bag)), Parameter("exit_when_done", value=False),
                     Parameter("wait_for_subscribers", value=True)]
        player = ros.add(BagPlayerNode(context=ros.context, parameter_overrides=overrides + [
            Parameter(k, value=v) for k, v in params.items()]))
        assert ros.spin_until(until or player.done.is_set, 30.0)
        ros.spin_until(lambda: False, 0.2)  # deliveries still in flight
        ros.nodes.remove(player)
        ros.executor.remove_node(player)
        player.destroy_node()
        return [text for _, text in received], [t for t, _ in received]

    got, times = play(rate=2.0, topics=["/a"])
    assert got == [f"a{i}" for i in range(20)]
    assert np.median(np.diff(times)) >= 0.9 * 0.1 / 2.0  # never faster than asked (the first may come late)
    got, _ = play(rate=10.0, start_offset=1.05)
    assert got == [f"a{i}" for i in range(11, 20)]
    got, _ = play(lambda: len(received) >= 3, rate=20.0, loop=True, exclude_topics=["/a"])
    assert got[:3] == ["b", "b", "b"] and "a0" not in got


def test_player_publishes_the_bags_time_on_clock_for_nodes_with_sim_time(ros, tmp_path) -> None:
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    from profile_pose_ros.nodes.bag_player import BagPlayerNode

    bag = tmp_path / "bag"
    writer = BagWriter(bag)
    writer.add_topic("/a", STRING)
    for i in range(30):  # 3 s of bag time, a day after the epoch: far from this machine's clock
        writer.write("/a", 86400 * 10 ** 9 + i * 10 ** 8, string_bytes(f"a{i}"))
    writer.close()
    clocks: list[int] = []
    listener = ros.node("clock_listener")
    listener.create_subscription(Clock, "/clock", lambda m: clocks.append(m.clock.sec * 10 ** 9 + m.clock.nanosec), 100)
    sim = ros.node("sim_time_user")
    sim.set_parameters([Parameter("use_sim_time", value=True)])
    ros.add(BagPlayerNode(context=ros.context, parameter_overrides=[
        Parameter("bag", value=str(bag)), Parameter("clock", value=50.0), Parameter("rate", value=2.0),
        Parameter("exit_when_done", value=False), Parameter("wait_for_subscribers", value=True)]))
    assert ros.spin_until(lambda: len(clocks) >= 20, 30.0)
    assert all(86400 * 10 ** 9 <= c <= 86400 * 10 ** 9 + 29 * 10 ** 8 for c in clocks)
    assert clocks == sorted(clocks) and clocks[-1] > clocks[0]
    assert 86400 * 10 ** 9 <= sim.get_clock().now().nanoseconds <= 86400 * 10 ** 9 + 29 * 10 ** 8  # the bag's time


def test_player_refuses_a_missing_bag_with_the_reason(tmp_path) -> None:
    command = processes.executable("bag_player", MODULES["bag_player"]) + [
        "--ros-args", "-p", f"bag:={tmp_path / 'nothing'}"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and "nothing" in result.stderr and "refusing to start" in result.stderr


def test_recorder_counts_the_messages_it_never_got(ros, tmp_path) -> None:
    """A burst while the recorder is busy overruns its queue: every message is either in the bag or counted
    lost, and the diagnostics say so."""
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from std_msgs.msg import String

    from profile_pose_ros.nodes.bag_recorder import BagRecorderNode

    chatter = ros.node("talker").create_publisher(String, "chatter", qos_profile_sensor_data)
    recorder = ros.add(BagRecorderNode(context=ros.context, parameter_overrides=[
        Parameter("output", value=str(tmp_path / "bag")), Parameter("topics", value=["chatter"]),
        Parameter("queue_depth", value=5), Parameter("discovery_period", value=0.05)]))
    sent = []

    def publish() -> None:
        chatter.publish(String(data="warm-up"))
        sent.append(1)
    assert ros.spin_until(lambda: recorder.received > 0, 30.0, action=publish), "nothing recorded"
    assert ros.spin_until(lambda: recorder.received + recorder.lost >= len(sent))  # none still in flight
    received, lost = recorder.received, recorder.lost
    for i in range(40):  # without spinning: the recorder takes none of them yet
        chatter.publish(String(data=f"b{i}"))
    assert ros.spin_until(lambda: recorder.received - received + recorder.lost - lost >= 40)
    burst_recorded, burst_lost = recorder.received - received, recorder.lost - lost
    assert burst_recorded + burst_lost == 40 and burst_lost >= 30, (burst_recorded, burst_lost)
    assert recorder.gaps["/chatter"] is not None
