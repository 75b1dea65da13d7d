"""Test vectors for the MotoPlus protocol, generated from the Python codec: the shared specification the
controller-side C codec (firmware/motoplus) is checked against. `python -m
profile_pose_ros.tools.motoplus_vectors > firmware/motoplus/vectors.txt` regenerates the file; a test
checks that the committed one is what this writes, so the two cannot drift.

Format, one item per line (`#` starts a comment):
    stream <hex>                 bytes as they arrive on the TCP stream (length prefixes included)
    frame <int> ...              the next frame the stream must yield, flattened (see `flatten`)
    end | error <rule>           the stream ends cleanly, or with that rule's error (MotoPlusProtocolError.rule)
    sequence <last> <seq> <new|old|gap>
    clamp <increment x6> <limit x6> <clamped x6> <0|1>
"""
from __future__ import annotations

import random
import struct
import sys
import zlib

from ..core.wire import motoplus_protocol as mp

I32_MIN, I32_MAX, U32_MAX = -2 ** 31, 2 ** 31 - 1, 2 ** 32 - 1
_KINDS = {mp.Hello: mp.HELLO, mp.Correction: mp.CORRECTION, mp.State: mp.STATE, mp.Heartbeat: mp.HEARTBEAT,
          mp.Stop: mp.STOP, mp.Fault: mp.FAULT}


def flatten(frame: mp.Frame) -> list[int]:
    """type, seq, ack, then the body's fields in wire order (a FAULT: code, text length, the text's bytes)."""
    b = frame.body
    head = [_KINDS[type(b)], frame.seq, frame.ack]
    if isinstance(b, mp.Hello):
        return head + [b.period_us, *b.max_step, *b.max_offset, b.watchdog_ms, b.frame, b.tool, b.user_frame]
    if isinstance(b, mp.Correction):
        return head + [*b.increment, b.frame, b.tool, b.user_frame]
    if isinstance(b, mp.State):
        return head + [b.echoed_seq, *b.pose, *b.offset, b.status, b.error_code, b.time_us]
    if isinstance(b, mp.Fault):
        text = b.text.encode("utf-8")[:mp.MAX_FAULT_TEXT]
        return head + [b.code, len(text), *text]
    return head


def resealed(inner: bytes) -> bytes:
    """`inner` (magic to payload) with a valid checksum and length prefix: a peer's bug, not line noise."""
    body = inner + struct.pack("<I", zlib.crc32(inner))
    return struct.pack("<I", len(body)) + body


