"""TUM trajectory files: ``t tx ty tz qx qy qz qw`` per line, '#' comments allowed.

Kept apart from the math (as evo does): this module only reads and writes; poses come back as
4x4 matrices via :mod:`scenesig.surveys.geometry`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import DataError
from .geometry import pose_to_xyzquat, xyzquat_to_pose
from .io import atomic_write_text

__all__ = ["read_tum", "write_tum", "format_tum"]


def read_tum(path, require_increasing: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file.

    Returns
    -------
    times : (N,) float64
    poses : (N, 4, 4) float64, ``T_world_body``

    Raises
    ------
    DataError
        Naming the file and line of the first problem: wrong column count, non-numbers, NaN/inf,
        a zero quaternion, or (by default) timestamps that do not strictly increase.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "file not found")
    rows, lines = [], []
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not a text file ({exc})") from None
    for n, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise DataError(path, f"expected 8 columns 't tx ty tz qx qy qz qw', found {len(parts)}", n)
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise DataError(path, f"non-numeric value in {s!r}", n) from None
        if not np.all(np.isfinite(vals)):
            raise DataError(path, "NaN or infinite value", n)
        if np.linalg.norm(vals[4:]) < 1e-9:
            raise DataError(path, "zero quaternion", n)
        if require_increasing and rows and vals[0] <= rows[-1][0]:
            raise DataError(path, f"timestamp {vals[0]!r} does not increase (previous {rows[-1][0]!r}, "
                                  f"line {lines[-1]})", n)
        rows.append(vals)
        lines.append(n)
    if not rows:
        raise DataError(path, "no poses")
    arr = np.asarray(rows)
    return arr[:, 0], xyzquat_to_pose(arr[:, 1:]).reshape(-1, 4, 4)


def format_tum(times, poses) -> str:
    """TUM text for times (N,) and poses (N,4,4); full float precision so a round trip is exact-ish."""
    times = np.asarray(times, dtype=float).reshape(-1)
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    if len(times) != len(poses):
        raise ValueError(f"{len(times)} times but {len(poses)} poses")
    xyzq = pose_to_xyzquat(poses).reshape(-1, 7)
    out = []
    for t, r in zip(times, xyzq):
        out.append(" ".join([f"{t:.9f}"] + [repr(float(v)) for v in r]))
    return "\n".join(out) + "\n"


def write_tum(path, times, poses) -> None:
    """Write a TUM file atomically (temp file + rename): a crash never leaves half a trajectory."""
    atomic_write_text(path, format_tum(times, poses))
