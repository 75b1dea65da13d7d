"""The controller-side C codec (firmware/motoplus) agrees with the Python codec: the shared vectors are
current and pass, and through ctypes, random frames and mutated streams come out the same on both sides."""
from __future__ import annotations

import shutil
import struct
import subprocess
import zlib

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from profile_pose_ros.core.wire import motoplus_protocol as mp
from profile_pose_ros.sim.motoplus_app import STRICT, sanitizers
from profile_pose_ros.tools import motoplus_vectors
from profile_pose_ros.tools.c_codec import (ERROR_NAMES, SOURCE, CCodec, available, same_frame,
                                            same_outcome)
from test_motoplus_protocol import BODIES, U32

needs_cc = pytest.mark.skipif(not available(), reason="no C compiler or no firmware sources")


def test_the_vectors_file_is_what_the_python_codec_writes() -> None:
    committed = (SOURCE / "vectors.txt").read_text().splitlines()
    assert committed == motoplus_vectors.lines(), \
        "regenerate: python -m profile_pose_ros.tools.motoplus_vectors > firmware/motoplus/vectors.txt"
    kinds = [line.split()[0] for line in committed if line and not line.startswith("#")]
    errors = {line.split()[1] for line in committed if line.startswith("error ")}
    assert kinds.count("stream") > 60 and kinds.count("frame") > 60
    assert errors == set(mp.RULES) - {"short"}  # every rule a stream can break ("short": decode() alone)


@needs_cc
@pytest.mark.skipif(not shutil.which("make"), reason="no make")
def test_the_c_codec_passes_the_shared_vectors_and_a_wrong_vector_fails_it(tmp_path) -> None:
    work = tmp_path / "motoplus"
    shutil.copytree(SOURCE, work, ignore=shutil.ignore_patterns("mpcl_selftest"))
    flags = " ".join(STRICT + sanitizers(tmp_path))
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
def c_codec() -> CCodec:
    if not available():
        pytest.skip("no C compiler or no firmware sources")
    return CCodec()


def test_both_codecs_name_the_rules_alike(c_codec) -> None:
    assert [c_codec.lib.mpcl_error_name(-k).decode() for k in range(len(ERROR_NAMES))] == ERROR_NAMES


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(U32, U32, BODIES), min_size=1, max_size=4), st.integers(1, 40))
def test_frames_encoded_by_either_side_decode_the_same_on_the_other(c_codec, frames, chunk) -> None:
    frames = [mp.Frame(seq, ack, body) for seq, ack, body in frames]
    stream = b"".join(mp.encode(f) for f in frames)
    decoded, error = c_codec.read(stream, chunk)
    assert error is None and len(decoded) == len(frames)
    assert all(same_frame(c, f) for c, f in zip(decoded, frames))
    assert all(c_codec.encode(frame) == mp.encode(frame) for frame in frames)


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
    rule = same_outcome(c_codec, stream, chunk)  # raises when they differ
    event(f"ended with {rule}")  # --hypothesis-show-statistics: which rules the mutations reach
