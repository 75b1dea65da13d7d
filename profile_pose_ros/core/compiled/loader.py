"""Which build of the compiled kernels this process runs, loaded on first need.

The prebuilt extension (aot.py) when it can be built on this machine, else numba's JIT of the same
source. PROFILE_POSE_KERNEL=aot|jit|auto (default auto) forces a choice. Decoding a profile needs only
this module and decode_kernel, never the estimator.
"""
from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np

from . import aot

_kernels = None
_kernel_name = ""


def kernels():
    """The compiled functions in use (estimate, detect, refine_pose, decode_xz, refine_dense): loaded (and,
    the first time on a machine, built) on first need."""
    global _kernels, _kernel_name
    if _kernels is None:
        choice = os.environ.get("PROFILE_POSE_KERNEL", "auto")
        module = aot.load() if choice in ("auto", "aot") else None
        if module is not None:
            _kernels, _kernel_name = module, "prebuilt (aot)"
        elif choice == "aot":
            raise RuntimeError("PROFILE_POSE_KERNEL=aot but the prebuilt estimator could not be built here")
        else:
            from . import estimate_kernel
            from .decode_kernel import decode_xz as jit_decode_xz
            from .dense_kernel import refine_dense

            _kernels = SimpleNamespace(estimate=estimate_kernel.estimate, detect=estimate_kernel.detect,
                                       refine_pose=estimate_kernel.refine_pose, decode_xz=jit_decode_xz,
                                       refine_dense=refine_dense)
            _kernel_name = "numba jit"
    return _kernels


def kernel_name() -> str:
    """"prebuilt (aot)" or "numba jit" once the kernels are loaded; "" before."""
    return _kernel_name


def will_compile() -> bool:
    """Whether the kernels' first use in a process will compile them (a minute or more): the prebuilt
    kernel is wanted and this machine has no build of these sources yet."""
    return os.environ.get("PROFILE_POSE_KERNEL", "auto") != "jit" and not aot.is_current()


def decode_xz(table: np.ndarray, x_col: int, y_col: int, z_col: int, out: np.ndarray) -> tuple[int, int]:
    """decode_kernel.decode_xz through the build in use (wire/profile_cloud.decode_profile calls it)."""
    return kernels().decode_xz(table, x_col, y_col, z_col, out)
