"""Which build of the compiled kernels this process runs, loaded on first need.

The prebuilt extension (aot.py) when it can be built on this machine, else numba's JIT of the same
source. PROFILE_POSE_KERNEL=aot|jit|auto (default auto) forces a choice; PROFILE_POSE_KERNEL=python runs
the very same source uncompiled, as plain Python and numpy (about 100x slower: for stepping through it in
a debugger, or a study that wants to print from inside a stage); without numba installed that is what
runs. Decoding a profile needs only this module and decode_kernel, never the estimator.
"""
from __future__ import annotations

import importlib.util
import os
import sys
from types import SimpleNamespace

import numpy as np

from . import aot

# looked up, not imported: a process on the prebuilt kernel never loads numba (its LLVM costs ~130 MiB)
HAVE_NUMBA = importlib.util.find_spec("numba") is not None

CHOICES = ("auto", "aot", "jit", "python")
_kernels = None
_kernel_name = ""


def kernels():
    """The compiled functions in use (estimate, detect, refine_pose, decode_xz, refine_dense): loaded (and, the
    first time on a machine, built) on first need."""
    global _kernels, _kernel_name
    if _kernels is None:
        choice = os.environ.get("PROFILE_POSE_KERNEL", "auto")
        if choice not in CHOICES:
            raise RuntimeError(f"PROFILE_POSE_KERNEL={choice!r}: expected one of {', '.join(CHOICES)}")
        module = aot.load() if choice in ("auto", "aot") and HAVE_NUMBA else None
        if module is not None:
            _kernels, _kernel_name = module, "prebuilt (aot)"
        elif choice == "aot":
            raise RuntimeError("PROFILE_POSE_KERNEL=aot but the prebuilt estimator could not be built here")
        else:
            if choice == "python":
                _uncompiled()
            from . import estimate_kernel, profile_kernel
            from .decode_kernel import decode_xz as jit_decode_xz
            from .dense_kernel import refine_dense

            _kernels = SimpleNamespace(estimate=profile_kernel.estimate,
                                       detect=estimate_kernel.detect,
                                       refine_pose=estimate_kernel.refine_pose,
                                       decode_xz=jit_decode_xz,
                                       refine_dense=refine_dense)
            _kernel_name = "numba jit" if HAVE_NUMBA and choice != "python" else "uncompiled (python)"
    return _kernels


KERNEL_MODULES = tuple(f"{__package__}.{name}"
                       for name in ("estimate_kernel", "search_kernel", "pipeline_kernel", "partial_kernel",
                                    "profile_kernel", "decode_kernel", "dense_kernel"))


def _uncompiled() -> None:
    """numba decides at decoration time whether @njit compiles: switched off before the kernels are imported,
    their functions stay plain Python calling plain Python. (Without numba they always are.)"""
    if not HAVE_NUMBA:
        return
    import numba

    loaded = [name for name in KERNEL_MODULES if name in sys.modules]
    if loaded and not numba.config.DISABLE_JIT:
        raise RuntimeError(f"PROFILE_POSE_KERNEL=python must be set before the kernels are imported ({loaded[0]} "
                           "already is, compiled)")
    numba.config.DISABLE_JIT = True


def kernel_name() -> str:
    """"prebuilt (aot)" or "numba jit" once the kernels are loaded; "" before."""
    return _kernel_name


def will_compile() -> bool:
    """Whether the kernels' first use in a process will compile them (a minute or more): the prebuilt
    kernel is wanted and this machine has no build of these sources yet."""
    return HAVE_NUMBA and os.environ.get("PROFILE_POSE_KERNEL", "auto") in ("auto", "aot") and not aot.is_current()


def decode_xz(table: np.ndarray, x_col: int, y_col: int, z_col: int, out: np.ndarray) -> tuple[int, int]:
    """decode_kernel.decode_xz through the build in use (wire/profile_cloud.decode_profile calls it)."""
    return kernels().decode_xz(table, x_col, y_col, z_col, out)