def _valid_frames(rng: random.Random) -> list[mp.Frame]:
    six = lambda low, high: tuple(rng.randint(low, high) for _ in range(6))  # noqa: E731
    frames = [
        mp.Frame(1, 0, mp.Hello(12000, (200, 200, 200, 1000, 1000, 1000), (20000,) * 3 + (50000,) * 3, 500)),
        mp.Frame(2, 7, mp.Hello(4000, (0,) * 6, (I32_MAX,) * 6, U32_MAX, mp.FRAME_USER, 255, 63)),
        mp.Frame(3, 8, mp.Correction((12, -7, 0, 3, -2, 1))),
        mp.Frame(U32_MAX, U32_MAX, mp.Correction((I32_MIN, I32_MAX, -1, 1, 0, I32_MIN), mp.FRAME_TOOL, 7, 2)),
        mp.Frame(9, 3, mp.State(3, (1_000_000, -250_000, 400_000, 1_800_000, -900_000, 0), (5, -5, 0, 0, 0, 1),
                                mp.ARMED | mp.MOVING, 0, 123_456_789)),
        mp.Frame(10, 4, mp.State(U32_MAX, (I32_MIN,) * 6, (I32_MAX,) * 6, U32_MAX, U32_MAX, 2 ** 64 - 1)),
        mp.Frame(11, 5, mp.Heartbeat()),
        mp.Frame(12, 6, mp.Stop()),
        mp.Frame(13, 6, mp.Fault(mp.FAULT_SEQUENCE_GAP, "")),
        mp.Frame(14, 6, mp.Fault(mp.FAULT_ALARM, "Übertemperatur Achse 2 (°C)")),
        mp.Frame(15, 6, mp.Fault(mp.FAULT_WATCHDOG, "x" * mp.MAX_FAULT_TEXT)),
    ]
    for _ in range(40):
        seq, ack = rng.randint(0, U32_MAX), rng.randint(0, U32_MAX)
        kind = rng.choice([mp.Hello, mp.Correction, mp.State, mp.Fault])
        if kind is mp.Hello:
            body = mp.Hello(rng.randint(1, U32_MAX), six(0, I32_MAX), six(0, I32_MAX), rng.randint(0, U32_MAX),
                            rng.randint(0, 3), rng.randint(0, 255), rng.randint(0, 255))
        elif kind is mp.Correction:
            body = mp.Correction(six(I32_MIN, I32_MAX), rng.randint(0, 3), rng.randint(0, 255), rng.randint(0, 255))
        elif kind is mp.State:
            body = mp.State(rng.randint(0, U32_MAX), six(I32_MIN, I32_MAX), six(I32_MIN, I32_MAX),
                            rng.randint(0, U32_MAX), rng.randint(0, U32_MAX), rng.randint(0, 2 ** 64 - 1))
        else:
            body = mp.Fault(rng.randint(0, U32_MAX), "".join(chr(rng.randint(32, 0x2FF)) for _ in range(rng.randint(0, 60))))
        frames.append(mp.Frame(seq, ack, body))
    return frames


def _malformed() -> list[tuple[str, bytes]]:
    """(what, stream) for every rule; the stream starts with a good frame, which must still come out."""
    good = mp.encode(mp.Frame(5, 4, mp.Correction((1, 2, 3, 4, 5, 6))))
    inner = good[4:-4]  # magic .. payload
    hello = mp.encode(mp.Frame(1, 0, mp.Hello(12000, (1,) * 6, (1,) * 6, 500)))[4:-4]
    state = mp.encode(mp.Frame(1, 0, mp.State(0, (0,) * 6)))[4:-4]
    fault = mp.encode(mp.Frame(1, 0, mp.Fault(3, "abc")))[4:-4]
    header = mp.HEADER.size

    def with_byte(data: bytes, index: int, value: int) -> bytes:
        return data[:index] + bytes([value]) + data[index + 1:]

    def fault_text(length: int, text: bytes) -> bytes:
        return resealed(inner[:5] + bytes([mp.FAULT]) + inner[6:header] + struct.pack("<IH", 3, length) + text)

    cases = [
        ("length", "prefix announces 3 bytes", struct.pack("<I", 3) + b"abc"),
        ("length", "prefix announces 19 bytes", struct.pack("<I", 19) + bytes(19)),
        ("length", "prefix announces 1025 bytes", struct.pack("<I", 1025) + bytes(1025)),
        ("checksum", "a payload bit flipped", good[:12] + bytes([good[12] ^ 0x40]) + good[13:]),
        ("checksum", "a checksum bit flipped", good[:-1] + bytes([good[-1] ^ 1])),
        ("magic", "magic XXXX", resealed(b"XXXX" + inner[4:])),
        ("version", "version 2", resealed(with_byte(inner, 4, 2))),
        ("version", "version 0", resealed(with_byte(inner, 4, 0))),
        ("type", "type 0", resealed(with_byte(inner, 5, 0))),
        ("type", "type 9", resealed(with_byte(inner, 5, 9))),
        ("size", "CORRECTION 4 bytes short", resealed(inner[:-4])),
        ("size", "CORRECTION 1 byte long", resealed(inner + b"\x00")),
        ("size", "HELLO 1 byte short", resealed(hello[:-1])),
        ("size", "STATE 1 byte long", resealed(state + b"\x00")),
        ("size", "HEARTBEAT with a payload", resealed(with_byte(inner, 5, mp.HEARTBEAT)[:header] + b"\x01")),
        ("size", "STOP with a payload", resealed(with_byte(inner, 5, mp.STOP))),
        ("size", "FAULT shorter than its code and length", resealed(fault[:header + 5])),
        ("text", "FAULT text shorter than its length", resealed(fault[:-1])),
        ("text", "FAULT text longer than its length", resealed(fault + b"d")),
        ("text", "FAULT text over 200 bytes", fault_text(201, b"y" * 201)),
        ("frame", "CORRECTION in frame 4", resealed(with_byte(inner, header + 24, 4))),
        ("frame", "HELLO in frame 255", resealed(with_byte(hello, header + 56, 255))),
        ("limits", "HELLO period 0", resealed(hello[:header] + bytes(4) + hello[header + 4:])),
        ("limits", "HELLO negative step", resealed(hello[:header + 8] + struct.pack("<i", -1) + hello[header + 12:])),
        ("limits", "HELLO negative offset", resealed(hello[:header + 28] + struct.pack("<i", I32_MIN)
                                                     + hello[header + 32:])),
    ]
    return [(rule, what, good + stream) for rule, what, stream in cases]


