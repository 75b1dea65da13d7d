"""profile_pose fuzz: every decoder and parser of outside input against mutated and random input, and
decoded but absurd values through the nodes' own logic.

For each target, valid inputs are encoded, then mutated (bit flips, byte changes, insertions, deletions,
truncations, splices of two inputs) or replaced by random bytes; the target must either accept the input
or raise its documented error type. Anything else is counted as unexpected, with the first example. The
node targets (tools/node_fuzz.py) read each case as a pose or reference near a real one with parts pushed
to an edge, and count as unexpected any motion the raw values say must not happen.
Deterministic for a seed. CI runs a small budget (test/test_fuzz.py); the default is 100,000 per target.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np
import yaml

from ..core.wire import motoplus_protocol as mp
from ..core.model.gauge import Gauge, GaugeError
from ..core.wire.pose_cdr import (CdrFormatError, SerializedPosePair, decode_pose_with_covariance_cdr, decode_twist_cdr,
                                  encode_twist_cdr)
from ..core.wire.profile_cdr import decode_profile_cdr
from ..core.wire.profile_cloud import Field, ProfileFormatError, decode_profile, encode_profile
from ..core.wire.profiler_protocol import FrameDecoder, ProfilerProtocolError, encode_frame
from ..core.wire.trigger_protocol import TriggerLineError, format_trigger, parse_line
from ..resources import DEFAULT_GAUGE, config_path
from . import c_codec, node_fuzz
from .c_codec import same_outcome


@dataclass
class Target:
    name: str
    seeds: list[bytes]
    run: Callable[[bytes], object]
    expected: tuple[type[BaseException], ...]
    close: Callable[[], None] | None = None  # after its cases


def mutate(data: bytes, other: bytes, rng: np.random.Generator) -> bytes:
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 6))):
        kind = int(rng.integers(0, 7))
        i = int(rng.integers(0, len(buf) + 1))
        if kind == 0 and buf:  # flip a bit
            j = min(i, len(buf) - 1)
            buf[j] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1 and buf:  # any byte, including the interesting ones
            j = min(i, len(buf) - 1)
            buf[j] = int(rng.choice([0, 1, 0x7F, 0x80, 0xFF, int(rng.integers(0, 256))]))
        elif kind == 2:  # insert
            buf[i:i] = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
        elif kind == 3 and buf:  # delete
            del buf[i:i + int(rng.integers(1, 9))]
        elif kind == 4:  # truncate
            del buf[i:]
        elif kind == 5:  # splice with another input
            buf = buf[:i] + bytearray(other[int(rng.integers(0, len(other) + 1)):])
        else:  # a 32-bit field set to an edge value
            if len(buf) >= 4:
                j = min(i, len(buf) - 4)
                buf[j:j + 4] = int(rng.choice([0, 1, 2 ** 31 - 1, 2 ** 31, 2 ** 32 - 1])).to_bytes(4, "little")
    return bytes(buf)


def cases(target: Target, count: int, rng: np.random.Generator):
    for k in range(count):
        if k % 10 == 9:
            yield rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        else:
            a = target.seeds[int(rng.integers(0, len(target.seeds)))]
            b = target.seeds[int(rng.integers(0, len(target.seeds)))]
            yield mutate(a, b, rng)


def _profiler_frames(data: bytes) -> None:
    """The decoder returns its errors in the stream (it must never raise); the first one counts as a rejection."""
    decoder = FrameDecoder()
    for item in decoder.feed(data):
        if isinstance(item, ProfilerProtocolError):
            raise item


def _motoplus(data: bytes) -> None:
    mp.FrameReader().feed(data)


def _trigger_lines(data: bytes) -> None:
    for line in data.split(b"\n"):
        parse_line(line)


CLOUD_HEADER = 6  # bytes of (point_step, row_step delta, flags) that the fuzzer may change


def _point_cloud(data: bytes) -> None:
    """The first bytes choose the metadata a malformed PointCloud2 may carry; the rest is its data."""
    if len(data) < CLOUD_HEADER:
        raise ProfileFormatError("too short to be a cloud")
    point_step, width_delta, flags, field_mask, datatype, offset_shift = data[:CLOUD_HEADER]
    payload = data[CLOUD_HEADER:]
    fields = [Field(name, off + (offset_shift % 8 if i == 2 else 0), datatype % 9 if i == 1 else 7, 1)
              for i, (name, off) in enumerate((("x", 0), ("y", 4), ("z", 8))) if field_mask & (1 << i)]
    width = max(0, len(payload) // max(point_step, 1) + (width_delta % 3) - 1)
    decode_profile(width=width, height=1 + (flags & 1), fields=fields, is_bigendian=bool(flags & 2),
                   point_step=point_step, row_step=width * point_step + (flags >> 4) % 2, data=payload)


def _serialized_clouds(points: np.ndarray) -> list[bytes]:
    """Profiles as the estimator node takes them from the topic: rclpy's serialization, with and without
    intensity, two frame names."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import PointCloud2

    from ..nodes.messages import cloud_from_points

    stamp = PointCloud2().header.stamp
    return [serialize_message(cloud_from_points(points, stamp, frame, intensity))
            for frame, intensity in (("profiler", None), ("cell_2/profiler", np.ones(len(points))))]


