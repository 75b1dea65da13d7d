"""profile_pose replay: re-run pose_estimator's computation on the profiles of a bag, offline and as fast
as possible, and compare with the poses the live node published (and with the truth, when the bag has
sim_cell's /sim/ground_truth).

With the parameters the live node had, every pose must come out bit for bit the same (every field of
the messages is compared); with others (`-p refine_model:=dense`, `--params-file tuned.yaml`) it shows what
the change does on real recorded data. `--output` writes the re-estimated poses to a new bag.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ..bags import BagError, BagWriter, bag_info, read_messages
from .param_files import node_parameters, parse_overrides
from .report import nearest_stamp, summary, table

PROFILE_TYPE = "sensor_msgs/msg/PointCloud2"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
COVARIANCE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRUTH_TOPIC = "/sim/ground_truth"


def estimator_values(params_file: str | None, overrides: dict, namespace: str = "") -> dict:
    from ..nodes.parameters import defaults
    from ..nodes.pose_estimator import NODE_NAME, PARAMETERS

    values = defaults(PARAMETERS)
    given = dict(node_parameters(params_file, NODE_NAME, namespace, set(values)) if params_file else {})
    given.update(overrides)
    unknown = sorted(set(given) - set(values))
    if unknown:
        raise ValueError(f"pose_estimator has no parameter {', '.join(unknown)}")
    values.update(given)
    return values


def profile_topic_of(info, wanted: str | None) -> str:
    if wanted:
        if wanted not in info.topics:
            raise BagError(f"{wanted} is not in the bag (it has {sorted(info.topics)})")
        return wanted
    profiles = [t.name for t in info.topics.values() if t.msgtype == PROFILE_TYPE]
    if len(profiles) != 1:
        raise BagError(f"cannot tell the profile topic among {profiles or 'none'}: give --profile-topic")
    return profiles[0]


def canonical(data: bytes, msgtype: str) -> bytes:
    """The message re-serialized with zero padding: rclpy's serializer leaves the alignment bytes
    uninitialised, so equal messages can differ in those bytes; every field's bits are kept."""
    from ..bags.reader import typestore

    store = typestore()
    return bytes(store.serialize_cdr(store.deserialize_cdr(data, msgtype), msgtype))


TRUTH_TOLERANCE_NS = 500_000  # a pose's stamp (the estimated trigger time) within 0.5 ms of the true one


