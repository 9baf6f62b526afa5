"""Loops compiled with numba, loaded on first use.

:mod:`scenesig.signatures._hog_kernel` (HOG) and :mod:`scenesig.localiser._solver_kernel` (the eq. 10 solver) compile
their per-pixel and per-detection loops the same way: numba's ``njit`` with ``cache=True`` (compiled
once per machine, then loaded from ``__pycache__``) and ``nogil=True`` (other threads run meanwhile).
numba is imported at the first call, so commands that never run such a loop do not pay its import
(~0.3 s).
"""
from __future__ import annotations

import importlib.util

__all__ = ["AVAILABLE", "lazy_njit"]

#: numba is installed (a dependency; without it the callers run their numpy code).
AVAILABLE = importlib.util.find_spec("numba") is not None


def lazy_njit(fn):
    """``fn`` compiled (``numba.njit(cache=True, nogil=True)``) at its first call; needs :data:`AVAILABLE`."""
    compiled = None

    def call(*args):
        nonlocal compiled
        if compiled is None:
            import numba

            compiled = numba.njit(cache=True, nogil=True)(fn)
        return compiled(*args)

    call.__name__, call.__doc__, call.py_func = fn.__name__, fn.__doc__, fn
    return call
