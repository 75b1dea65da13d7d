"""Intra-process delivery for the loop's nodes composed in one process (cell_container).

rclpy has no intra-process transport: between two nodes of one process a message still goes through
DDS, and each hop costs a publish, a wake-up of the taking thread and a take (most of the graph's CPU at
1 kHz: docs/performance.md). Composed, the loop's topics
(profile -> pose_with_covariance -> correction) are handed from the publishing node to the taking node
as the same serialized bytes, in the publisher's thread: the driver's link thread receives a frame,
and the estimate, the correction and the bridge's store follow without a wake-up. DDS still carries
every message to whoever else subscribes (a recorder, an observer, another process); with none, it is
not serialized for nobody.

A topic is matched by its resolved name, so namespaces and remappings apply as they do over DDS. The
taker's callback gets the bytes alone, no middleware message info. It runs in the publisher's thread,
so a taker guards its state against its own executor's callbacks; an exception it raises is logged by
the publisher and goes no further (one node's fault must not stop another's thread).

Profiles: the driver hands over only the newest of the frames it read at once (profiler_driver.py).
The chain runs in its link thread, so when the chain is slower than the profiler, frames wait in the
socket and arrive together, and the older ones are superseded instead of queued: the loop works on
the newest measurement, as with the estimator's KEEP_LAST queue over DDS. Handing over every profile
falls ever further behind when the chain is slower than the profiler; a worker thread with its own queue
makes the link thread wait for the GIL at every socket read, so it falls behind too (docs/design_notes.md).
"""
from __future__ import annotations

from typing import Callable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

Taker = Callable[[bytes], None]

# How a loop node takes its high-rate input over DDS (the compensator's poses, the bridge's corrections):
# the newest message is what counts, and a retransmitted old one is of no use to a loop. A best-effort
# reader also about halves what each publish costs the publisher, which keeps its reliable offer for
# anyone else (a recorder, `ros2 topic echo`; docs/design_notes.md). Over loopback nothing is lost either
# way unless the reader's queue overflows, and then KEEP_LAST drops the oldest, reliable or not.
LOOP_INPUT_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT,
                            durability=DurabilityPolicy.VOLATILE)


def profile_input_qos(depth: int) -> QoSProfile:
    """How a node takes profiles over DDS: sensor-data QoS (a consumer that falls behind drops the oldest)
    with a queue of its own depth."""
    return QoSProfile(depth=depth, reliability=qos_profile_sensor_data.reliability,
                      durability=qos_profile_sensor_data.durability, history=qos_profile_sensor_data.history)


LOOP_TOPICS = ("profile", "pose_with_covariance", "correction", "robot_state", "lost_increment")


class LocalTopics:
    """Resolved topic name -> the callbacks of the composed nodes that take it; and which of the loop's topics
    (relative names) both ends of which are in this process, so a node knows whether to take one here or
    subscribe over DDS."""

    def __init__(self, carried: tuple[str, ...] = LOOP_TOPICS) -> None:
        unknown = set(carried) - set(LOOP_TOPICS)
        if unknown:
            raise ValueError(f"not loop topics: {sorted(unknown)}")
        self.carried = frozenset(carried)
        self._takers: dict[str, list[Taker]] = {}

    def carries(self, topic: str) -> bool:
        return topic in self.carried

    def take(self, topic: str, callback: Taker) -> None:
        self._takers.setdefault(topic, []).append(callback)

    def takers(self, topic: str) -> list[Taker]:
        return self._takers.get(topic, [])


class LoopOutput:
    """A node's publisher of a loop topic. publish() sends over DDS if anyone subscribes there (publishing
    to nobody still costs a serialization and a write); hand_over() then gives the same bytes to every local
    taker. Two steps, so that a node times its stage at the publish, as it does standalone, and not after
    the downstream nodes' work."""

    def __init__(self, publisher, local: LocalTopics | None, logger=None) -> None:
        self.publisher = publisher
        self.local = local
        self.logger = logger

    def publish(self, serialized: bytes) -> None:
        if self.publisher.get_subscription_count():  # DDS subscribers only: local takers get hand_over()
            self.publisher.publish(serialized)

    def hand_over(self, serialized: bytes) -> None:
        if self.local is None:
            return
        for taker in self.local.takers(self.publisher.topic_name):  # looked up each time: nodes compose in any order
            try:
                taker(serialized)
            except Exception as exc:  # noqa: BLE001 - the taker's fault, reported, not the publisher's
                if self.logger is not None:
                    self.logger.error(f"composed taker of {self.publisher.topic_name} failed: {exc!r}",
                                      throttle_duration_sec=1.0)
