"""The kernels' decorator: numba's njit where numba is installed, else the plain Python function, so the
core still runs, uncompiled, with numpy alone (DESIGN.md: studies and notebooks need no more than numpy).
"""
from __future__ import annotations

import os

try:
    from numba import config as _numba_config
    from numba import njit as _njit
except ImportError:  # the core without numba: every kernel runs as plain Python
    _njit = None
else:
    if not os.environ.get("NUMBA_CACHE_DIR"):  # numba reads it as each kernel is decorated, after this
        from .caches import jit_cache

        _numba_config.CACHE_DIR = str(jit_cache())


def kernel(**options):
    """@njit(**options) with numba; the function itself without."""
    def decorate(function):
        return function if _njit is None else _njit(**options)(function)
    return decorate
