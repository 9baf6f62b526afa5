"""Timing helper shared by the benchmarks."""
from __future__ import annotations

import time

import numpy as np


def median_ms(fn, repeat: int = 20) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeat`` calls, after one warm-up call."""
    fn()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(ts))
