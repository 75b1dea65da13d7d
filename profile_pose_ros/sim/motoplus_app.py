"""The MotoPlus application of firmware/motoplus, built for this host and loaded through ctypes.

sim_cell's robot controller is this C application, not a model of it: the same mpcl_app.c that a user
compiles with Yaskawa's SDK, over host/mp_host.c, whose interpolation clock ticks when the simulation
says and whose mpExRcsIncrementMove reports to the simulated arm. The library is compiled once per
source version into a cache folder; each controller loads a private copy, so that two controllers in one
process (a test's) do not share the application's globals.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from ..resources import shipped_path

SOURCES = ("mpcl.c", "mpcl_session.c", "mpcl_app.c", "host/mp_host.c")
HEADERS = ("mpcl.h", "mpcl_session.h", "mpcl_app.h", "host/motoPlus.h", "host/mph.h")
STRICT = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2")  # what the controller's toolchain gets too
FLAGS = (*STRICT, "-D_DEFAULT_SOURCE", "-pthread")
SANITIZERS = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g")
CONFIG_D_BASE = 80  # MPCL_CONFIG_D_BASE: where the application reads its configuration (mpcl_app.h)
TEXT = 160


def firmware_dir() -> Path:
    """The sources: a source checkout's firmware/motoplus first (edits take effect), then the installed copy."""
    checkout = Path(__file__).resolve().parents[2] / "firmware" / "motoplus"
    return checkout if (checkout / "mpcl_app.c").is_file() else shipped_path("firmware", "motoplus")


def compiler() -> str | None:
    return shutil.which(os.environ.get("CC", "cc"))


def sanitizers(workdir: Path) -> tuple[str, ...]:
    """SANITIZERS if this compiler and its runtime support them (a probe program links), else ()."""
    probe = workdir / "sanitizer_probe.c"
    probe.write_text("int main(void) { return 0; }\n")
    linked = subprocess.run([compiler() or "cc", *SANITIZERS, str(probe), "-o", str(workdir / "sanitizer_probe")],
                            capture_output=True, timeout=120).returncode == 0
    return SANITIZERS if linked else ()


def build(output: str, sources: tuple[str, ...] = SOURCES, flags: tuple[str, ...] = ("-shared", "-fPIC"),
          source: Path | None = None) -> Path:
    """Compiles `sources` (relative to `source`, the firmware folder by default) into the cache, keyed by
    the sources' and flags' hash; returns the file. RuntimeError with the compiler's message if it fails."""
    source = source or firmware_dir()
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler (cc): sim_cell's robot controller is the C application, built on first use")
    digest = hashlib.sha256(" ".join((cc, *FLAGS, *flags)).encode())
    for name in sorted(set(sources) | set(HEADERS)):
        digest.update(name.encode() + (source / name).read_bytes())
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "profile_pose_ros" / "motoplus"
    target = cache / digest.hexdigest()[:16] / output
    if target.is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(f".{output}.{os.getpid()}")
    result = subprocess.run([cc, *FLAGS, *flags, "-I", str(source), "-I", str(source / "host"), "-o", str(partial),
                             *(str(source / name) for name in sources)], capture_output=True, text=True, timeout=300)
    if result.returncode != 0:
        raise RuntimeError(f"building {output} from {source} failed:\n{result.stderr}")
    os.replace(partial, target)  # atomic: a concurrent build of the same version writes the same bytes
    return target


class Stats(ctypes.Structure):
    _fields_ = [(name, ctypes.c_uint32) for name in ("sessions", "sessions_ended", "faults", "clamped", "idle_closed",
                                                      "replaced", "states", "refused_peers", "dropped_frames",
                                                      "last_fault_code")] + [
        ("last_fault", ctypes.c_char * TEXT), ("session_end", ctypes.c_char * TEXT)]


class Status(ctypes.Structure):
    """mpcl_app_status."""
    _fields_ = [("stats", Stats), ("offset", ctypes.c_int32 * 6), ("period_step", ctypes.c_int32 * 6),
                ("session_step", ctypes.c_int32 * 6), ("session_offset", ctypes.c_int32 * 6),
                ("session_watchdog_ms", ctypes.c_uint32),
                ("periods", ctypes.c_uint32), ("cycles", ctypes.c_uint32), ("motion_errors", ctypes.c_uint32),
                ("armed", ctypes.c_int), ("connected", ctypes.c_int), ("configured", ctypes.c_int),
                ("pending", ctypes.c_int), ("closing", ctypes.c_int),
                ("config_error", ctypes.c_char * TEXT)]


