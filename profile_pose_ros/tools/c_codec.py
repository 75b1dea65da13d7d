"""The controller-side C codec (firmware/motoplus), built for this host and driven through ctypes, and
the Python codec's answer to the same bytes: the tests and profile_pose fuzz compare the two."""
from __future__ import annotations

import ctypes

from ..core.wire import motoplus_protocol as mp
from ..sim.motoplus_app import build, compiler, firmware_dir
from .motoplus_vectors import flatten, python_read

SOURCE = firmware_dir()  # a source checkout's, else the installed copy
ERROR_NAMES = ["ok", *mp.RULES, "capacity"]  # enum mpcl_error, negated


def available() -> bool:
    """A C compiler and the firmware's sources."""
    return compiler() is not None and (SOURCE / "mpcl.c").is_file()


class CCodec:
    def __init__(self) -> None:
        """mpcl.c and its self-test helpers as a shared library (strict C99, warnings are errors), built
        once per source version into the firmware build cache, and loaded."""
        library = build("libmpcl_selftest.so", ("mpcl.c", "mpcl_selftest.c"),
                        ("-shared", "-fPIC", "-DMPCL_SELFTEST_NO_MAIN"), source=SOURCE)
        self.lib = ctypes.CDLL(str(library))
        int64_p = ctypes.POINTER(ctypes.c_int64)
        self.lib.mpcl_test_stream.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_size_t, int64_p,
                                              ctypes.c_size_t, ctypes.POINTER(ctypes.c_int)]
        self.lib.mpcl_test_encode.argtypes = [int64_p, ctypes.c_size_t, ctypes.c_char_p, ctypes.c_size_t]
        self.lib.mpcl_error_name.restype = ctypes.c_char_p
        self._out = (ctypes.c_int64 * 65536)()

    def read(self, stream: bytes, chunk: int) -> tuple[list[list[int]], str | None]:
        """The C reader's frames (flattened) from `stream` fed `chunk` bytes at a time, and the rule that
        ended it (None: it did not fail)."""
        error = ctypes.c_int()
        written = self.lib.mpcl_test_stream(stream, len(stream), chunk, self._out, len(self._out),
                                            ctypes.byref(error))
        if written < 0:
            raise OverflowError("more frames than the output holds")
        values = self._out[:written]
        frames, k = [], 0
        while k < written:
            frames.append(values[k + 1:k + 1 + values[k]])
            k += 1 + values[k]
        name = self.lib.mpcl_error_name(error.value).decode()
        return frames, None if name == "ok" else name

    def encode(self, frame: mp.Frame) -> bytes:
        values = c_flattened(frame)
        out = ctypes.create_string_buffer(2048)
        n = self.lib.mpcl_test_encode((ctypes.c_int64 * len(values))(*values), len(values), out, len(out))
        if n < 0:
            raise ValueError(f"mpcl_encode: {self.lib.mpcl_error_name(n).decode()}")
        return out.raw[:n]


def c_flattened(frame: mp.Frame) -> list[int]:
    """motoplus_vectors.flatten as C's int64 values hold it: a u64 time past 2^63 wraps."""
    values = flatten(frame)
    if isinstance(frame.body, mp.State) and values[-1] >= 2 ** 63:
        values[-1] -= 2 ** 64
    return values


def same_frame(c_values: list[int], frame: mp.Frame) -> bool:
    """Whether C decoded what Python did. Python keeps a FAULT's text decoded (invalid UTF-8 replaced), C
    its raw bytes."""
    if isinstance(frame.body, mp.Fault):
        raw = bytes(c_values[5:])
        return (c_values[:4] == c_flattened(frame)[:4] and c_values[4] == len(raw)
                and raw.decode("utf-8", "replace") == frame.body.text)
    return c_values == c_flattened(frame)


def same_outcome(codec: CCodec, stream: bytes, chunk: int = 7) -> str | None:
    """The rule both codecs refuse `stream` with (None: both accept it); AssertionError when they differ."""
    c_frames, c_rule = codec.read(stream, chunk)
    frames, rule = python_read(stream)
    if c_rule != rule or len(c_frames) != len(frames) or not all(map(same_frame, c_frames, frames)):
        raise AssertionError(f"C: {len(c_frames)} frames, {c_rule}; Python: {len(frames)} frames, {rule}")
    return rule