def _serialized_poses() -> list[bytes]:
    """Poses as the compensator takes them (the estimator's bytes), two frame names."""
    out = []
    for frame in ("gauge", "cell_2/gauge"):
        pair = SerializedPosePair()
        pair.fill(np.eye(3), np.array([0.01, -0.02, 0.4]), np.diag([1e-10] * 3 + [1e-8] * 3), 1, 2, frame)
        out.append(pair.with_covariance)
    return out


def _gauge_yaml(data: bytes) -> None:
    try:
        document = yaml.safe_load(data.decode("utf-8"))
    except (UnicodeDecodeError, yaml.YAMLError) as exc:
        raise GaugeError(f"not YAML: {exc}") from None
    Gauge.from_dict(document, "<fuzz>")


def _parameter_updates(data: bytes) -> None:
    """Parameter values as a node's set-parameters callback would get them: numbers of any size."""
    from ..core.control.compensator import Gains

    values = np.frombuffer(data[: len(data) // 8 * 8], dtype="<f8")
    chunks = [tuple(float(v) for v in values[i:i + 6]) for i in range(0, len(values), 6)] or [()]
    Gains(chunks[0], chunks[min(1, len(chunks) - 1)], chunks[-1]).check()


def _motoplus_c(codec) -> Callable[[bytes], None]:
    """The controller's C codec against the Python one: the same frames and the same rule, or unexpected.
    The first byte's low bit asks for the first frame to be resealed (a valid checksum over whatever the
    mutations left), without which nearly every mutation stops at the checksum and the deeper checks
    (magic, version, type, sizes, frame, limits, text) would never be compared."""

    def run(data: bytes) -> None:
        stream = bytearray(data[1:])
        if data[:1] and data[0] & 1 and len(stream) >= 4:
            length = int.from_bytes(stream[:4], "little")
            if 4 <= length <= len(stream) - 4:
                stream[length:length + 4] = zlib.crc32(stream[4:length]).to_bytes(4, "little")
        rule = same_outcome(codec, bytes(stream))
        if rule is not None:
            raise mp.MotoPlusProtocolError(f"both refuse it ({rule})", rule)
    return run


def targets() -> list[Target]:
    rng = np.random.default_rng(0)
    z = rng.uniform(0.3, 0.6, 64)
    z[::7] = np.nan
    profiler = [encode_frame(k, 1000 * k, -0.12, 75e-6, z[: 8 * k]) for k in range(1, 5)]
    motoplus = [mp.encode(mp.Frame(k, k - 1, body)) for k, body in enumerate([
        mp.Hello(12000, (100,) * 6, (5000,) * 6, 500), mp.Correction((1, -2, 3, 0, 0, 4)),
        mp.State(3, (1,) * 6, (2,) * 6, 5, 0, 99), mp.Heartbeat(), mp.Stop(), mp.Fault(3, "limit")], start=1)]
    lines = [format_trigger(12, 4000000000), b"PONG 77\n", b"OK ARM\n", b"READY trigger_mcu 1\n", b"E what\n"]
    points = np.column_stack([np.linspace(-0.1, 0.1, 20), rng.uniform(0.3, 0.5, 20)])
    cloud = [bytes([12, 1, 0, 7, 7, 0]) + encode_profile(points)[2]]
    serialized = _serialized_clouds(points)
    gauge = [config_path(DEFAULT_GAUGE).read_bytes()]
    params = [np.array([4.0] * 6 + [0.2] * 6 + [0.05] * 6).tobytes()]
    return [
        Target("profiler frames", profiler, _profiler_frames, (ProfilerProtocolError,)),
        Target("MotoPlus frames", motoplus, _motoplus, (mp.MotoPlusProtocolError,)),
        Target("trigger-MCU lines", lines, _trigger_lines, (TriggerLineError,)),
        Target("PointCloud2 profiles", cloud, _point_cloud, (ProfileFormatError,)),
        Target("serialized PointCloud2 profiles", serialized, decode_profile_cdr, (ProfileFormatError,)),
        Target("serialized poses (pd_compensator)", _serialized_poses(), decode_pose_with_covariance_cdr,
               (CdrFormatError,)),
        Target("serialized corrections (motoplus_bridge)",
               [encode_twist_cdr([1e-3, 0, -2e-3, 0, 0, 1e-2], 5_000_000_007, frame) for frame in ("base", "")],
               decode_twist_cdr, (CdrFormatError,)),
        Target("gauge files", gauge, _gauge_yaml, (GaugeError,)),
        Target("parameter updates", params, _parameter_updates, (ValueError,)),
    ] + _c_targets(motoplus) + _node_targets()


def _node_targets() -> list[Target]:
    """Decoded values through pd_compensator and motoplus_bridge themselves (tools/node_fuzz.py), when
    rclpy is importable; the nodes are made at the first case."""
    if importlib.util.find_spec("rclpy") is None:
        return []
    chain: list[node_fuzz.NodeChain] = []

    def with_chain(case: Callable[[node_fuzz.NodeChain, bytes], None]) -> Callable[[bytes], None]:
        def run(data: bytes) -> None:
            if not chain:
                chain.append(node_fuzz.NodeChain())
            case(chain[0], data)
        return run

    def close() -> None:
        if chain:
            chain.pop().close()

    seeds = node_fuzz.pose_seeds()
    return [Target("poses through pd_compensator and motoplus_bridge", seeds,
                   with_chain(node_fuzz.NodeChain.pose_case), (node_fuzz.Refused,)),
            Target("references through pd_compensator", seeds, with_chain(node_fuzz.NodeChain.reference_case),
                   (node_fuzz.Refused,)),
            Target("corrections through motoplus_bridge", seeds, with_chain(node_fuzz.NodeChain.correction_case),
                   (node_fuzz.Refused,), close)]


def _c_targets(motoplus: list[bytes]) -> list[Target]:
    """The controller-side C codec (firmware/motoplus) when there is a compiler and a source checkout."""
    if not c_codec.available():
        return []
    seeds = [bytes([flag]) + frame for frame in motoplus for flag in (0, 1)]
    return [Target("MotoPlus frames, C codec = Python", seeds, _motoplus_c(c_codec.CCodec()),
                   (mp.MotoPlusProtocolError,))]


def fuzz(count: int, seed: int = 1, names: list[str] | None = None) -> list[dict]:
    results = []
    for target in targets():
        if names and target.name not in names:
            continue
        rng = np.random.default_rng(seed)
        accepted = rejected = 0
        unexpected: list[str] = []
        start = time.perf_counter()
        for data in cases(target, count, rng):
            try:
                target.run(data)
                accepted += 1
            except target.expected:
                rejected += 1
            except Exception as exc:  # noqa: BLE001 - this is what the fuzzer is looking for
                if len(unexpected) < 3:
                    unexpected.append(f"{exc!r} for {data[:64]!r}")
        if target.close is not None:
            target.close()
        results.append({"target": target.name, "cases": count, "accepted": accepted, "rejected": rejected,
                        "unexpected": count - accepted - rejected, "examples": unexpected,
                        "seconds": time.perf_counter() - start})
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=100_000, help="cases per target")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    results = fuzz(args.cases, args.seed)
    width = max(len(r["target"]) for r in results)
    print(f"{'target':{width}}  {'cases':>8}  {'accepted':>8}  {'rejected':>8}  {'unexpected':>10}  seconds")
    for r in results:
        print(f"{r['target']:{width}}  {r['cases']:8d}  {r['accepted']:8d}  {r['rejected']:8d}  "
              f"{r['unexpected']:10d}  {r['seconds']:7.1f}")
        for example in r["examples"]:
            print(f"    {example}")
    return 1 if any(r["unexpected"] for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