Six = ctypes.c_int32 * 6


class HostApplication:
    """One running copy of the application: configure, start, tick its clock, read what it did."""

    def __init__(self, config: dict[int, int], bind_address: str = "127.0.0.1", port: int | None = None) -> None:
        """config: D variable offsets (mpcl_app.h) to values; port: where to listen on this PC instead of the
        configured port (0: any free one: several simulated cells side by side)."""
        library = build("libmpcl_host.so")
        self._copy = tempfile.TemporaryDirectory(prefix="mpcl-app-")
        private = Path(self._copy.name) / library.name
        shutil.copyfile(library, private)
        self.lib = lib = ctypes.CDLL(str(private))
        lib.mph_set_var_d.argtypes = [ctypes.c_int, ctypes.c_int32]
        lib.mph_set_io.argtypes = [ctypes.c_uint32, ctypes.c_int]
        lib.mph_set_bind_address.argtypes = [ctypes.c_char_p]
        lib.mph_set_bind_port.argtypes = [ctypes.c_int]
        lib.mph_set_cart_pos.argtypes = [Six]
        lib.mph_set_motion_error.argtypes = [ctypes.c_int]
        lib.mph_set_net_faults.argtypes = [ctypes.c_double, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint64]
        lib.mph_tick.argtypes = [ctypes.c_uint32]
        lib.mph_take_increment.argtypes = [Six]
        lib.mph_overruns.restype = ctypes.c_uint32
        lib.mph_last_alarm.restype = ctypes.c_char_p
        lib.mph_bound_address.restype = ctypes.c_char_p
        lib.mpcl_app_read_status.argtypes = [ctypes.POINTER(Status)]
        lib.mph_reset()
        lib.mph_set_bind_address(bind_address.encode())
        if port is not None:
            lib.mph_set_bind_port(port)
        for offset, value in config.items():
            lib.mph_set_var_d(CONFIG_D_BASE + offset, int(value))
        self._increment = Six()
        self.running = False

    def start(self) -> int:
        """Runs mpUsrRoot; returns the port the application listens on. RuntimeError when it refused its
        configuration (its alarm text) or did not start."""
        started = self.lib.mph_start() == 0
        self.running = started
        status = self.status()
        if not status.configured:
            raise RuntimeError(f"the MotoPlus application refused its configuration: {self.alarm()}")
        port = self.lib.mph_port() if started else -1
        if port < 0:
            self.stop()
            raise RuntimeError(f"the MotoPlus application did not start: {self.alarm() or 'no listening socket'}")
        return port

    def tick(self, pose_units: tuple[int, ...], timeout_s: float = 0.004) -> tuple[int, ...]:
        """One interpolation cycle with the arm at `pose_units`: the increment it was told to move. A cycle
        whose work outlasts `timeout_s` is not waited for (overruns() counts it)."""
        self.lib.mph_set_cart_pos(Six(*pose_units))
        self.lib.mph_tick(int(timeout_s * 1e6))
        self.lib.mph_take_increment(self._increment)
        return tuple(self._increment)

    def overruns(self) -> int:
        """Cycles whose work did not finish within the cycle, or that came while the task was late."""
        return self.lib.mph_overruns()

    def status(self) -> Status:
        status = Status()
        self.lib.mpcl_app_read_status(ctypes.byref(status))
        return status

    def address(self) -> str:
        """The address the application's socket is bound to."""
        return self.lib.mph_bound_address().decode()

    def alarm(self) -> str:
        return self.lib.mph_last_alarm().decode(errors="replace")

    def set_io(self, address: int, value: bool) -> None:
        self.lib.mph_set_io(address, int(value))

    def set_motion_error(self, code: int) -> None:
        self.lib.mph_set_motion_error(code)

    def set_net_faults(self, state_drop: float, delay_s: float, fail_after_states: int, seed: int) -> None:
        self.lib.mph_set_net_faults(state_drop, int(delay_s * 1e6), fail_after_states, seed)

    def stop(self) -> None:
        if self.running:
            self.lib.mph_stop()
            self.running = False
