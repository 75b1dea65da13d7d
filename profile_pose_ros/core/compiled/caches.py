"""Where the compiled kernels are kept on this machine: the prebuilt builds (aot.py) and numba's JIT cache, each
under a fingerprint of the kernels' sources and the toolchain, so that no build or cache outlives the code it
was made from.
"""
from __future__ import annotations

import functools
import hashlib
import os
import platform
import shutil
import sys
import time
from importlib.metadata import version
from pathlib import Path

SOURCES = ("compiled/estimate_kernel.py", "compiled/search_kernel.py", "compiled/pipeline_kernel.py",
           "compiled/partial_kernel.py", "compiled/profile_kernel.py", "compiled/codes.py", "compiled/dense_kernel.py",
           "compiled/decode_kernel.py", "compiled/kernel.py", "model/sym3.py")


def _user_cache() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")) / "profile_pose_ros"


def cache_root() -> Path:
    explicit = os.environ.get("PROFILE_POSE_AOT_DIR")
    return Path(explicit) if explicit else _user_cache() / "aot"


def jit_cache() -> Path:
    """Where numba's JIT keeps the kernels of these sources (kernel.py points it here unless NUMBA_CACHE_DIR is
    set): one directory per fingerprint, because numba keys a function's cache on its own file alone, and a
    caller (pipeline_kernel) would run its stale machine code after a callee's file (dense_kernel) changed.
    Marked in use, and the directories of other sources unused for a month removed, as the prebuilt ones."""
    directory = _user_cache() / "jit" / fingerprint()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        os.utime(directory)
        prune(directory.parent, keep=directory)
    except OSError:
        pass
    return directory


@functools.cache
def fingerprint() -> str:
    """Changes whenever the compiled code or the toolchain that compiles it changes. Computed once a
    process: the sources it hashes are the ones this process imported."""
    digest = hashlib.sha256()
    here = Path(__file__).resolve().parent.parent  # core/
    for name in SOURCES:
        digest.update((here / name).read_bytes())
    for item in (version("numba"), version("numpy"), sys.version, platform.machine()):
        digest.update(item.encode())
    return digest.hexdigest()[:16]


UNUSED_FOR_S = 30 * 86400  # a build no process has loaded for this long is removed after the next build
ABANDONED_AFTER_S = 86400  # a scratch directory this old is a build that died


def prune(root: Path, keep: Path, now: float | None = None) -> list[Path]:
    """Remove the builds of other fingerprints unused for UNUSED_FOR_S, and scratch directories of builds
    that died: each upgrade of the package (or of numba) builds anew, and the old ones (~1 MB each) would
    pile up. A build in use by another installed version is touched at each load, so it stays."""
    now = time.time() if now is None else now
    removed = []
    for entry in root.iterdir() if root.is_dir() else ():
        if entry == keep or not entry.is_dir():
            continue
        limit = ABANDONED_AFTER_S if "." in entry.name else UNUSED_FOR_S
        try:
            if now - entry.stat().st_mtime > limit:
                shutil.rmtree(entry)
                removed.append(entry)
        except OSError:
            pass
    return removed
