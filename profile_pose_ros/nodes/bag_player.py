"""bag_player: publish a rosbag2 bag with its original timing (or a rate factor), from a start offset,
once or in a loop, all topics or a filtered set; the messages go out as recorded (serialized bytes,
header stamps untouched) with the QoS their publishers offered. Exits when done unless looping. With
`clock` > 0 it also publishes the bag's time on /clock, so nodes run with use_sim_time live in the bag's time.

Recorded topics keep their absolute names; remap them as usual (`--ros-args -r /profile:=/cell2/profile`).
"""
from __future__ import annotations

import sys
import threading
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from ..bags import BagError, bag_info, read_messages
from .bag_common import from_bag_qos, message_class
from .diagnostics import ERROR, OK, diagnostic_array
from .parameters import Param, declare_all
from .run import run_node

NODE_NAME = "bag_player"

PARAMETERS = [
    Param("bag", "", "Bag directory to play (required).", read_only=True),
    Param("rate", 1.0, "Playback speed factor (2.0: twice as fast).", 0.01, 100.0, read_only=True),
    Param("start_offset", 0.0, "Start this far into the bag (s).", 0.0, 1e7, read_only=True),
    Param("loop", False, "Start again at the end, until stopped.", read_only=True),
    Param("topics", [], "Topics to play (as recorded, absolute). Empty: all.", read_only=True),
    Param("exclude_topics", [], "Topics never played.", read_only=True),
    Param("queue_depth", 100, "Publisher history depth.", 1, 100000, read_only=True),
    Param("wait_for_subscribers", False, "Start only once every played topic (and /clock, when published) has a "
          "subscriber (or after wait_timeout).", read_only=True),
    Param("wait_timeout", 10.0, "Longest wait for subscribers (s).", 0.0, 3600.0, read_only=True),
    Param("discovery_grace", 0.5, "After the subscribers appear, wait this long before the first message when a "
          "topic is best-effort (s): such a writer sees its reader before the reader has matched it back, and "
          "the first messages would be lost (sensor topics such as profile are best-effort).", 0.0, 60.0,
          read_only=True),
    Param("exit_when_done", True, "Shut down after the last message (unless looping).", read_only=True),
    Param("clock", 0.0, "Publish the bag's time on /clock this often (Hz), as `ros2 bag play --clock` does, for "
          "nodes run with use_sim_time; 0: no /clock.", 0.0, 1000.0, read_only=True),
    Param("diagnostics_period", 1.0, "Period of /diagnostics (s).", 0.02, 60.0, read_only=True),
]


class BagPlayerNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        v = self.values = declare_all(self, PARAMETERS)
        if not v["bag"]:
            raise ValueError("parameter 'bag' (the bag directory to play) is required")
        self.info = bag_info(v["bag"])  # BagError: refuses to start, naming the problem
        excluded = set(v["exclude_topics"])
        self.topics = [t for t in self.info.topics.values()
                       if (not v["topics"] or t.name in v["topics"]) and t.name not in excluded]
        if not self.topics:
            raise ValueError(f"none of the topics asked for is in {v['bag']} (it has {sorted(self.info.topics)})")
        self.publishers_by_topic = {
            t.name: self.create_publisher(message_class(t.msgtype), t.name, from_bag_qos(t.qos, v["queue_depth"]))
            for t in self.topics}
        self.published = 0
        self.passes = 0
        self.last_error = ""
        self.done = threading.Event()
        self._stop = threading.Event()
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics)
        self._bag_origin: tuple[int, float] | None = None  # (bag time ns, monotonic s) of this pass's start
        self.clock_pub = None
        if v["clock"] > 0:
            self.clock_pub = self.create_publisher(Clock, "/clock", 10)
            self._clock_thread = threading.Thread(target=self._run_clock, name="bag-clock", daemon=True)
            self._clock_thread.start()
        self._thread = threading.Thread(target=self._run, name="bag-player", daemon=True)
        self._thread.start()
        seconds = self.info.duration_ns * 1e-9
        self.get_logger().info(f"playing {len(self.topics)} topics of {v['bag']} ({seconds:.1f} s) "
                               f"at {v['rate']}x{' in a loop' if v['loop'] else ''}")

    def _wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + self.values["wait_timeout"]
        # /clock too: a use_sim_time node whose clock subscription matches late misses the start of the bag's time
        waited = [*self.publishers_by_topic.values(), *([self.clock_pub] if self.clock_pub is not None else [])]
        while time.monotonic() < deadline and not self._stop.is_set():
            if all(p.get_subscription_count() for p in waited):
                if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                       for p in self.publishers_by_topic.values()):
                    self._stop.wait(self.values["discovery_grace"])
                return
            self._stop.wait(0.02)
        self.get_logger().warn("not every topic has a subscriber; playing anyway")

    def _run(self) -> None:
        try:
            if self.values["wait_for_subscribers"]:
                self._wait_for_subscribers()
            while not self._stop.is_set():
                self._play_once()
                self.passes += 1
                if not self.values["loop"]:
                    break
        except BagError as exc:
            self.last_error = str(exc)
            self.get_logger().error(f"playback stopped: {exc}")
        for publisher in self.publishers_by_topic.values():  # reliable subscribers get the last messages too
            if publisher.qos_profile.reliability == ReliabilityPolicy.RELIABLE:
                publisher.wait_for_all_acked(Duration(seconds=1.0))
        self.done.set()
        if self.values["exit_when_done"] and not self._stop.is_set():
            rclpy.try_shutdown(context=self.context)

    def _play_once(self) -> None:
        rate = self.values["rate"]
        start_ns = self.info.start_ns + int(self.values["start_offset"] * 1e9)
        first_ns = wall_start = None
        for topic, _type, stamp_ns, data in read_messages(self.info.path, list(self.publishers_by_topic), start_ns):
            if first_ns is None:
                first_ns, wall_start = stamp_ns, time.monotonic()
                self._bag_origin = (first_ns, wall_start)
            delay = wall_start + (stamp_ns - first_ns) * 1e-9 / rate - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            if self._stop.is_set():
                return
            self.publishers_by_topic[topic].publish(data)
            self.published += 1

    def _run_clock(self) -> None:
        """/clock at the `clock` rate: the bag time being played now (the pass's first message time, plus the
        time since, times `rate`); nothing before the first message or after the end."""
        period = 1.0 / self.values["clock"]
        message = Clock()
        while not self._stop.wait(period) and not self.done.is_set():
            origin = self._bag_origin
            if origin is None:
                continue
            now_ns = origin[0] + int((time.monotonic() - origin[1]) * self.values["rate"] * 1e9)
            message.clock.sec, message.clock.nanosec = divmod(min(now_ns, self.info.start_ns + self.info.duration_ns),
                                                              1_000_000_000)
            self.clock_pub.publish(message)

    def _publish_diagnostics(self) -> None:
        level, message = (ERROR, self.last_error) if self.last_error else (
            OK, "done" if self.done.is_set() else f"playing (pass {self.passes + 1})")
        values = {"bag": str(self.info.path), "published": self.published, "passes": self.passes}
        self.diagnostics_pub.publish(diagnostic_array(self, "playback",
                                                      self.info.path.name, level, message, values))

    def destroy_node(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        if self.clock_pub is not None:
            self._clock_thread.join(timeout=5.0)
        super().destroy_node()


def main(args=None) -> int:
    return run_node(BagPlayerNode, NODE_NAME, args, startup_errors=(BagError, ValueError))


if __name__ == "__main__":
    sys.exit(main())
