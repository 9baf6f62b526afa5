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


def reference_seconds() -> float:
    """Wall time of a fixed single-threaded workload (a 3-million-step Python loop and 300 products of
    200x200 matrices on one BLAS thread): about 0.4 s on the development machine at its usual speed.

    A shared virtual machine's speed drifts (this one by half within minutes, with nothing else
    running), so a timing means little without the machine's speed at that moment: benchmarks
    report this before and after their own work (``machine_reference_seconds``)."""
    from threadpoolctl import threadpool_limits

    a = np.random.default_rng(0).random((200, 200))
    t0 = time.perf_counter()
    x = 0
    for j in range(3_000_000):
        x += j * j
    with threadpool_limits(limits=1):
        for _ in range(300):
            a @ a
    return round(time.perf_counter() - t0, 3)
