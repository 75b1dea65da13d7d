"""What bag_recorder and bag_player share: message classes by type name, and QoS between rclpy and the
form rosbag2 stores (`offered_qos_profiles`)."""
from __future__ import annotations

import importlib

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime


def message_class(msgtype: str):
    """`sensor_msgs/msg/PointCloud2` -> the generated Python class; ValueError if not installed."""
    try:
        package, kind, name = msgtype.split("/")
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ValueError, ImportError, AttributeError):
        raise ValueError(f"message type {msgtype!r} is not installed here") from None


def _time(duration: Duration) -> QosTime:
    sec, nsec = divmod(duration.nanoseconds, 1_000_000_000)
    return QosTime(sec, nsec)


def to_bag_qos(profile: QoSProfile) -> Qos:
    """An endpoint's QoS as rosbag2 records it (the enums share their numbering)."""
    return Qos(QosHistory(int(profile.history)), profile.depth, QosReliability(int(profile.reliability)),
               QosDurability(int(profile.durability)), _time(profile.deadline), _time(profile.lifespan),
               QosLiveliness(int(profile.liveliness)), _time(profile.liveliness_lease_duration),
               profile.avoid_ros_namespace_conventions)


def from_bag_qos(offered: list[Qos] | tuple[Qos, ...], depth: int) -> QoSProfile:
    """The QoS to publish a recorded topic with: what its first publisher offered (reliability,
    durability), keep-last `depth`; reliable and volatile when the bag says nothing."""
    profile = QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST)
    if offered:
        first = offered[0]
        if first.reliability in (QosReliability.RELIABLE, QosReliability.BEST_EFFORT):
            profile.reliability = ReliabilityPolicy(first.reliability.value)
        if first.durability in (QosDurability.TRANSIENT_LOCAL, QosDurability.VOLATILE):
            profile.durability = DurabilityPolicy(first.durability.value)
        if first.liveliness in (QosLiveliness.AUTOMATIC, QosLiveliness.MANUAL_BY_TOPIC):
            profile.liveliness = LivelinessPolicy(first.liveliness.value)
    return profile


def subscription_qos(offered: list[QoSProfile], depth: int) -> QoSProfile:
    """A subscription compatible with every publisher: best effort if any of them is, transient local
    only if all of them are (then late joiners' latched messages are recorded too)."""
    reliable = all(p.reliability == ReliabilityPolicy.RELIABLE for p in offered)
    latched = bool(offered) and all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in offered)
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
