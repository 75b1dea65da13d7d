"""bag_recorder: record topics of the graph to a rosbag2 bag (MCAP by default, sqlite3 by parameter).

Messages are taken serialized (raw) and written as they came, with the QoS their publishers offered and
the time they arrived. New topics are picked up as they appear. Every `flush_period` the bag reaches
the disk, so a recorder that is killed loses at most that much (`profile_pose_bag recover` finishes such
a bag); Ctrl-C or SIGTERM closes it properly. Thin glue around profile_pose_ros.bags.BagWriter.

Messages the recorder never got (its `queue_depth` overrun while it was busy, or lost on the way) are
counted from the gaps in each writer's DDS sequence numbers (core/timing/sequence_gaps.py) on the topics that
have one publisher (most of a cell's; /diagnostics, with one per node, is not checked): a bag that is
missing messages says so.
"""
from __future__ import annotations

import sys
import time
from functools import partial
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node

from ..bags import BagError, BagWriter
from ..bags.writer import COMPRESSIONS, STORAGES
from ..core.timing.sequence_gaps import SequenceGaps
from .bag_common import message_class, subscription_qos, to_bag_qos
from .diagnostics import ERROR, OK, WARN, diagnostic_array
from .direct_input import DirectInput, ServedDirectly, spin, take_all
from .parameters import Param, declare_all
from .run import run_node

NODE_NAME = "bag_recorder"

PARAMETERS = [
    Param("output", "", "Bag directory to create (never overwritten). Empty: rosbag2_<date-time> here.",
          read_only=True),
    Param("topics", [], "Topics to record (relative names resolve in this node's namespace). Empty: all.",
          read_only=True),
    Param("exclude_topics", [], "Topics never recorded, even when `topics` is empty.", read_only=True),
    Param("storage", "mcap", f"Storage: {' or '.join(STORAGES)}.", read_only=True),
    Param("compression", "zstd", f"MCAP chunk compression: {' or '.join(COMPRESSIONS)} (none with sqlite3).",
          read_only=True),
    Param("max_bag_size", 0, "Split to a new file after this many bytes of messages (0: never).", 0, 2 ** 62,
          read_only=True),
    Param("max_bag_duration", 0.0, "Split to a new file after this long (s; 0: never).", 0.0, 1e6, read_only=True),
    Param("flush_period", 1.0, "Put the bag on disk this often (s): what a crash can lose at most.", 0.05, 60.0,
          read_only=True),
    Param("discovery_period", 0.5, "Look for new topics this often (s).", 0.05, 60.0, read_only=True),
    Param("queue_depth", 1000, "Messages a subscription keeps while the recorder is busy.", 1, 100000,
          read_only=True),
    Param("diagnostics_period", 1.0, "Period of /diagnostics (s).", 0.02, 60.0, read_only=True),
]


def default_output() -> str:
    return time.strftime("rosbag2_%Y_%m_%d-%H_%M_%S")


class BagRecorderNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        v = self.values = declare_all(self, PARAMETERS)
        self.writer = BagWriter(v["output"] or default_output(), v["storage"], v["compression"],
                                v["max_bag_size"], v["max_bag_duration"])
        self.wanted = {self.resolve_topic_name(t) for t in v["topics"]}
        self.excluded = {self.resolve_topic_name(t) for t in v["exclude_topics"]}
        self.subscriptions_by_topic: dict[str, object] = {}
        self.refused: dict[str, str] = {}  # topic -> why it is not recorded
        self.received = 0
        self.gaps: dict[str, SequenceGaps | None] = {}  # per topic while it has one publisher, else None
        self.lost = 0  # messages never recorded (on single-publisher topics)
        self.lost_before = 0  # self.lost as of the last diagnostics
        self.flushed = 0  # messages on disk as of the last flush: what a kill cannot take
        self.last_error = ""
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # Messages are taken straight from their subscriptions (direct_input.py): through the executor, which
        # rebuilds its wait set over every entity for each message, that was half the recorder's CPU.
        self.served_here = ServedDirectly()
        self.direct_input = DirectInput(None, self.context)
        self.create_timer(v["discovery_period"], self._discover)
        self.create_timer(v["flush_period"], self._flush)
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics)
        self._discover()
        self.get_logger().info(f"recording {'all topics' if not self.wanted else sorted(self.wanted)} to "
                               f"{self.writer.path} ({v['storage']}, flushed every {v['flush_period']} s)")

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subscriptions_by_topic:
                self._check_writers(topic)
                continue
            if topic in self.refused or topic in self.excluded:
                continue
            if self.wanted and topic not in self.wanted:
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue  # only subscribers so far: no QoS to match yet
            if len(types) > 1:
                self._refuse(topic, f"published with several types {types}")
                continue
            try:
                self.writer.add_topic(topic, types[0], [to_bag_qos(p.qos_profile) for p in publishers])
                msg_class = message_class(types[0])
            except (BagError, ValueError) as exc:
                self._refuse(topic, str(exc))
                continue
            qos = subscription_qos([p.qos_profile for p in publishers], self.values["queue_depth"])
            on_message = partial(self._on_message, topic)
            subscription = self.create_subscription(msg_class, topic, on_message, qos, raw=True,
                                                    callback_group=self.served_here)
            self.subscriptions_by_topic[topic] = subscription
            self._check_writers(topic)
            self.direct_input.add(subscription, on_message, with_info=True)
            self.get_logger().info(f"recording {topic} ({types[0]})")

    def _refuse(self, topic: str, reason: str) -> None:
        self.refused[topic] = reason
        self.get_logger().error(f"not recording {topic}: {reason}")

    def _check_writers(self, topic: str) -> None:
        """Count gaps on `topic` only while it has one publisher: several writers' numbers interleave."""
        single = self.count_publishers(topic) == 1
        if not single:
            self.gaps[topic] = None
        elif self.gaps.get(topic) is None:
            self.gaps[topic] = SequenceGaps()  # afresh: the writer it had may not be this one

    def _on_message(self, topic: str, data: bytes, info: dict | None = None) -> None:
        gaps = self.gaps.get(topic)
        if gaps is not None and info is not None:
            self.lost += gaps.update(info.get("publication_sequence_number"))
        try:
            self.writer.write(topic, self.get_clock().now().nanoseconds, data)
            self.received += 1
        except (OSError, BagError) as exc:  # a full disk must not take the node down
            self.last_error = str(exc)
            self.get_logger().error(f"write failed: {exc}", throttle_duration_sec=1.0)

    def _flush(self) -> None:
        try:
            self.writer.flush()
            self.flushed = self.received
        except OSError as exc:
            self.last_error = str(exc)
            self.get_logger().error(f"flush failed: {exc}", throttle_duration_sec=1.0)

    def _publish_diagnostics(self) -> None:
        if self.last_error:
            level, message = ERROR, f"writing failed: {self.last_error}"
        elif not self.subscriptions_by_topic:
            level, message = WARN, "no topic to record yet"
        elif self.lost > self.lost_before:
            level, message = WARN, (f"{self.lost - self.lost_before} messages lost before recording (queue_depth "
                                    f"too small for this machine, or lost on the way)")
        else:
            level, message = OK, f"recording {len(self.subscriptions_by_topic)} topics"
        self.lost_before = self.lost
        values = {"bag": str(self.writer.path), "messages": self.received, "messages_flushed": self.flushed,
                  "messages_lost": self.lost,
                  "topics_checked_for_loss": sum(g is not None for g in self.gaps.values()),
                  "topics": len(self.subscriptions_by_topic),
                  "splits_closed": self.writer.splits_closed, "not_recorded": "; ".join(
                      f"{t}: {r}" for t, r in self.refused.items()) or "none"}
        self.diagnostics_pub.publish(diagnostic_array(self, "recording",
                                                      str(Path(self.writer.path).name), level, message, values))

    def pump(self, timeout_sec: float = 0.0) -> int:
        """Write the messages queued (see direct_input.py); spin() or a test harness calls this."""
        return self.direct_input.pump(timeout_sec)

    def drain(self) -> int:
        """Write what the subscriptions still hold (not yet taken)."""
        drained = 0
        for topic, subscription in self.subscriptions_by_topic.items():
            for message, info in take_all(subscription):
                self._on_message(topic, message, info)
                drained += 1
        return drained

    def destroy_node(self) -> None:
        if self.context.ok():
            self.drain()
        self.writer.close()  # on every shutdown path: the bag is complete
        print(f"[bag_recorder] closed {self.writer.path}: {self.received} messages", file=sys.stderr)
        super().destroy_node()


def main(args=None) -> int:
    return run_node(BagRecorderNode, NODE_NAME, args, startup_errors=(BagError, ValueError),
                    spin=lambda executor, node, stop: spin(executor, node.direct_input, stop))


if __name__ == "__main__":
    sys.exit(main())
