"""The bridge <-> MotoPlus application protocol (docs/motoplus_protocol.md): pure encode and decode.

Little-endian, length-prefixed frames over TCP. Values are in the controller's native units (um and
0.0001 deg) as int32, so nothing is rounded twice. Every decoder rejects anything malformed with
MotoPlusProtocolError; nothing else escapes.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

MAGIC = b"MPCL"
VERSION = 1
PREFIX = struct.Struct("<I")  # length of everything after it
HEADER = struct.Struct("<4sBBHII")  # magic, version, type, reserved, seq, ack
CRC = struct.Struct("<I")
MAX_FRAME = 1024

HELLO, CORRECTION, STATE, HEARTBEAT, STOP, FAULT = 1, 2, 3, 4, 5, 6
TYPE_NAMES = {HELLO: "HELLO", CORRECTION: "CORRECTION", STATE: "STATE", HEARTBEAT: "HEARTBEAT", STOP: "STOP",
              FAULT: "FAULT"}

# Cartesian frames of an increment (MotoPlus MP_BASE_COORD, MP_ROBO_COORD, MP_TOOL_COORD, MP_USER_COORD)
FRAME_BASE, FRAME_ROBOT, FRAME_TOOL, FRAME_USER = 0, 1, 2, 3

# STATE status bits
ARMED, MOVING, HOLDING, FAULTED, CLAMPED = 1, 2, 4, 8, 16

# FAULT codes
FAULT_SEQUENCE_GAP, FAULT_WATCHDOG, FAULT_LIMIT, FAULT_PROTOCOL, FAULT_NOT_ARMED, FAULT_STOPPED, FAULT_ALARM = (
    1, 2, 3, 4, 5, 6, 7)

UM_PER_M = 1e6
TENTH_MILLIDEG_PER_RAD = 1e4 * 180.0 / 3.141592653589793
UNITS_PER_SI = (UM_PER_M,) * 3 + (TENTH_MILLIDEG_PER_RAD,) * 3  # x y z (m), rx ry rz (rad) -> units


RULES = ("length", "short", "checksum", "magic", "version", "type", "size", "frame", "limits", "text")


class MotoPlusProtocolError(ValueError):
    """A frame that breaks the protocol; the message says how, `rule` (one of RULES) which check failed:
    the controller-side C codec (firmware/motoplus) reports the same rule for the same bytes."""

    def __init__(self, message: str, rule: str = "size") -> None:
        super().__init__(message)
        self.rule = rule


def six(values) -> tuple[int, ...]:
    values = tuple(int(v) for v in values)
    if len(values) != 6:
        raise MotoPlusProtocolError(f"expected 6 values (x y z rx ry rz), got {len(values)}", "size")
    return values


@dataclass(frozen=True)
class Hello:
    period_us: int  # control period the bridge expects (a multiple of the 4 ms interpolation clock)
    max_step: tuple[int, ...]  # per-cycle clamp, um / 0.0001 deg, per axis
    max_offset: tuple[int, ...]  # bound on the total offset from the start pose
    watchdog_ms: int  # the controller ends the session after this long without a frame
    frame: int = FRAME_BASE
    tool: int = 0
    user_frame: int = 0


@dataclass(frozen=True)
class Correction:
    increment: tuple[int, ...]  # this cycle's move, um / 0.0001 deg
    frame: int = FRAME_BASE
    tool: int = 0
    user_frame: int = 0


@dataclass(frozen=True)
class State:
    echoed_seq: int  # the last CORRECTION the controller applied
    pose: tuple[int, ...]  # the commanded Cartesian pose, um / 0.0001 deg
    offset: tuple[int, ...] = (0,) * 6  # total applied offset since HELLO
    status: int = 0
    error_code: int = 0
    time_us: int = 0  # controller clock


@dataclass(frozen=True)
class Heartbeat:
    pass


@dataclass(frozen=True)
class Stop:
    pass


@dataclass(frozen=True)
class Fault:
    code: int
    text: str = ""


Body = Hello | Correction | State | Heartbeat | Stop | Fault


@dataclass(frozen=True)
class Frame:
    seq: int
    ack: int
    body: Body = field(default_factory=Heartbeat)


_HELLO = struct.Struct("<I6i6iIBBBx")
_CORRECTION = struct.Struct("<6iBBBx")
_STATE = struct.Struct("<I6i6iIIQ")
_FAULT = struct.Struct("<IH")
MAX_FAULT_TEXT = 200


def _payload(body: Body) -> tuple[int, bytes]:
    if isinstance(body, Hello):
        return HELLO, _HELLO.pack(body.period_us, *six(body.max_step), *six(body.max_offset), body.watchdog_ms,
                                  body.frame, body.tool, body.user_frame)
    if isinstance(body, Correction):
        return CORRECTION, _CORRECTION.pack(*six(body.increment), body.frame, body.tool, body.user_frame)
    if isinstance(body, State):
        return STATE, _STATE.pack(body.echoed_seq, *six(body.pose), *six(body.offset), body.status,
                                  body.error_code, body.time_us)
    if isinstance(body, Heartbeat):
        return HEARTBEAT, b""
    if isinstance(body, Stop):
        return STOP, b""
    if isinstance(body, Fault):
        text = body.text.encode("utf-8")[:MAX_FAULT_TEXT]
        return FAULT, _FAULT.pack(body.code, len(text)) + text
    raise TypeError(f"not a protocol body: {body!r}")


def encode(frame: Frame) -> bytes:
    kind, payload = _payload(frame.body)
    inner = HEADER.pack(MAGIC, VERSION, kind, 0, frame.seq & 0xFFFFFFFF, frame.ack & 0xFFFFFFFF) + payload
    inner += CRC.pack(zlib.crc32(inner))
    return PREFIX.pack(len(inner)) + inner


def _body(kind: int, payload: bytes) -> Body:
    try:
        if kind == HELLO:
            v = _HELLO.unpack(payload)
            hello = Hello(v[0], v[1:7], v[7:13], v[13], v[14], v[15], v[16])
            if hello.frame not in (FRAME_BASE, FRAME_ROBOT, FRAME_TOOL, FRAME_USER):
                raise MotoPlusProtocolError(f"HELLO: unknown frame {hello.frame}", "frame")
            if hello.period_us <= 0 or min(hello.max_step) < 0 or min(hello.max_offset) < 0:
                raise MotoPlusProtocolError("HELLO: period and limits must be positive", "limits")
            return hello
        if kind == CORRECTION:
            v = _CORRECTION.unpack(payload)
            if v[6] not in (FRAME_BASE, FRAME_ROBOT, FRAME_TOOL, FRAME_USER):
                raise MotoPlusProtocolError(f"CORRECTION: unknown frame {v[6]}", "frame")
            return Correction(v[:6], v[6], v[7], v[8])
        if kind == STATE:
            v = _STATE.unpack(payload)
            return State(v[0], v[1:7], v[7:13], v[13], v[14], v[15])
        if kind in (HEARTBEAT, STOP):
            if payload:
                raise MotoPlusProtocolError(f"{TYPE_NAMES[kind]} carries no payload, got {len(payload)} bytes",
                                            "size")
            return Heartbeat() if kind == HEARTBEAT else Stop()
        if kind == FAULT:
            code, length = _FAULT.unpack_from(payload)
            if len(payload) != _FAULT.size + length:
                raise MotoPlusProtocolError(f"FAULT: text length {length} does not match the payload", "text")
            if length > MAX_FAULT_TEXT:
                raise MotoPlusProtocolError(f"FAULT: text of {length} bytes, more than {MAX_FAULT_TEXT}", "text")
            return Fault(code, payload[_FAULT.size:].decode("utf-8", "replace"))
    except struct.error as exc:
        raise MotoPlusProtocolError(f"{TYPE_NAMES.get(kind, kind)}: payload of {len(payload)} bytes: {exc}",
                                    "size") from None
    raise MotoPlusProtocolError(f"unknown frame type {kind}", "type")


def decode(inner: bytes) -> Frame:
    """One frame without its length prefix; raises MotoPlusProtocolError."""
    if len(inner) < HEADER.size + CRC.size:
        raise MotoPlusProtocolError(f"frame of {len(inner)} bytes is shorter than a header", "short")
    (crc,) = CRC.unpack_from(inner, len(inner) - CRC.size)
    if zlib.crc32(inner[:-CRC.size]) != crc:
        raise MotoPlusProtocolError("checksum mismatch", "checksum")
    magic, version, kind, _, seq, ack = HEADER.unpack_from(inner)
    if magic != MAGIC:
        raise MotoPlusProtocolError(f"bad magic {magic!r}", "magic")
    if version != VERSION:
        raise MotoPlusProtocolError(f"unsupported protocol version {version} (this side speaks {VERSION})", "version")
    return Frame(seq, ack, _body(kind, bytes(inner[HEADER.size:-CRC.size])))


class FrameReader:
    """Splits a TCP byte stream into frames. A bad length cannot be resynchronised on a length-prefixed
    stream, so after any error the connection must be dropped: the reader raises and stays failed."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.failed: MotoPlusProtocolError | None = None

    def feed(self, data: bytes) -> list[Frame]:
        if self.failed is not None:
            raise self.failed
        self._buffer += data
        frames = []
        try:
            while len(self._buffer) >= PREFIX.size:
                (length,) = PREFIX.unpack_from(self._buffer)
                if not HEADER.size + CRC.size <= length <= MAX_FRAME:
                    raise MotoPlusProtocolError(f"frame length {length} out of range", "length")
                if len(self._buffer) < PREFIX.size + length:
                    break
                inner = bytes(self._buffer[PREFIX.size:PREFIX.size + length])
                del self._buffer[:PREFIX.size + length]
                frames.append(decode(inner))
        except MotoPlusProtocolError as exc:
            self.failed = exc
            raise
        return frames