def replay(bag: str | Path, values: dict, profile_topic: str | None = None, output: str | None = None) -> dict:
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.serialization import deserialize_message

    from ..core.estimation.estimator import warm_up
    from ..core.model.gauge import Gauge
    from ..nodes.messages import pose_difference, stamp_ns
    from ..nodes.pose_estimator import options_from, poses_from_profile
    from ..resources import DEFAULT_GAUGE, config_path

    info = bag_info(bag)
    profile_topic = profile_topic_of(info, profile_topic)
    prefix = profile_topic[: -len("profile")] if profile_topic.endswith("profile") else "/"
    pose_topic, covariance_topic = prefix + "pose", prefix + "pose_with_covariance"
    gauge = Gauge.from_yaml(values["gauge_file"] or str(config_path(DEFAULT_GAUGE)))
    options = options_from(values)
    warm_up(gauge, options)

    recorded: dict[int, bytes] = {}
    recorded_covariance: dict[int, bytes] = {}
    truth: dict[int, object] = {}
    replayed: dict[int, tuple[bytes, bytes, object]] = {}
    reasons: dict[str, int] = {}
    writer = BagWriter(output) if output else None
    if writer:
        writer.add_topic(pose_topic, POSE_TYPE, list(info.topics[pose_topic].qos) if pose_topic in info.topics else [])
        writer.add_topic(covariance_topic, COVARIANCE_TYPE)
    busy = 0.0
    wanted = [t for t in (profile_topic, pose_topic, covariance_topic, TRUTH_TOPIC) if t in info.topics]
    for topic, _type, received_ns, data in read_messages(bag, wanted):
        if topic == profile_topic:
            start = time.perf_counter()
            result = poses_from_profile(data, gauge, options, values["profiler_frame"], values["gauge_frame"],
                                        hint=values["orientation_hint"])
            busy += time.perf_counter() - start
            if result.reason:
                key = result.reason.split(":")[0][:60]
                reasons[key] = reasons.get(key, 0) + 1
                continue
            pose_bytes = canonical(result.pose, POSE_TYPE)
            covariance_bytes = canonical(result.pose_with_covariance, COVARIANCE_TYPE)
            replayed[result.stamp_ns] = (pose_bytes, covariance_bytes)
            if writer:
                writer.write(pose_topic, received_ns, pose_bytes)
                writer.write(covariance_topic, received_ns, covariance_bytes)
        elif topic == pose_topic:
            recorded[stamp_ns(deserialize_message(data, PoseStamped).header.stamp)] = canonical(data, POSE_TYPE)
        elif topic == covariance_topic:
            msg = deserialize_message(data, PoseWithCovarianceStamped)
            recorded_covariance[stamp_ns(msg.header.stamp)] = canonical(data, COVARIANCE_TYPE)
        else:
            msg = deserialize_message(data, PoseStamped)
            truth[stamp_ns(msg.header.stamp)] = msg.pose
    if writer:
        writer.close()

    both = sorted(set(recorded) & set(replayed))
    identical = {s for s in both if recorded[s] == replayed[s][0]
                 and (s not in recorded_covariance or recorded_covariance[s] == replayed[s][1])}
    differences = [pose_difference(deserialize_message(recorded[s], PoseStamped).pose,
                                   deserialize_message(replayed[s][0], PoseStamped).pose)
                   for s in both if s not in identical]
    report = {
        "bag": str(bag), "profile_topic": profile_topic, "profiles": info.topics[profile_topic].count,
        "replayed_poses": len(replayed), "recorded_poses": len(recorded), "compared": len(both),
        "identical": len(identical), "different": len(both) - len(identical),
        "recorded_only": len(set(recorded) - set(replayed)), "replayed_only": len(set(replayed) - set(recorded)),
        "rejected": reasons, "replay_ms_per_profile": 1e3 * busy / max(1, info.topics[profile_topic].count),
        "difference_position_um": summary(d[0] * 1e6 for d in differences),
        "difference_rotation_urad": summary(d[1] * 1e6 for d in differences),
    }
    if truth:
        truth_stamps = np.array(sorted(truth), dtype=np.int64)
        for name, poses in (("recorded", {s: deserialize_message(recorded[s], PoseStamped).pose for s in recorded}),
                            ("replayed", {s: deserialize_message(replayed[s][0], PoseStamped).pose for s in replayed})):
            matched = {s: nearest_stamp(truth_stamps, s, TRUTH_TOLERANCE_NS) for s in sorted(poses)}
            errors = [pose_difference(poses[s], truth[t]) for s, t in matched.items() if t is not None]
            report[f"{name}_error_position_um"] = summary(e[0] * 1e6 for e in errors)
            report[f"{name}_error_rotation_urad"] = summary(e[1] * 1e6 for e in errors)
    return report


def print_report(report: dict) -> None:
    rows = [(k.replace("_", " "), str(report[k])) for k in
            ("profiles", "replayed_poses", "recorded_poses", "compared", "identical", "different", "recorded_only",
             "replayed_only")]
    rows.append(("replay ms per profile", f"{report['replay_ms_per_profile']:.3f}"))
    print(table(("replay of " + report["profile_topic"], "value"), rows))
    if report["rejected"]:
        print("rejected by the replay: " + "; ".join(f"{k} ({v})" for k, v in report["rejected"].items()))
    if report["different"]:
        p, r = report["difference_position_um"], report["difference_rotation_urad"]
        print(f"replayed vs recorded: position median {p['median']:.3f} max {p['max']:.3f} um, "
              f"rotation median {r['median']:.3f} max {r['max']:.3f} urad")
    for name in ("recorded", "replayed"):
        if f"{name}_error_position_um" in report:
            p, r = report[f"{name}_error_position_um"], report[f"{name}_error_rotation_urad"]
            if p.get("n"):
                print(f"{name:>8} vs truth: position median {p['median']:.2f} p99 {p['p99']:.2f} um, "
                      f"rotation median {r['median']:.2f} p99 {r['p99']:.2f} urad ({p['n']} poses)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", help="bag directory with the profile topic (and the recorded poses)")
    parser.add_argument("--params-file", help="pose_estimator parameters (ROS 2 YAML) the replay uses")
    parser.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="override one pose_estimator parameter (repeatable)")
    parser.add_argument("--namespace", default="", help="namespace of the node block in the params file")
    parser.add_argument("--profile-topic", help="default: the bag's only PointCloud2 topic")
    parser.add_argument("--output", help="write the re-estimated poses to this new bag")
    parser.add_argument("--expect-identical", action="store_true",
                        help="exit 1 unless every recorded pose is reproduced bit for bit")
    args = parser.parse_args(argv)
    try:
        values = estimator_values(args.params_file, parse_overrides(args.param), args.namespace)
        report = replay(args.bag, values, args.profile_topic, args.output)
    except (BagError, ValueError, OSError) as exc:
        print(f"profile_pose replay: {exc}", file=sys.stderr)
        return 2
    print_report(report)
    if args.expect_identical and (report["different"] or report["recorded_only"] or not report["identical"]):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
