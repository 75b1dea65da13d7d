"""The `ljx` backend: a Keyence LJ-X8000 controller through the vendor's Linux library (libljxacom.so),
in high-speed data communication mode, loaded with ctypes.

The library calls our callback from its own thread with batches of profiles (header, heights in 0.01 um,
optional luminance, footer); we turn each into a ProfileFrame. Data is valid only when the callback's
notify code is 0 or 0x10000; any other code means the stream broke and the connection loop reconnects.
The x grid (start and pitch, 0.01 um units) is read from the controller when streaming starts.
"""
from __future__ import annotations

import ctypes
import ipaddress
import queue
import time

import numpy as np

from ..core.wire.profiler_protocol import ProfileFrame, ProfilerProtocolError

RC_OK = 0
NOTIFY_OK = (0, 0x10000)
X_UNIT = 1e-8  # m per count of lXStart / lXPitch (0.01 um)
HEADER_BYTES, FOOTER_BYTES = 24, 4
SEND_FROM_NEXT = 2  # bySendPosition: start with the next profile measured


class EthernetConfig(ctypes.Structure):
    _fields_ = [("abyIpAddress", ctypes.c_ubyte * 4), ("wPortNo", ctypes.c_ushort), ("reserve", ctypes.c_ubyte * 2)]


class ProfileInfo(ctypes.Structure):
    _fields_ = [("byProfileCount", ctypes.c_ubyte), ("reserve1", ctypes.c_ubyte),
                ("byLuminanceOutput", ctypes.c_ubyte), ("reserve2", ctypes.c_ubyte),
                ("wProfileDataCount", ctypes.c_ushort), ("reserve3", ctypes.c_ubyte * 2),
                ("lXStart", ctypes.c_int), ("lXPitch", ctypes.c_int)]


class PreStartRequest(ctypes.Structure):
    _fields_ = [("bySendPosition", ctypes.c_ubyte), ("reserve", ctypes.c_ubyte * 3)]


CALLBACK = ctypes.CFUNCTYPE(None, ctypes.POINTER(ctypes.c_ubyte), ctypes.c_uint, ctypes.c_uint, ctypes.c_uint,
                            ctypes.c_uint)


class LjxError(OSError):
    """A library call failed; the message names the call and its return code."""


def _load(path: str) -> ctypes.CDLL:
    try:
        lib = ctypes.CDLL(path)
    except OSError as exc:
        raise LjxError(f"cannot load the LJ-X library '{path}': {exc}") from None
    int_args = {
        "LJX8IF_EthernetOpen": [ctypes.c_int, ctypes.POINTER(EthernetConfig)],
        "LJX8IF_CommunicationClose": [ctypes.c_int],
        "LJX8IF_InitializeHighSpeedDataCommunication": [ctypes.c_int, ctypes.POINTER(EthernetConfig), ctypes.c_ushort,
                                                        CALLBACK, ctypes.c_uint, ctypes.c_uint],
        "LJX8IF_PreStartHighSpeedDataCommunication": [ctypes.c_int, ctypes.POINTER(PreStartRequest),
                                                      ctypes.POINTER(ProfileInfo)],
        "LJX8IF_StartHighSpeedDataCommunication": [ctypes.c_int],
        "LJX8IF_StopHighSpeedDataCommunication": [ctypes.c_int],
        "LJX8IF_FinalizeHighSpeedDataCommunication": [ctypes.c_int],
    }
    for name, argtypes in int_args.items():
        try:
            fn = getattr(lib, name)
        except AttributeError:
            raise LjxError(f"'{path}' has no function {name}: not the LJ-X8000 library") from None
        fn.argtypes, fn.restype = argtypes, ctypes.c_int
    lib.LJX8IF_Initialize.restype = ctypes.c_long
    lib.LJX8IF_Finalize.restype = ctypes.c_long
    return lib


