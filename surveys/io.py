"""Atomic file writes: a reader (or a crash) sees the old file or the whole new one, never a part.

Every writer of the project goes through here: the map store's place files and manifest, survey-run
TUM files, the localiser's outputs, reports, figures and benchmark JSON.  The new content goes to a
hidden temporary file beside the target (same folder, so the rename never crosses file systems), is
flushed and fsync'ed, and replaces the target with ``os.replace``; the folder is fsync'ed so the
rename survives a power cut.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_path", "temp_name", "fsync_dir"]


def _fsync_dir(folder: Path) -> None:
    """Make a rename durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def temp_name(path: Path, keep_suffix: bool = False) -> Path:
    """The temporary file for ``path``: hidden, per process, ending in ``.tmp`` (plus the target's suffix
    with ``keep_suffix``, for writers that choose a format by it, e.g. matplotlib's ``savefig``)."""
    path = Path(path)
    if keep_suffix:
        return path.parent / f".{path.stem}.{os.getpid()}.tmp{path.suffix}"
    return path.parent / f".{path.name}.{os.getpid()}.tmp"


def fsync_dir(folder) -> None:
    """Make renames and removals in ``folder`` durable."""
    _fsync_dir(Path(folder))


def _replace(tmp: Path, path: Path) -> None:
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    path = Path(path)
    tmp = temp_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        _replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path, text: str, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically (UTF-8 by default)."""
    atomic_write_bytes(path, text.encode(encoding))


@contextmanager
def atomic_path(path):
    """``with atomic_path(p) as tmp: write(tmp)`` -- for writers that want a file name (e.g.
    ``fig.savefig(tmp)``): ``tmp`` replaces ``p`` when the block ends without an exception, and is
    removed otherwise."""
    path = Path(path)
    tmp = temp_name(path, keep_suffix=True)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        _replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
