"""A profile read straight from its serialized PointCloud2 (the estimator node's and replay's path): the
same stamp, frame and points as rclpy's own deserialization, and every malformed message rejected with
ProfileFormatError and nothing else."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2, PointField

from profile_pose_ros.core.wire.profile_cdr import decode_profile_cdr, encode_profile_cdr
from profile_pose_ros.core.wire.profile_cloud import ProfileFormatError
from profile_pose_ros.nodes.messages import cloud_from_points, points_from_cloud


def cloud(frame_id="profiler", intensity=False, n=50):
    x = np.linspace(-0.05, 0.05, n)
    points = np.column_stack([x, 0.4 + 0.1 * np.abs(x)])
    points[3] = np.nan
    msg = cloud_from_points(points, PointCloud2().header.stamp, frame_id, np.ones(n) if intensity else None)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_796_000_123, 456_789_012
    return msg


@pytest.mark.parametrize("frame_id", ["profiler", "", "cell_2/profiler_äß"])
@pytest.mark.parametrize("intensity", [False, True])
def test_reads_what_rclpy_serialized(frame_id, intensity):
    msg = cloud(frame_id, intensity)
    profile = decode_profile_cdr(serialize_message(msg))
    assert (profile.stamp_sec, profile.stamp_nanosec, profile.frame_id) == (1_796_000_123, 456_789_012, frame_id)
    assert profile.stamp_ns == 1_796_000_123_456_789_012
    assert profile.points.tobytes() == points_from_cloud(msg).tobytes()


def _padding_free(data: bytes) -> bytes:
    """rclpy leaves CDR alignment padding as whatever was in memory: re-serialized by another library
    (rosbags, which writes padding as zeros) every field stays and only the padding changes."""
    from profile_pose_ros.bags.reader import typestore

    store = typestore()
    return bytes(store.serialize_cdr(store.deserialize_cdr(data, "sensor_msgs/msg/PointCloud2"),
                                     "sensor_msgs/msg/PointCloud2"))


@pytest.mark.parametrize("frame_id", ["profiler", "", "p", "cell_2/profiler_äß"])
@pytest.mark.parametrize("intensity", [False, True])
@pytest.mark.parametrize("n", [0, 7, 3200])
def test_the_driver_publishes_what_rclpy_would_serialize(frame_id, intensity, n):
    msg = cloud(frame_id, intensity, n) if n > 3 else cloud_from_points(
        np.zeros((n, 2)), PointCloud2().header.stamp, frame_id, np.ones(n) if intensity else None)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_796_000_123, 456_789_012
    ours = encode_profile_cdr(points_from_cloud(msg) if n else np.zeros((0, 2)), 1_796_000_123, 456_789_012,
                              frame_id, np.ones(n) if intensity else None)
    theirs = serialize_message(msg)
    assert len(ours) == len(theirs)
    assert ours == _padding_free(theirs)  # every field the same; padding zero in ours
    assert _padding_free(ours) == ours
    if n:
        assert decode_profile_cdr(ours).points.tobytes() == points_from_cloud(msg).tobytes()


def test_field_layout_is_read_not_assumed():
    """z before x, an extra field in front: the offsets come from the message."""
    msg = cloud()
    table = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(-1, 3)
    swapped = np.column_stack([np.full(len(table), 7.0, dtype="<f4"), table[:, 2], table[:, 0]])
    msg.fields = [PointField(name=name, offset=4 * k, datatype=7, count=1) for k, name in enumerate(["pad", "z", "x"])]
    msg.data = swapped.tobytes()
    assert decode_profile_cdr(serialize_message(msg)).points.tobytes() == points_from_cloud(cloud()).tobytes()


def test_every_truncation_and_trailing_garbage_is_rejected():
    data = serialize_message(cloud(n=8))
    for end in range(len(data) - 4):  # up to 3 bytes of alignment padding may end a message
        with pytest.raises(ProfileFormatError):
            decode_profile_cdr(data[:end])
    with pytest.raises(ProfileFormatError, match="after the end"):
        decode_profile_cdr(data + b"\x00" * 8)
    with pytest.raises(ProfileFormatError, match="little-endian CDR"):
        decode_profile_cdr(b"\x00\x00" + data[2:])


def test_profile_checks_still_apply():
    msg = cloud()
    msg.height = 2
    with pytest.raises(ProfileFormatError, match="height is 2"):
        decode_profile_cdr(serialize_message(msg))


@settings(max_examples=400, deadline=None)
@given(st.data())
def test_mutated_messages_raise_only_profile_format_error(data):
    original = bytearray(serialize_message(cloud(n=6)))
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(original) - 1))
        original[i] = data.draw(st.sampled_from([0, 1, 0x7F, 0x80, 0xFF, data.draw(st.integers(0, 255))]))
    try:
        profile = decode_profile_cdr(bytes(original))
    except ProfileFormatError:
        return
    assert profile.points.ndim == 2 and profile.points.shape[1] == 2


def _outcome(data: bytes):
    try:
        profile = decode_profile_cdr(data)
    except ProfileFormatError as exc:
        return "error", str(exc)
    return profile.stamp_ns, profile.frame_id, profile.points.tobytes()


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_a_layout_remembered_from_the_last_profile_reads_as_a_fresh_parse(data):
    """decode_profile_cdr skips re-reading a layout it has just read: whatever follows a good profile
    (another layout, a changed field, padding, truncation, trailing bytes) must read exactly as if nothing
    had been remembered."""
    import profile_pose_ros.core.wire.profile_cdr as module

    good = serialize_message(cloud(data.draw(st.sampled_from(["profiler", "p", ""])), data.draw(st.booleans())))
    message = bytearray(good)
    for _ in range(data.draw(st.integers(0, 3))):
        at = data.draw(st.integers(0, len(message) - 1))
        message[at] = data.draw(st.integers(0, 255))
    cut = data.draw(st.sampled_from([None, len(message) - 1, len(message) - 4, len(message) // 2, 40]))
    message = bytes(message[:cut]) + data.draw(st.sampled_from([b"", b"\x00", b"\x00" * 4]))
    module._last_layout = None
    fresh = _outcome(message)
    decode_profile_cdr(good)  # remembered
    assert _outcome(message) == fresh


def test_padding_does_not_hide_a_known_layout(monkeypatch):
    """rclpy's padding bytes differ from message to message: a layout is recognised without them."""
    import profile_pose_ros.core.wire.profile_cdr as module

    first, second = serialize_message(cloud()), bytearray(serialize_message(cloud()))
    decode_profile_cdr(first)
    reads = []
    monkeypatch.setattr(module, "_read_layout", lambda d, read=module._read_layout: reads.append(1) or read(d))
    pieces = module._last_layout.pieces
    covered = {at for start, piece in pieces for at in range(start, start + len(piece))}
    padding = [at for at in range(12, module._last_layout.table_start) if at not in covered]
    assert padding  # frame_id, each field name, each field's datatype and is_bigendian are padded
    for at in padding:
        second[at] ^= 0xA5
    assert decode_profile_cdr(bytes(second)).points.tobytes() == decode_profile_cdr(first).points.tobytes()
    assert reads == []
