"""Wall time per pipeline stage, measured by wrapping the functions that do each stage's work.

A profile needs stage totals, not a call graph: :class:`StageTimer` replaces chosen functions or
methods (module attributes, looked up at call time by their callers) with timing wrappers for the
duration of a ``with`` block.  Times are *exclusive* per thread -- a timed function called inside
another timed one is charged to its own stage only -- so the stages add up to the time spent in
timed code, and what is left of the wall time is the caller's bookkeeping.
"""
from __future__ import annotations

import contextlib
import functools
import threading
import time
from collections import defaultdict

__all__ = ["StageTimer", "emit_json"]


class StageTimer:
    """Exclusive wall time, CPU time of the calling thread and call counts per stage name.

    On a loaded machine the wall time includes waiting for a core; the thread's CPU time does not.

    Examples
    --------
    >>> st = StageTimer()
    >>> with st.patch(some_module, "expensive", "compute"):
    ...     some_module.caller()
    >>> st.seconds["compute"], st.calls["compute"]
    """

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self.cpu_seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.thread_names: dict[str, set] = defaultdict(set)
        # stage -> thread name -> (wall, CPU) seconds: what each thread spent in the stage
        self.by_thread: dict[str, dict] = defaultdict(lambda: defaultdict(lambda: [0.0, 0.0]))
        self._local = threading.local()
        self._lock = threading.Lock()

    def wrap(self, fn, stage: str):
        """``fn`` timed as ``stage``."""
        timer = self

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            stack = getattr(timer._local, "stack", None)
            if stack is None:
                stack = timer._local.stack = []
            stack.append([0.0, 0.0])             # wall and CPU time spent in timed callees
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                dt, dc = time.perf_counter() - t0, time.thread_time() - c0
                inner = stack.pop()
                if stack:
                    stack[-1][0] += dt
                    stack[-1][1] += dc
                with timer._lock:
                    timer.seconds[stage] += dt - inner[0]
                    timer.cpu_seconds[stage] += dc - inner[1]
                    timer.calls[stage] += 1
                    name = threading.current_thread().name
                    timer.thread_names[stage].add(name)
                    own = timer.by_thread[stage][name]
                    own[0] += dt - inner[0]
                    own[1] += dc - inner[1]
        return timed

    @contextlib.contextmanager
    def patch(self, *targets):
        """Time ``(owner, attribute, stage)`` triples while the block runs; restores them after."""
        saved = []
        try:
            for owner, attr, stage in targets:
                orig = owner.__dict__[attr] if isinstance(owner, type) else getattr(owner, attr)
                kind = type(orig) if isinstance(orig, (staticmethod, classmethod)) else None
                wrapped = self.wrap(orig.__func__ if kind else orig, stage)
                setattr(owner, attr, kind(wrapped) if kind else wrapped)
                saved.append((owner, attr, orig))
            yield self
        finally:
            for owner, attr, orig in reversed(saved):
                setattr(owner, attr, orig)

    def as_dict(self, per: int | None = None, scale: float = 1e3) -> dict:
        """``{stage: {"ms", "cpu_ms", "calls"[, "ms_per", "cpu_ms_per"]}}`` (totals and per ``per``)."""
        out = {}
        for k in sorted(self.seconds, key=lambda s: -self.seconds[s]):
            d = {"ms": round(scale * self.seconds[k], 3), "cpu_ms": round(scale * self.cpu_seconds[k], 3),
                 "calls": int(self.calls[k])}
            if per:
                d["ms_per"] = round(scale * self.seconds[k] / per, 3)
                d["cpu_ms_per"] = round(scale * self.cpu_seconds[k] / per, 3)
            out[k] = d
        return out


def emit_json(result: dict, path=None) -> None:
    """Print a benchmark's result as JSON and, with ``path``, write it there atomically."""
    import json

    from scenesig.surveys.io import atomic_write_text

    text = json.dumps(result, indent=1)
    print(text)
    if path:
        atomic_write_text(path, text + "\n")


def read_config(path):
    """A benchmark's ``--config JSON`` file as a dict (None for no path); a DataError names a file
    that cannot be read or parsed."""
    if not path:
        return None
    import json
    from pathlib import Path

    from scenesig.surveys.errors import DataError

    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise DataError(path, f"cannot read the settings: {exc}") from None
