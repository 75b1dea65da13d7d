"""The profiler frame codec: round trips, every malformed frame rejected, resynchronisation, fuzzing."""
from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from profile_pose_ros.core.wire.profiler_protocol import (CRC, HEADER, HEADER_SIZE, INVALID_Z, TYPE_HEARTBEAT, FrameDecoder,
                                                          ProfileFrame, ProfilerProtocolError, decode_frame, encode_frame,
                                                          z_counts)
from profile_pose_ros.sim.profiler_device import CORRUPT_MODES, corrupt

Z = np.array([0.4, np.nan, 0.41234567, -0.001, np.inf, 0.5])


def frame(trigger: int = 7, z: np.ndarray = Z) -> bytes:
    return encode_frame(trigger, 123456789, -0.11996, 75e-6, z)


def reheader(data: bytes, **changes) -> bytes:
    """A frame whose header says something else, with a valid header checksum (a device bug, not noise)."""
    fields = dict(zip(("magic", "version", "frame_type", "reserved", "trigger", "device_us", "n", "x0", "pitch"),
                      HEADER.unpack_from(data)))
    fields.update(changes)
    header = HEADER.pack(*fields.values())
    return header + CRC.pack(zlib.crc32(header)) + data[HEADER_SIZE:]


def test_round_trip_keeps_every_field() -> None:
    decoded = decode_frame(frame())
    assert (decoded.trigger_count, decoded.device_time_us) == (7, 123456789)
    assert (decoded.x_start, decoded.x_pitch) == (-0.11996, 75e-6)
    finite = np.isfinite(Z)
    np.testing.assert_allclose(decoded.z[finite], Z[finite], atol=0.5e-8)  # 0.01 um units
    assert np.all(np.isnan(decoded.z[~finite]))  # NaN and inf both travel as the invalid code
    np.testing.assert_allclose(decoded.points[:, 0], -0.11996 + 75e-6 * np.arange(len(Z)))


def test_heartbeat_and_wrapping_counters() -> None:
    beat = decode_frame(encode_frame(2 ** 32 + 5, 2 ** 64 + 9, 0.0, 1.0, None, frame_type=TYPE_HEARTBEAT))
    assert (beat.frame_type, beat.trigger_count, beat.device_time_us, len(beat.z)) == (TYPE_HEARTBEAT, 5, 9, 0)


def test_out_of_range_depths_become_invalid_not_wrapped() -> None:
    assert list(z_counts(np.array([30.0, -30.0, np.nan]))) == [INVALID_Z] * 3


@pytest.mark.parametrize("damage, reason", [
    (lambda f: f[:4] + bytes([2]) + f[5:], "header checksum"),
    (lambda f: f[:20] + (70000).to_bytes(4, "little") + f[24:], "header checksum"),
    (lambda f: reheader(f, version=2), "version"),
    (lambda f: reheader(f, frame_type=9), "frame type"),
    (lambda f: reheader(f, n=70000), "point count"),
    (lambda f: reheader(f, pitch=-1.0), "x grid"),
    (lambda f: f[:HEADER_SIZE] + bytes([f[HEADER_SIZE] ^ 1]) + f[HEADER_SIZE + 1:], "checksum"),
    (lambda f: f[:-1] + bytes([f[-1] ^ 0xFF]), "checksum"),
    (lambda f: b"xx" + f, "garbage"),
    (lambda f: f[:-3], "left over"),
    (lambda f: f + b"\x00", "left over"),
])
def test_each_malformed_frame_is_rejected_with_its_reason(damage, reason) -> None:
    with pytest.raises(ProfilerProtocolError, match=reason):
        decode_frame(damage(frame()))


@pytest.mark.parametrize("mode", CORRUPT_MODES)
def test_stream_resynchronises_after_each_kind_of_damage(mode) -> None:
    rng = np.random.default_rng(3)
    stream = frame(1) + corrupt(frame(2), mode, rng) + frame(3) + frame(4)
    decoder = FrameDecoder()
    out = []
    for k in range(0, len(stream), 37):  # TCP chunks at arbitrary boundaries
        out += decoder.feed(stream[k:k + 37])
    frames = [o.trigger_count for o in out if isinstance(o, ProfileFrame)]
    errors = [o for o in out if isinstance(o, ProfilerProtocolError)]
    assert {1, 3, 4} <= set(frames)
    assert (2 in frames) == (mode == "garbage")  # noise before an intact frame costs only the noise
    assert errors, "the damaged frame must be reported"


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=600), st.integers(1, 64))
def test_fuzz_decoder_only_yields_frames_and_documented_errors(data: bytes, chunk: int) -> None:
    decoder = FrameDecoder()
    for k in range(0, len(data), chunk):
        for item in decoder.feed(data[k:k + chunk]):
            assert isinstance(item, (ProfileFrame, ProfilerProtocolError))


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=1, max_size=64), st.integers(0, 400))
def test_fuzz_inserted_noise_never_costs_the_following_frames(noise: bytes, where: int) -> None:
    good = frame(10)
    damaged = good[:where] + noise + good[where:]
    out = FrameDecoder().feed(damaged + frame(11) + frame(12))
    frames = [o for o in out if isinstance(o, ProfileFrame)]
    assert [f.trigger_count for f in frames][-2:] == [11, 12]
    for f in frames:  # whatever decodes passed its checksum: it is one of the frames sent
        assert f.trigger_count in (10, 11, 12)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.integers(-(2 ** 31), 2 ** 31 - 1), st.integers(-(2 ** 31), -(2 ** 31) + 20)),
                max_size=400),
       st.floats(-0.2, 0.2), st.floats(1e-6, 1e-3))
def test_the_point_table_from_the_counts_is_the_table_from_the_points(counts: list[int], x_start: float,
                                                                       x_pitch: float) -> None:
    """The driver publishes ProfileFrame.xyz_table (straight from the device's counts, every invalid code
    included); it must be byte for byte the cloud the float64 points would give."""
    from profile_pose_ros.core.wire.profile_cdr import encode_profile_cdr, encode_xyz_table_cdr
    from profile_pose_ros.core.wire.profiler_protocol import ProfileFrame

    frame_ = ProfileFrame(1, 2, x_start, x_pitch, np.array(counts, dtype="<i4"))
    assert encode_xyz_table_cdr(frame_.xyz_table(), 17, 42, "profiler") == \
        encode_profile_cdr(frame_.points, 17, 42, "profiler")
