"""Write failures injected at the system-call boundary, as a full disk or a read-only folder causes them.

Every result file goes through :mod:`scenesig.surveys.io`, which writes with ``os.open`` / ``os.write``;
these helpers make those calls fail for files under one folder only (found through /proc/self/fd),
after an optional number of bytes, exactly where a real ENOSPC or EACCES would strike.
"""
from __future__ import annotations

import errno
import os
from pathlib import Path


def _under(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder + os.sep)


def disk_full(monkeypatch, folder, after_bytes: int = 0, err: int = errno.ENOSPC):
    """``os.write`` to files under ``folder`` fails with ``err`` once ``after_bytes`` have been written
    there (the write that crosses the limit writes what fits first, as a filling disk does).
    Returns a dict whose ``"failures"`` counts the failed writes."""
    real_write = os.write
    folder = str(Path(folder).resolve())
    state = {"left": int(after_bytes), "failures": 0}

    def write(fd, data):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            target = ""
        if not _under(target, folder):
            return real_write(fd, data)
        if state["left"] <= 0:
            state["failures"] += 1
            raise OSError(err, os.strerror(err))
        n = min(len(data), state["left"])
        state["left"] -= n
        return real_write(fd, bytes(memoryview(data).cast("B")[:n]))

    monkeypatch.setattr(os, "write", write)
    return state


def read_only(monkeypatch, folder, err: int = errno.EACCES):
    """Creating or writing files or folders under ``folder`` fails with ``err`` (as for a read-only
    folder, which root -- who runs CI -- would otherwise ignore)."""
    real_open, real_mkdir = os.open, os.mkdir
    folder = str(Path(folder).resolve())

    def open_(path, flags, *a, **k):
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT) and _under(str(Path(path).resolve()), folder):
            raise OSError(err, os.strerror(err), str(path))
        return real_open(path, flags, *a, **k)

    def mkdir(path, *a, **k):
        if _under(str(Path(path).resolve()), folder):
            raise OSError(err, os.strerror(err), str(path))
        return real_mkdir(path, *a, **k)

    monkeypatch.setattr(os, "open", open_)
    monkeypatch.setattr(os, "mkdir", mkdir)


def folder_bytes(root) -> dict:
    """``{relative path: bytes}`` of every file below ``root``."""
    root = Path(root)
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
