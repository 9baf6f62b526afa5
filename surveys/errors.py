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