def parse_batch(buffer: bytes, unit_size: int, count: int, info: ProfileInfo) -> list[ProfileFrame]:
    """A callback's batch -> frames; raises ProfilerProtocolError if the sizes disagree with the settings."""
    n = info.wProfileDataCount
    luminance = 1 if info.byLuminanceOutput else 0
    expected = HEADER_BYTES + 4 * n * (1 + luminance) + FOOTER_BYTES
    if unit_size != expected:
        raise ProfilerProtocolError(f"profile unit of {unit_size} bytes, expected {expected} for {n} points "
                                    f"(luminance {'on' if luminance else 'off'}): controller settings changed?")
    if len(buffer) != unit_size * count:
        raise ProfilerProtocolError(f"batch of {len(buffer)} bytes for {count} profiles of {unit_size}")
    frames = []
    x_start, x_pitch = info.lXStart * X_UNIT, info.lXPitch * X_UNIT
    for k in range(count):
        unit = buffer[k * unit_size:(k + 1) * unit_size]
        trigger_count = int.from_bytes(unit[4:8], "little")
        heights = np.frombuffer(unit, dtype="<i4", count=n, offset=HEADER_BYTES)
        frames.append(ProfileFrame(trigger_count, 0, x_start, x_pitch, heights))
    return frames


class LjxProfileSource:
    def __init__(self, library_path: str, host: str, command_port: int = 24691, data_port: int = 24692,
                 device_id: int = 0) -> None:
        self.name = f"ljx://{host}:{command_port}/{data_port}"
        self.library_path = library_path
        self.config = EthernetConfig()
        self.config.abyIpAddress[:] = list(ipaddress.IPv4Address(host).packed)
        self.config.wPortNo = command_port
        self.data_port = data_port
        self.device_id = device_id
        self._lib: ctypes.CDLL | None = None
        self._callback = CALLBACK(self._on_batch)  # kept referenced: the library holds a raw pointer
        self._queue: queue.Queue = queue.Queue(maxsize=10000)
        self._info = ProfileInfo()
        self._open = False
        self._last_data = time.monotonic()

    def _call(self, name: str, *args) -> None:
        rc = getattr(self._lib, name)(*args)
        if rc != RC_OK:
            raise LjxError(f"{name} returned 0x{rc & 0xFFFFFFFF:04x}")

    def open(self) -> None:
        self.close()
        if self._lib is None:
            self._lib = _load(self.library_path)
        self._lib.LJX8IF_Initialize()
        self._call("LJX8IF_EthernetOpen", self.device_id, ctypes.byref(self.config))
        self._open = True
        self._call("LJX8IF_InitializeHighSpeedDataCommunication", self.device_id, ctypes.byref(self.config),
                   self.data_port, self._callback, 1, 0)
        request = PreStartRequest(bySendPosition=SEND_FROM_NEXT)
        self._call("LJX8IF_PreStartHighSpeedDataCommunication", self.device_id, ctypes.byref(request),
                   ctypes.byref(self._info))
        if self._info.lXPitch <= 0 or self._info.wProfileDataCount == 0:
            raise LjxError(f"controller reports no usable x grid (pitch {self._info.lXPitch}, "
                           f"{self._info.wProfileDataCount} points)")
        self._call("LJX8IF_StartHighSpeedDataCommunication", self.device_id)
        self._last_data = time.monotonic()

    def _on_batch(self, buffer, unit_size: int, count: int, notify: int, _user: int) -> None:
        """Runs on the library's thread: copy out and return quickly."""
        self._last_data = time.monotonic()
        try:
            if notify not in NOTIFY_OK:
                item = [ConnectionError(f"high-speed communication interrupted (notify 0x{notify:x})")]
            elif count == 0:
                return
            else:
                item = parse_batch(ctypes.string_at(buffer, unit_size * count), unit_size, count, self._info)
        except ProfilerProtocolError as exc:
            item = [exc]
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            pass  # the reader is stalled; the trigger-count gap will show the loss

    def read(self, timeout: float) -> list:
        try:
            batch = self._queue.get(timeout=timeout)
        except queue.Empty:
            return []
        items = list(batch)
        while not self._queue.empty():
            items.extend(self._queue.get_nowait())
        for item in items:
            if isinstance(item, ConnectionError):
                raise item
        return items

    def seconds_since_data(self) -> float:
        return time.monotonic() - self._last_data

    def close(self) -> None:
        if self._lib is not None and self._open:
            self._open = False
            for name in ("LJX8IF_StopHighSpeedDataCommunication", "LJX8IF_FinalizeHighSpeedDataCommunication",
                         "LJX8IF_CommunicationClose"):
                getattr(self._lib, name)(self.device_id)  # best effort: the link may already be gone
        while not self._queue.empty():
            self._queue.get_nowait()
