"""Atomic file writes: a reader (or a crash, or a rerun after a full disk) sees the old file or the
whole new one, never a part.

Every writer of the project goes through here: the map store's place files, manifest and journals,
survey-run TUM files, the localiser's outputs, reports, figures and benchmark JSON.  The new content
goes to a hidden temporary file beside the target (same folder, so the rename never crosses file
systems), is fsync'ed, and replaces the target with ``os.replace``; the folder is fsync'ed so the
rename survives a power cut.  Journals (``journal.jsonl``, ``build_stats.jsonl``) grow by
:func:`append_line`, which cuts a failed append back off, so a torn line never precedes the next one.

A failed write (ENOSPC, EACCES, EROFS, EDQUOT...) removes its temporary file and raises
:class:`scenesig.surveys.errors.OutputError` naming the file, which the command line reports as
``scenesig: error: FILE: reason`` (exit 2).  The final name is untouched, so whatever an earlier run
finished is kept and a rerun after freeing space resumes from it.  Bytes go through ``os.write`` on
a raw descriptor, so a test can inject a full disk at the system-call boundary, where a real one
strikes.
"""
from __future__ import annotations

import errno
import os
import shutil
from contextlib import contextmanager
from pathlib import Path

from .errors import OutputError

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_path", "atomic_folder", "append_line", "make_dirs",
           "temp_name", "remove_stale_temps", "fsync_dir", "output_error"]

_HINTS = {errno.ENOSPC: "free some space and run the command again: finished files are kept",
          errno.EDQUOT: "free some space and run the command again: finished files are kept",
          errno.EACCES: "the folder is not writable: fix its permissions or choose another output folder",
          errno.EPERM: "the folder is not writable: fix its permissions or choose another output folder",
          errno.EROFS: "the file system is read-only: choose another output folder"}


def output_error(path, exc: OSError) -> OutputError:
    """An :class:`OutputError` for ``path`` from the OSError a write raised."""
    code = errno.errorcode.get(exc.errno, "") if exc.errno else ""
    reason = f"could not write: {exc.strerror or exc}" + (f" ({code})" if code else "")
    hint = _HINTS.get(exc.errno)
    return OutputError(path, reason + (f"; {hint}" if hint else ""))


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


def remove_stale_temps(folder) -> None:
    """Delete temporary files a killed writer left in ``folder`` (never renamed: never results)."""
    for p in Path(folder).glob(".*.tmp*"):
        p.unlink(missing_ok=True)


def fsync_dir(folder) -> None:
    """Make renames and removals in ``folder`` durable."""
    _fsync_dir(Path(folder))


def make_dirs(folder) -> Path:
    """``mkdir -p`` that reports a failure as :class:`OutputError` naming the folder."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(folder, exc) from exc
    return folder


def _replace(tmp: Path, path: Path) -> None:
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _abandon(tmp: Path, path: Path, exc: BaseException):
    """A write to ``tmp`` for ``path`` failed: remove the temporary, re-raise (an OSError as
    :class:`OutputError` naming ``path``, so the final file is never half-written)."""
    try:
        tmp.unlink(missing_ok=True)
    except OSError:
        pass
    if isinstance(exc, OSError):
        raise output_error(path, exc) from exc
    raise exc


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically; :class:`OutputError` (the file left as it was) on failure."""
    path = Path(path)
    tmp = temp_name(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        _replace(tmp, path)
    except BaseException as exc:
        _abandon(tmp, path, exc)


def atomic_write_text(path, text: str, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically (UTF-8 by default)."""
    atomic_write_bytes(path, text.encode(encoding))


@contextmanager
def atomic_path(path):
    """``with atomic_path(p) as tmp: write(tmp)`` -- for writers that want a file name (e.g.
    ``fig.savefig(tmp)``): ``tmp`` replaces ``p`` when the block ends without an exception, and is
    removed otherwise (an OSError becomes :class:`OutputError` naming ``p``)."""
    path = Path(path)
    tmp = temp_name(path, keep_suffix=True)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        _replace(tmp, path)
    except BaseException as exc:
        _abandon(tmp, path, exc)


@contextmanager
def atomic_folder(folder, overwrite: bool = False, what: str = "folder"):
    """Write a whole folder atomically (a survey run, a kapture): ``with atomic_folder(f) as tmp: fill(tmp)``.

    Yields a fresh ``folder.tmp`` to fill, renamed to ``folder`` when the block ends without an exception.

    Refuses (FileExistsError) when ``folder`` exists and ``overwrite`` is false: nothing written is
    lost silently. On an exception the partial ``.tmp`` is removed and ``folder`` (new or old) is
    untouched; an old ``folder`` is moved aside and deleted only after the new one is in place. A
    ``.tmp`` left by a killed process is removed on the next write.
    """
    folder = Path(folder)
    if folder.exists() and not overwrite:
        raise FileExistsError(f"{folder}: {what} already exists (pass overwrite=True to replace it)")
    tmp = folder.with_name(folder.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if folder.exists():
        old = folder.with_name(folder.name + ".old")
        if old.exists():
            shutil.rmtree(old)
        os.replace(folder, old)
        os.replace(tmp, folder)
        shutil.rmtree(old)
    else:
        os.replace(tmp, folder)
    _fsync_dir(folder.parent)
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
