"""The one input-validation module: poses, covariances, images (as scikit-learn's ``utils.validation``).

Library functions check their array inputs here, so the same mistake gets the same message everywhere:
the argument's name, the expected shape and what is wrong.  Each check returns the input as a float (or
image) array, so callers write ``T = check_pose(T, "T_world_place")``.  Bad *files* are reported as
:class:`scenesig.surveys.errors.DataError` by the readers (:func:`csv_header` is their shared check of a CSV file's
header); the array checks raise ``ValueError`` for bad arguments.
"""
from __future__ import annotations

import numpy as np

__all__ = ["check_array", "check_pose", "check_poses", "check_covariance", "check_image", "csv_header"]


def csv_header(reader, path, required) -> list[str]:
    """The stripped header row of a CSV file being read with ``reader`` (a :func:`csv.reader`); raises
    :class:`scenesig.surveys.errors.DataError` naming ``path`` when the file is empty or lacks a ``required`` column."""
    from scenesig.surveys.errors import DataError

    header = next(reader, None)
    if header is None:
        raise DataError(path, "empty file")
    header = [h.strip() for h in header]
    missing = [c for c in required if c not in header]
    if missing:
        raise DataError(path, f"missing column(s) {', '.join(missing)}; header is {header}", 1)
    return header


def check_array(a, shape: tuple, name: str) -> np.ndarray:
    """``a`` as a finite float array of ``shape`` (``None`` in ``shape``: any length on that axis)."""
    a = np.asarray(a, dtype=float)
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = tuple("N" if s is None else s for s in shape)
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


_I3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def check_pose(T, name: str = "pose", rigid: bool = False, atol: float = 1e-6) -> np.ndarray:
    """A finite 4x4 pose; with ``rigid``, also an orthonormal rotation and a ``[0, 0, 0, 1]`` last row."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 pose, got shape {T.shape}")
    # np.allclose's test (|a - b| <= atol + 1e-5 |b|) written out: the localiser checks every
    # odometry increment, and allclose's generality costs more than the test itself.
    if rigid and (not (np.abs(T[:3, :3] @ T[:3, :3].T - _I3) <= atol + 1e-5 * _I3).all()
                  or not (np.abs(T[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all()):
        raise ValueError(f"{name} is not a rigid transform (rotation not orthonormal or bad last row)")
    return T


def check_poses(T, name: str = "poses", n: int | None = None) -> np.ndarray:
    """A finite (N, 4, 4) stack of poses (N = ``n`` when given)."""
    return check_array(T, (n, 4, 4), name)


def check_covariance(M, dim: int, name: str = "covariance", symmetrise: bool = False) -> np.ndarray:
    """A finite, positive definite ``dim`` x ``dim`` matrix (Cholesky test); with ``symmetrise`` the
    symmetric part ``(M + M^T) / 2`` is checked and returned."""
    M = np.asarray(M, dtype=float)
    if M.shape != (dim, dim) or not np.all(np.isfinite(M)):
        raise ValueError(f"{name} must be a finite {dim}x{dim} matrix, got shape {M.shape}")
    if symmetrise:
        M = 0.5 * (M + M.T)
    try:
        np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        raise ValueError(f"{name} must be positive definite, got {M.tolist()}") from None
    return M


def check_image(img, name: str = "image", uint8: bool = False) -> np.ndarray:
    """A non-empty gray (H, W) or colour (H, W, C) image array (``uint8`` when asked)."""
    a = np.asarray(img)
    if a.ndim not in (2, 3) or a.size == 0:
        raise ValueError(f"{name}: expected a gray or BGR image array, got shape {a.shape}")
    if uint8 and a.dtype != np.uint8:
        raise ValueError(f"{name} must be a uint8 gray or BGR image, got {a.dtype} {a.shape}")
    return a
