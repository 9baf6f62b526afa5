"""Atomic file writes: a reader -- or a rerun after a crash or a full disk -- sees the old file or the
whole new one, never a part.

Every result file of ``build-map``, ``localise`` and ``report`` is written here:

* :func:`atomic_write_bytes` writes a temporary file in the same folder, fsyncs it, renames it over
  the final name (``os.replace``, atomic on POSIX) and fsyncs the folder;
* :func:`append_line` appends one line to a journal and fsyncs it; a failed append is cut back off,
  so the journal never keeps a torn line that the next append would glue to its own;
* a failed write (ENOSPC, EACCES, EROFS, EDQUOT...) removes its temporary file and raises
  :class:`surveys.errors.OutputError` naming the file, which the command line reports as
  ``scenesig: error: FILE: reason`` (exit 2).  The final name is untouched, so whatever an earlier
  run finished is kept and a rerun after freeing space resumes from it.

Bytes go through ``os.write`` on a raw descriptor, so a test can inject a full disk at the system-call
boundary exactly where a real one would strike.
"""
from __future__ import annotations

import errno
import os
from pathlib import Path

from .errors import OutputError

__all__ = ["atomic_write_bytes", "atomic_write_text", "append_line", "temp_name", "remove_stale_temps",
           "fsync_dir", "output_error", "make_dirs", "atomic_write_figure"]


def output_error(path, exc: OSError) -> OutputError:
    """An :class:`OutputError` for ``path`` from the OSError a write raised."""
    code = errno.errorcode.get(exc.errno, "") if exc.errno else ""
    hint = {errno.ENOSPC: "free some space and run the command again: finished files are kept",
            errno.EDQUOT: "free some space and run the command again: finished files are kept",
            errno.EACCES: "the folder is not writable: fix its permissions or choose another output folder",
            errno.EPERM: "the folder is not writable: fix its permissions or choose another output folder",
            errno.EROFS: "the file system is read-only: choose another output folder"}.get(exc.errno, "")
    reason = f"could not write: {exc.strerror or exc}" + (f" ({code})" if code else "")
    return OutputError(path, reason + (f"; {hint}" if hint else ""))


def make_dirs(folder) -> Path:
    """``mkdir -p`` that reports a failure as :class:`OutputError` naming the folder."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(folder, exc) from exc
    return folder


def fsync_dir(folder: Path) -> None:
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


def temp_name(path: Path) -> Path:
    """The temporary name :func:`atomic_write_bytes` uses for ``path`` (hidden, per process)."""
    path = Path(path)
    return path.parent / f".{path.name}.{os.getpid()}.tmp"


def remove_stale_temps(folder: Path) -> None:
    """Delete temporary files a killed writer left in ``folder`` (never renamed: never results)."""
    for p in Path(folder).glob(".*.tmp"):
        p.unlink(missing_ok=True)


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view:
        n = os.write(fd, view)
        view = view[n:]


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically; :class:`OutputError` (file left as it was) on failure."""
    path = Path(path)
    tmp = temp_name(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise output_error(path, exc) from exc
    fsync_dir(path.parent)


def atomic_write_text(path, text: str) -> None:
    """:func:`atomic_write_bytes` of UTF-8 text."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_figure(fig, path, **savefig_kw) -> Path:
    """Render a matplotlib figure in memory and write it atomically (format from the suffix)."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".") or "png", **savefig_kw)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def append_line(path, line: str) -> None:
    """Append ``line`` (a newline is added) to a journal and fsync it.

    On failure the file is cut back to its previous length (best effort) before
    :class:`OutputError` is raised, so a torn line never precedes a later append.
    """
    path = Path(path)
    data = (line.rstrip("\n") + "\n").encode("utf-8")
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    except OSError as exc:
        raise output_error(path, exc) from exc
    try:
        size = os.fstat(fd).st_size
        try:
            _write_all(fd, data)
            os.fsync(fd)
        except OSError as exc:
            try:
                os.ftruncate(fd, size)
            except OSError:
                pass
            raise output_error(path, exc) from exc
    finally:
        os.close(fd)