def python_read(stream: bytes) -> tuple[list[mp.Frame], str | None]:
    """The Python reader's frames and error rule (None: no error) for `stream`, fed byte by byte: frames
    before an error count, as they do in the C reader (FrameReader.feed raises before returning them)."""
    reader, frames = mp.FrameReader(), []
    try:
        for i in range(len(stream)):
            frames += reader.feed(stream[i:i + 1])
    except mp.MotoPlusProtocolError as exc:
        return frames, exc.rule
    return frames, None


def _stream_lines(title: str, stream: bytes, expected_error: str | None = None) -> list[str]:
    frames, error = python_read(stream)
    if error != expected_error:  # a vector that tests another rule than its title says is worthless
        raise AssertionError(f"{title}: the Python codec says {error}, expected {expected_error}")
    return [f"# {title}", f"stream {stream.hex()}", *(f"frame {' '.join(map(str, flatten(f)))}" for f in frames),
            f"error {error}" if error else "end"]


def lines(seed: int = 2026) -> list[str]:
    rng = random.Random(seed)
    out = ["# MotoPlus correction protocol test vectors (docs/motoplus_protocol.md), written by",
           "# python -m profile_pose_ros.tools.motoplus_vectors; format in that module's docstring."]
    frames = _valid_frames(rng)
    for frame in frames:
        out += _stream_lines(f"{type(frame.body).__name__} seq {frame.seq}", mp.encode(frame))
    out += _stream_lines("every kind of frame back to back", b"".join(mp.encode(f) for f in frames[:11]))
    for rule, what, stream in _malformed():
        out += _stream_lines(f"refused ({rule}): {what}", stream, rule)
    out.append("# sequence rule: a CORRECTION after <last>")
    for last, seq in [(0, 1), (5, 5), (5, 4), (5, 6), (5, 9), (5, 10), (U32_MAX - 1, U32_MAX), (0, U32_MAX)]:
        out.append(f"sequence {last} {seq} {mp.sequence_verdict(last, seq)}")
    out.append("# per-cycle clamp")
    for _ in range(12):
        limit = tuple(rng.choice([0, 1, 200, 1000, I32_MAX]) for _ in range(6))
        increment = tuple(rng.choice([0, 1, -1, 150, -250, 5000, I32_MIN, I32_MAX]) for _ in range(6))
        clamped, cut = mp.clamp(increment, limit)
        out.append(f"clamp {' '.join(map(str, increment + limit + clamped))} {int(cut)}")
    return out


def main(argv=None) -> int:
    sys.stdout.write("\n".join(lines()) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
