"""Errors for bad input: every message names the file (and line, where there is one)."""
from __future__ import annotations

from pathlib import Path


class DataError(ValueError):
    """Bad or missing input data.

    Parameters
    ----------
    path : file the problem is in.
    message : what is wrong.
    line : 1-based line number, where it applies.
    """

    def __init__(self, path, message: str, line: int | None = None):
        self.path = Path(path) if path is not None else None
        self.line = line
        self.message = message
        where = f"{self.path}" if self.path is not None else "<input>"
        if line is not None:
            where += f":{line}"
        super().__init__(f"{where}: {message}")

    def __reduce__(self):
        # picklable with its fields, so a DataError raised in a joblib / Dask worker reaches the driver
        # as itself (the default would call __init__ with the formatted message only)
        return (self.__class__, (self.path, self.message, self.line))


class CorruptImageError(DataError):
    """An image that is missing, truncated or does not decode cleanly (see :mod:`scenesig.surveys.images`).

    A separate type because a corrupt camera frame is often survivable: the localiser skips the
    frame, and ``build-map --skip-corrupt`` leaves it out, where any other bad input stops the job.
    """


class OutputError(DataError):
    """A result could not be written (disk full, read-only folder...).

    A :class:`DataError` so that the command line's one error handler reports it as
    ``scenesig: error: FILE: reason`` (exit 2) instead of a traceback; ``path`` is the file that was
    being written, which is left as it was (see :mod:`scenesig.surveys.io`).
    """
