"""The controller-side C codec (firmware/motoplus) agrees with the Python codec: the shared vectors are
current and pass, and through ctypes, random frames and mutated streams come out the same on both sides."""
from __future__ import annotations

import ctypes
import shutil
import struct
import subprocess
import zlib

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from conftest import ROOT
from profile_pose_ros.core import motoplus_protocol as mp
from profile_pose_ros.tools import motoplus_vectors
from test_motoplus_protocol import BODIES, U32

SOURCE = ROOT / "firmware" / "motoplus"
STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2"]
needs_cc = pytest.mark.skipif(not shutil.which("cc"), reason="no C compiler")
ERROR_NAMES = ["ok", *mp.RULES, "capacity"]  # enum mpcl_error, negated


def test_the_vectors_file_is_what_the_python_codec_writes() -> None:
    committed = (SOURCE / "vectors.txt").read_text().splitlines()
    assert committed == motoplus_vectors.lines(), \
        "regenerate: python -m profile_pose_ros.tools.motoplus_vectors > firmware/motoplus/vectors.txt"
    kinds = [line.split()[0] for line in committed if line and not line.startswith("#")]
    errors = {line.split()[1] for line in committed if line.startswith("error ")}
    assert kinds.count("stream") > 60 and kinds.count("frame") > 60
    assert errors == set(mp.RULES) - {"short"}  # every rule a stream can break ("short": decode() alone)


def _sanitizers_work(tmp_path) -> list[str]:
    flags = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    probe = tmp_path / "probe.c"
    probe.write_text("int main(void) { return 0; }\n")
    ok = subprocess.run(["cc", *flags, str(probe), "-o", str(tmp_path / "probe")], capture_output=True).returncode == 0
    return flags if ok else []


@needs_cc
@pytest.mark.skipif(not shutil.which("make"), reason="no make")
def test_the_c_codec_passes_the_shared_vectors_and_a_wrong_vector_fails_it(tmp_path) -> None:
    work = tmp_path / "motoplus"
    shutil.copytree(SOURCE, work, ignore=shutil.ignore_patterns("mpcl_selftest"))
    flags = " ".join(STRICT + _sanitizers_work(tmp_path))
    result = subprocess.run(["make", "check", f"CFLAGS={flags}"], cwd=work, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 failure(s)" in result.stdout and "77 streams" in result.stdout

    text = (work / "vectors.txt").read_text()
    for wrong in (text.replace("\nerror checksum\n", "\nerror magic\n", 1),       # another rule
                  text.replace("frame 2 3 8 12 -7 0", "frame 2 3 8 12 -8 0", 1),  # another field value
                  text.replace("sequence 5 10 gap", "sequence 5 10 new", 1)):
        assert wrong != text
        (work / "wrong.txt").write_text(wrong)
        run = subprocess.run(["./mpcl_selftest", "wrong.txt"], cwd=work, capture_output=True, text=True, timeout=60)
        assert run.returncode == 1 and "1 failure(s)" in run.stdout, run.stdout + run.stderr


@pytest.fixture(scope="module")
def c_codec(tmp_path_factory):
    if not shutil.which("cc"):
        pytest.skip("no C compiler")
    library = tmp_path_factory.mktemp("mpcl") / "libmpcl.so"
    subprocess.run(["cc", *STRICT, "-shared", "-fPIC", "-DMPCL_SELFTEST_NO_MAIN", "-o", str(library),
                    str(SOURCE / "mpcl.c"), str(SOURCE / "mpcl_selftest.c")], check=True, timeout=120)
    lib = ctypes.CDLL(str(library))
    lib.mpcl_test_stream.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_size_t,
                                     ctypes.POINTER(ctypes.c_int64), ctypes.c_size_t, ctypes.POINTER(ctypes.c_int)]
    lib.mpcl_test_encode.argtypes = [ctypes.POINTER(ctypes.c_int64), ctypes.c_size_t, ctypes.c_char_p,
                                     ctypes.c_size_t]
    lib.mpcl_error_name.restype = ctypes.c_char_p
    return lib


