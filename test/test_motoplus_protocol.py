"""The MotoPlus protocol codec: every field round-trips, every malformed frame is rejected, fuzzing."""
from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from profile_pose_ros.core.wire import motoplus_protocol as mp

I32 = st.integers(-2 ** 31, 2 ** 31 - 1)
U32 = st.integers(0, 2 ** 32 - 1)
SIX = st.tuples(I32, I32, I32, I32, I32, I32)
NONNEG_SIX = st.tuples(*(st.integers(0, 2 ** 31 - 1),) * 6)
FRAMES = st.sampled_from([mp.FRAME_BASE, mp.FRAME_ROBOT, mp.FRAME_TOOL, mp.FRAME_USER])
BYTE = st.integers(0, 255)

BODIES = st.one_of(
    st.builds(mp.Hello, st.integers(1, 2 ** 32 - 1), NONNEG_SIX, NONNEG_SIX, U32, FRAMES, BYTE, BYTE),
    st.builds(mp.Correction, SIX, FRAMES, BYTE, BYTE),
    st.builds(mp.State, U32, SIX, SIX, U32, U32, st.integers(0, 2 ** 64 - 1)),
    st.just(mp.Heartbeat()), st.just(mp.Stop()),
    st.builds(mp.Fault, U32, st.text(max_size=50)),
)


@settings(max_examples=300, deadline=None)
@given(U32, U32, BODIES)
def test_every_field_round_trips(seq: int, ack: int, body) -> None:
    frame = mp.Frame(seq, ack, body)
    data = mp.encode(frame)
    assert mp.FrameReader().feed(data) == [frame]


def test_a_stream_in_pieces_gives_frames_in_order() -> None:
    frames = [mp.Frame(k, k - 1, mp.Correction((k, -k, 0, 0, 0, 1))) for k in range(1, 20)]
    data = b"".join(mp.encode(f) for f in frames)
    reader, out = mp.FrameReader(), []
    for i in range(0, len(data), 7):
        out += reader.feed(data[i:i + 7])
    assert out == frames


def good() -> bytes:
    return mp.encode(mp.Frame(5, 4, mp.Correction((1, 2, 3, 4, 5, 6))))


def resealed(inner: bytes) -> bytes:
    """A frame with a valid length and checksum around `inner` (a peer's bug, not line noise)."""
    body = inner + struct.pack("<I", zlib.crc32(inner))
    return struct.pack("<I", len(body)) + body


HEADER = mp.HEADER.size


@pytest.mark.parametrize("data, reason", [
    (struct.pack("<I", 3) + b"abc", "length 3 out of range"),
    (struct.pack("<I", 5000) + bytes(20), "length 5000 out of range"),
    (good()[:-1] + bytes([good()[-1] ^ 1]), "checksum"),
    (good()[:12] + bytes([good()[12] ^ 0x40]) + good()[13:], "checksum"),
    (resealed(b"XXXX" + good()[8:-4]), "bad magic"),
    (resealed(good()[4:8] + bytes([2]) + good()[9:-4]), "version 2"),
    (resealed(good()[4:9] + bytes([9]) + good()[10:-4]), "unknown frame type 9"),
    (resealed(good()[4:-8]), "CORRECTION: payload"),
    (resealed(good()[4:-4] + b"\x00"), "CORRECTION: payload"),
    (resealed(mp.encode(mp.Frame(1, 0, mp.Heartbeat()))[4:-4] + b"\x01"), "carries no payload"),
    (resealed(mp.encode(mp.Frame(1, 0, mp.Fault(3, "abc")))[4:-5]), "text length"),
])
def test_each_malformed_frame_is_rejected_with_its_reason(data: bytes, reason: str) -> None:
    reader = mp.FrameReader()
    with pytest.raises(mp.MotoPlusProtocolError, match=reason):
        reader.feed(data)
    with pytest.raises(mp.MotoPlusProtocolError):  # and the reader stays failed: drop the connection
        reader.feed(good())


def test_unknown_increment_frame_and_negative_limits_are_rejected() -> None:
    correction = bytearray(mp.encode(mp.Frame(1, 0, mp.Correction((0,) * 6))))
    correction[4 + HEADER + 24] = 9  # the frame byte
    with pytest.raises(mp.MotoPlusProtocolError, match="unknown frame 9"):
        mp.FrameReader().feed(resealed(bytes(correction[4:-4])))
    hello = mp.encode(mp.Frame(1, 0, mp.Hello(12000, (-1, 0, 0, 0, 0, 0), (0,) * 6, 500)))
    with pytest.raises(mp.MotoPlusProtocolError, match="positive"):
        mp.FrameReader().feed(hello)


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_reader_yields_frames_or_the_documented_error(data: bytes) -> None:
    try:
        for frame in mp.FrameReader().feed(data):
            assert isinstance(frame, mp.Frame)
    except mp.MotoPlusProtocolError:
        pass


@settings(max_examples=300, deadline=None)
@given(SIX, NONNEG_SIX)
def test_clamp_never_exceeds_the_limit(increment, limits) -> None:
    clamped, cut = mp.clamp(increment, limits)
    assert all(abs(c) <= lim for c, lim in zip(clamped, limits))
    assert cut == (clamped != tuple(increment))


def test_units() -> None:
    assert mp.metres_to_units([1e-3, -2e-6, 0.0, 3.141592653589793 / 180, 0.0, 0.0]) == (1000, -2, 0, 10000, 0, 0)
    assert mp.units_to_metres((1000, 0, 0, 10000, 0, 0))[0] == pytest.approx(1e-3)


def test_carried_rounding_sends_the_sum_asked_for_within_half_a_unit() -> None:
    rounding = mp.CarriedRounding()
    asked = np.array([0.4e-6, -0.7e-6, 2.5e-6, 1e-7, 0.0, -3e-6])  # m, rad per period
    scale = np.array([mp.UM_PER_M] * 3 + [mp.TENTH_MILLIDEG_PER_RAD] * 3)
    sent = np.zeros(6)
    for k in range(1, 101):
        sent += rounding(asked)
        assert np.all(np.abs(sent - k * asked * scale) <= 0.5 + 1e-9)
    assert sent[0] == 40 and mp.metres_to_units(asked)[0] == 0  # one by one, 0.4 um would never move
    rounding.reset()
    assert rounding([0.4e-6] + [0.0] * 5) == (0,) * 6
    with pytest.raises(mp.MotoPlusProtocolError):
        rounding([0.0] * 5)


def test_sequence_rule_ignores_old_frames_and_faults_after_three_missing() -> None:
    assert [mp.sequence_verdict(5, seq) for seq in (4, 5, 6, 9, 10)] == ["old", "old", "new", "new", "gap"]


def test_a_fault_text_over_200_bytes_is_refused_by_rule() -> None:
    inner = mp.encode(mp.Frame(1, 0, mp.Fault(2, "")))[4:-4 - 2] + struct.pack("<H", 201) + b"z" * 201
    with pytest.raises(mp.MotoPlusProtocolError, match="more than 200") as caught:
        mp.FrameReader().feed(resealed(inner))
    assert caught.value.rule == "text"
