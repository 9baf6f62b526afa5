"""Timing helper shared by the benchmarks."""
from __future__ import annotations

import time

import numpy as np


def median_ms(fn, repeat: int = 20) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeat`` calls, after one warm-up call."""
    return median_ms_unqueued(fn, repeat)[0]


def queued_seconds() -> float | None:
    """Time the calling thread has spent runnable but waiting for a core (Linux
    ``/proc/thread-self/schedstat``; None elsewhere)."""
    try:
        with open("/proc/thread-self/schedstat") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return None


def median_ms_unqueued(fn, repeat: int = 20) -> tuple[float, float | None]:
    """:func:`median_ms` and the median of the same calls' wall time minus the calling thread's
    wait for a core (:func:`queued_seconds`; None where unavailable): an estimate of the idle-machine
    time that holds up under load (conservative for work on several threads: the other threads'
    waits for a core stay in)."""
    fn()
    ts, us = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        q0 = queued_seconds()
        fn()
        q1 = queued_seconds()
        dt = time.perf_counter() - t0
        ts.append(dt)
        if q0 is not None and q1 is not None:
            us.append(dt - (q1 - q0))
    return 1000.0 * float(np.median(ts)), (1000.0 * float(np.median(us)) if us else None)
