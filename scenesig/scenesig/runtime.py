"""Process-wide tuning of the ``scenesig`` command line -- applied by :func:`scenesig.cli.main`, never by
importing the library nor inside its calls.

A program that imports the library keeps its own process settings; it may call :func:`configure` to get
the command line's (as the tests of the timings do).  What :func:`configure` changes:

* **malloc** (glibc): freed memory stays in the heap instead of going back to the OS
  (:func:`tune_malloc`), in this process and -- through glibc's environment variables -- in the worker
  processes it starts (joblib, Dask's local workers);
* **OpenCV's thread pool** is set to one thread while :func:`scenesig.signatures.hog.thread_map` runs its own
  threads (:func:`opencv_single_threaded`, installed with :func:`scenesig.signatures.hog.set_parallel_section`);
* a **fork hook** resets that section's lock and bookkeeping in a forked child.

None of it changes a result: only memory and CPU use.
"""
from __future__ import annotations

import contextlib
import os
import sys
import threading

__all__ = ["configure", "tune_malloc", "opencv_single_threaded", "MALLOC_ENV"]

#: glibc's tunables equivalent to :func:`tune_malloc`'s ``mallopt`` calls, read by a process at start-up:
#: mmap threshold 64 MB, trim threshold 256 MB.
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(64 << 20), "MALLOC_TRIM_THRESHOLD_": str(256 << 20)}

_STATE = {"configured": False, "malloc": False}
_CV_LOCK = threading.Lock()
_CV_STATE = {"users": 0, "saved": None}


def tune_malloc() -> bool:
    """Keep freed memory in the process heap instead of returning it to the OS (glibc only).

    A HOG pyramid allocates a few MB of temporaries per level.  glibc serves such blocks with mmap and
    trims the heap after each free, so every level pays ~4 ms of page faults on a 640x480 image -- as
    much as the arithmetic.  Raising the mmap and trim thresholds (64 MB / 256 MB) removes that cost;
    the price is that up to 256 MB of freed memory stays mapped.  The same thresholds go into the
    environment (:data:`MALLOC_ENV`, unless already set) for the worker processes started later.  Set
    ``SCENESIG_NO_MALLOPT=1`` to skip it.  Returns True if the thresholds were set.
    """
    if _STATE["malloc"]:
        return True
    if os.environ.get("SCENESIG_NO_MALLOPT") or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        ok = bool(libc.mallopt(m_mmap_threshold, 64 << 20) and libc.mallopt(m_trim_threshold, 256 << 20))
    except (OSError, AttributeError):
        return False
    if ok:
        for k, v in MALLOC_ENV.items():
            os.environ.setdefault(k, v)
    _STATE["malloc"] = ok
    return ok


@contextlib.contextmanager
def opencv_single_threaded():
    """OpenCV's own thread pool set to one thread while the block runs (nested and concurrent blocks
    share one save / restore).  When the callers already keep the cores busy, OpenCV's workers only add
    their busy-waiting: two level threads each running OpenCV on two threads took ~20 % more CPU than
    with OpenCV on one, for the same wall time."""
    import cv2

    with _CV_LOCK:
        if _CV_STATE["users"] == 0:
            _CV_STATE["saved"] = cv2.getNumThreads()
            cv2.setNumThreads(1)
        _CV_STATE["users"] += 1
    try:
        yield
    finally:
        with _CV_LOCK:
            _CV_STATE["users"] -= 1
            if _CV_STATE["users"] == 0:
                cv2.setNumThreads(_CV_STATE["saved"])


def _after_fork_in_child() -> None:
    """A forked child has none of the parent's threads: a lock one of them held would never be released."""
    global _CV_LOCK
    _CV_LOCK = threading.Lock()
    _CV_STATE.update(users=0, saved=None)


def configure() -> None:
    """Apply the command line's process-wide tuning once (see the module's docstring)."""
    if _STATE["configured"]:
        return
    _STATE["configured"] = True
    from scenesig.signatures.hog import set_parallel_section

    tune_malloc()
    set_parallel_section(opencv_single_threaded)
    if hasattr(os, "register_at_fork"):
        os.register_at_fork(after_in_child=_after_fork_in_child)