def c_read(lib, stream: bytes, chunk: int) -> tuple[list[list[int]], str | None]:
    """The C reader's frames (flattened) and the rule that ended the stream (None: it did not fail)."""
    out, error = (ctypes.c_int64 * 8192)(), ctypes.c_int()
    written = lib.mpcl_test_stream(stream, len(stream), chunk, out, len(out), ctypes.byref(error))
    assert written >= 0
    frames, k = [], 0
    while k < written:
        frames.append([int(v) for v in out[k + 1:k + 1 + out[k]]])
        k += 1 + out[k]
    name = lib.mpcl_error_name(error.value).decode()
    assert name == ERROR_NAMES[-error.value]
    return frames, None if name == "ok" else name


def as_c_flattens(frame: mp.Frame) -> list[int]:
    """motoplus_vectors.flatten as the C side writes it: a u64 time past 2^63 wraps in an int64."""
    values = motoplus_vectors.flatten(frame)
    if isinstance(frame.body, mp.State) and values[-1] >= 2 ** 63:
        values[-1] -= 2 ** 64
    return values


def same_frame(c_values: list[int], frame: mp.Frame) -> bool:
    if isinstance(frame.body, mp.Fault):  # Python keeps the text decoded, invalid UTF-8 replaced
        raw = bytes(c_values[5:])
        return (c_values[:4] == as_c_flattens(frame)[:4] and c_values[4] == len(raw)
                and raw.decode("utf-8", "replace") == frame.body.text)
    return c_values == as_c_flattens(frame)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(U32, U32, BODIES), min_size=1, max_size=4), st.integers(1, 40))
def test_frames_encoded_by_either_side_decode_the_same_on_the_other(c_codec, frames, chunk) -> None:
    frames = [mp.Frame(seq, ack, body) for seq, ack, body in frames]
    stream = b"".join(mp.encode(f) for f in frames)
    decoded, error = c_read(c_codec, stream, chunk)
    assert error is None and len(decoded) == len(frames)
    assert all(same_frame(c, f) for c, f in zip(decoded, frames))
    for frame in frames:
        values = as_c_flattens(frame)
        out = ctypes.create_string_buffer(2048)
        n = c_codec.mpcl_test_encode((ctypes.c_int64 * len(values))(*values), len(values), out, len(out))
        assert out.raw[:n] == mp.encode(frame)


def python_read(stream: bytes) -> tuple[list[mp.Frame], str | None]:
    reader, frames = mp.FrameReader(), []
    try:
        for i in range(len(stream)):  # byte by byte: the frames before an error count too
            frames += reader.feed(stream[i:i + 1])
    except mp.MotoPlusProtocolError as exc:
        return frames, exc.rule
    return frames, None


FLIPS = st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), max_size=3)


@settings(max_examples=500, deadline=None)
@given(st.tuples(U32, U32, BODIES), FLIPS, FLIPS, st.integers(-8, 8), st.booleans(), st.binary(max_size=8),
       st.integers(1, 40))
def test_a_mutated_stream_ends_with_the_same_frames_and_rule_on_both_sides(c_codec, first, flips, payload_flips,
                                                                           resize, reseal, tail, chunk) -> None:
    """A damaged frame, then a good one, then a few stray bytes; the damage: bytes changed anywhere and in
    the payload, the payload cut or padded, and usually a valid checksum around it all (a peer's bug
    rather than line noise), so that the deeper rules (type, size, frame, limits, text) are reached."""
    good = mp.encode(mp.Frame(*first))
    inner = bytearray(good[4:-4])
    for position, value in flips:
        inner[position % len(inner)] = value
    for position, value in payload_flips:
        if len(inner) > mp.HEADER.size:
            inner[mp.HEADER.size + position % (len(inner) - mp.HEADER.size)] = value
    inner = inner[:len(inner) + resize] if resize < 0 else inner + bytes(resize)
    inner += struct.pack("<I", zlib.crc32(inner)) if reseal or resize else good[-4:]
    stream = struct.pack("<I", len(inner)) + bytes(inner) + good + tail
    expected_frames, expected_rule = python_read(stream)
    frames, rule = c_read(c_codec, stream, chunk)
    event(f"ended with {rule}")  # --hypothesis-show-statistics: which rules the mutations reach
    assert rule == expected_rule
    assert len(frames) == len(expected_frames) and all(map(same_frame, frames, expected_frames))
