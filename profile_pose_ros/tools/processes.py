"""Running package executables as their own processes, and measuring them through /proc."""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
from pathlib import Path

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
_DOMAINS = itertools.count()
MAX_DOMAIN_ID = 232  # the largest domain id Fast DDS takes (its ports must fit in 16 bits)


def fresh_domain_id() -> int:
    """A DDS domain no recent call of this process handed out (the last 200 calls, or as many as
    PROFILE_POSE_DOMAIN_IDS's range holds), and likely none of another process running beside it: each graph
    or test context gets its own, so nothing left of an earlier one can answer. PROFILE_POSE_DOMAIN_IDS=
    first-last keeps a process to a range of its own, so that runners started side by side (the test suite's
    workers) never share one."""
    first, last = domain_range(os.environ.get("PROFILE_POSE_DOMAIN_IDS", ""))
    return first + (os.getpid() * 13 + next(_DOMAINS)) % (last - first + 1)


def domain_range(confined: str) -> tuple[int, int]:
    """The DDS domains fresh_domain_id may hand out: PROFILE_POSE_DOMAIN_IDS's `first-last`, 1-200 if unset."""
    if not confined:
        return 1, 200
    parts = confined.split("-")
    if len(parts) != 2 or not all(part.strip().isdigit() for part in parts):
        raise ValueError(f"PROFILE_POSE_DOMAIN_IDS={confined!r}: expected first-last, e.g. 101-200")
    first, last = int(parts[0]), int(parts[1])
    if not 0 <= first <= last <= MAX_DOMAIN_ID:
        raise ValueError(f"PROFILE_POSE_DOMAIN_IDS={confined!r}: expected 0 <= first <= last <= {MAX_DOMAIN_ID} "
                         "(Fast DDS's domain ids)")
    return first, last


def executable(name: str | None, module: str) -> list[str]:
    """The venv's console script if installed, else `python -m module` (always, for a module without a
    console script: name None)."""
    exe = Path(sys.executable).parent / name if name else None
    return [str(exe)] if exe is not None and exe.exists() else [sys.executable, "-m", module]


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the starting process dies, however it dies (a killed
    bringup or test leaves no node behind; SIGTERM takes the nodes' clean path, the bridge's STOP)."""
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def start(command: list[str], domain_id: int, log_path: Path) -> subprocess.Popen:
    """Start from the main thread: the death signal follows the thread that started the child."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id))
    log = open(log_path, "w")
    process = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT,
                               preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
    process.log_file = log  # closed by stop()
    return process


def stop(process: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGINT (a node's clean shutdown path), then SIGKILL if it does not exit in time."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    log = getattr(process, "log_file", None)
    if log is not None:
        log.close()
    return process.returncode


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def memory_kib(pid: int) -> dict:
    """Current (VmRSS) and peak (VmHWM) resident memory in KiB."""
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0])
    return values