def metres_to_units(vector) -> tuple[int, ...]:
    """[x y z (m), rx ry rz (rad)] -> the controller's int units (um, 0.0001 deg), rounded."""
    return tuple(int(round(v * scale)) for v, scale in zip(vector, UNITS_PER_SI))


def units_to_metres(units) -> tuple[float, ...]:
    return tuple(v / scale for v, scale in zip(units, UNITS_PER_SI))


class CarriedRounding:
    """Metres and radians to units for a stream of increments, each rounding's remainder carried into the
    next: the sum of what is sent stays within half a unit of the sum asked for. Rounded one by one, a
    loop asking 0.4 um a period would send nothing at all, and the error of many would wander (the loop
    then corrects it, as a disturbance that rings the arm's mode)."""

    def __init__(self) -> None:
        self.remainder = [0.0] * 6  # units

    def reset(self) -> None:
        self.remainder = [0.0] * 6

    def __call__(self, vector) -> tuple[int, ...]:
        vector = [float(v) for v in vector]
        if len(vector) != 6:
            raise MotoPlusProtocolError(f"expected 6 values (x y z rx ry rz), got {len(vector)}", "size")
        wanted = [v * scale + r for v, scale, r in zip(vector, UNITS_PER_SI, self.remainder)]
        units = tuple(int(round(w)) for w in wanted)
        self.remainder = [w - u for w, u in zip(wanted, units)]
        return units


def clamp(increment, limits) -> tuple[tuple[int, ...], bool]:
    """Each axis within +-limit; also whether anything was cut."""
    out = tuple(max(-lim, min(lim, v)) for v, lim in zip(six(increment), six(limits)))
    return out, out != tuple(increment)


MAX_SEQ_GAP = 3  # CORRECTION frames that may go missing in a row before the controller faults


def sequence_verdict(last_seq: int, seq: int) -> str:
    """The controller's rule for a frame's sequence number after `last_seq`: 'new' (take it), 'old'
    (old or repeated: ignore it) or 'gap' (more than MAX_SEQ_GAP frames missing: FAULT)."""
    if seq <= last_seq:
        return "old"
    return "gap" if seq - last_seq > MAX_SEQ_GAP + 1 else "new"
