"""Helpers every importer shares: image checks, gaps, rates, and odometry noise."""
from __future__ import annotations

from decimal import Decimal
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ..errors import DataError

__all__ = ["TIMESTAMP_UNITS", "ticks_to_seconds", "read_rows", "numbers", "checked_image_bytes", "find_gaps",
           "nominal_rate", "planar_dead_reckoning", "odometry_with_noise", "odometry_note",
           "odometry_from_groundtruth", "write_imported"]


def read_rows(path, min_cols: int, sep: str | None = ",") -> list[tuple[int, list[str]]]:
    """``[(line number, fields)]`` of a text table; blank and ``#`` lines skipped, fields stripped.

    ``sep`` None splits on whitespace. A row with fewer than ``min_cols`` fields is a DataError naming
    the line (a truncated line is the usual cause).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text ({exc})") from None
    rows = []
    for n, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        fields = [f.strip() for f in s.split(sep)]
        if len(fields) < min_cols:
            raise DataError(path, f"expected at least {min_cols} values, found {len(fields)} -- truncated line?", n)
        rows.append((n, fields))
    return rows


def numbers(path, line: int, fields: list[str]) -> list[float]:
    """Finite floats of ``fields`` or a DataError naming the file and line."""
    try:
        vals = [float(f) for f in fields]
    except ValueError:
        raise DataError(path, f"non-numeric value in {', '.join(fields)!r}", line) from None
    if not all(np.isfinite(vals)):
        raise DataError(path, "NaN or infinite value", line)
    return vals


def checked_image_bytes(paths: Iterable[Path], size: tuple[int, int] | None = None,
                        transform=None, jpeg_quality: int = 95, progress: str | None = None) -> Iterator[bytes]:
    """Yield each image file's bytes after decoding it once (a corrupt image fails at import, not later).

    Parameters
    ----------
    paths : image files (JPEG or PNG) in frame order.
    size : ``(width, height)`` every image must have (the camera's calibrated size), or None.
    transform : optional ``f(index, image) -> image`` applied to the decoded image, which is then
        re-encoded (JPEG at ``jpeg_quality`` or PNG, as the source); without it the source bytes
        are kept bit for bit.
    progress : tqdm description, or None for no progress bar.
    """
    import cv2
    from tqdm import tqdm

    paths = list(paths)
    for i, path in enumerate(tqdm(paths, desc=progress, unit="frame", disable=progress is None)):
        try:
            data = Path(path).read_bytes()
        except OSError as exc:
            raise DataError(path, f"cannot read image ({exc.strerror})") from None
        # OpenCV decodes a truncated file into a partly grey image without an error: check the end marker
        if data[:3] == b"\xff\xd8\xff" and not data.rstrip(b"\x00\n\r")[-2:] == b"\xff\xd9":
            raise DataError(path, "truncated JPEG (no end-of-image marker)")
        if data[:4] == b"\x89PNG" and b"IEND" not in data[-12:]:
            raise DataError(path, "truncated PNG (no IEND chunk)")
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise DataError(path, "not a decodable JPEG or PNG image")
        h, w = img.shape[:2]
        if size is not None and (w, h) != tuple(size):
            raise DataError(path, f"image is {w}x{h} but the calibration says {size[0]}x{size[1]}")
        if transform is None:
            yield data
            continue
        out = transform(i, img)
        ext = ".png" if str(path).lower().endswith(".png") else ".jpg"
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if ext == ".jpg" else []
        ok, enc = cv2.imencode(ext, out, params)
        if not ok:
            raise OSError(f"{path}: could not re-encode the transformed image")
        yield enc.tobytes()


TIMESTAMP_UNITS = {"ns": -9, "us": -6, "ms": -3, "s": 0}  # power of ten of one tick, in seconds


def ticks_to_seconds(ticks, unit: str = "ns") -> np.ndarray:
    """Integer timestamps -> float seconds, correctly rounded (nanoseconds since 1970 exceed float64's 2^53)."""
    exp = TIMESTAMP_UNITS[unit]
    return np.array([float(Decimal(int(t)).scaleb(exp)) for t in np.atleast_1d(ticks)], dtype=float)


def nominal_rate(times: np.ndarray) -> float:
    """Rate (Hz) from the median sampling interval (robust to dropped samples)."""
    d = np.diff(np.asarray(times, dtype=float))
    return float(1.0 / np.median(d)) if len(d) else 1.0


def find_gaps(times: np.ndarray, factor: float = 1.5) -> list[list[float]]:
    """``[[t_before, t_after], ...]`` where an interval exceeds ``factor`` times the median: dropped samples.

    Gaps are reported (run metadata, the import summary), never filled: a frame or pose invented
    between two real ones would look like a measurement.
    """
    t = np.asarray(times, dtype=float)
    if len(t) < 3:
        return []
    d = np.diff(t)
    idx = np.nonzero(d > factor * np.median(d))[0]
    return [[float(t[i]), float(t[i + 1])] for i in idx]


def planar_dead_reckoning(times: np.ndarray, v_forward: np.ndarray, v_left: np.ndarray,
                          yaw_rate: np.ndarray) -> np.ndarray:
    """Poses ``T_odom_vehicle`` (N,4,4) from body-frame speeds and yaw rate, as a wheel odometer integrates.

    Between samples the mean of the two speeds and yaw rates is held (trapezoid rule) and the
    translation is taken along the mid-interval heading (exact for a constant-curvature arc to second
    order). The motion is planar (z, roll and pitch stay zero), as a wheel odometer's is; the first
    pose is the identity. Across a gap the same rule bridges the interval: the integral is continuous
    even where samples were dropped.
    """
    t = np.asarray(times, dtype=float)
    vf, vl, w = (np.asarray(a, dtype=float) for a in (v_forward, v_left, yaw_rate))
    dt = np.diff(t)
    vf_m, vl_m, w_m = (0.5 * (a[1:] + a[:-1]) for a in (vf, vl, w))
    dth = w_m * dt
    half = 0.5 * dth
    dx = (vf_m * np.cos(half) - vl_m * np.sin(half)) * dt
    dy = (vf_m * np.sin(half) + vl_m * np.cos(half)) * dt
    out = np.tile(np.eye(4), (len(t), 1, 1))
    x = y = th = 0.0
    for k in range(len(dt)):
        c, s = np.cos(th), np.sin(th)
        x, y = x + c * dx[k] - s * dy[k], y + s * dx[k] + c * dy[k]
        th += dth[k]
        out[k + 1, :2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
        out[k + 1, :2, 3] = x, y
    return out


def odometry_with_noise(poses: np.ndarray, factor: float = 0.0, seed: int = 0) -> np.ndarray:
    """Odometry poses that drift from ``poses`` as a real odometer does; ``factor`` 0 returns them as they are.

    The error model is the simulator's VO model (:func:`scenesig.surveys.sim.motion.perturb_odometry`; factor 1
    ≈ 0.5 % scale bias, 0.4°/100 m heading drift and 0.25°/√100 m heading random walk), so an
    imported run and a simulated one drift alike at the same factor. Seeded: the same seed gives the
    same drift.
    """
    poses = np.asarray(poses, dtype=float)
    if factor < 0 or not np.isfinite(factor):
        raise ValueError(f"odometry noise factor must be >= 0, got {factor}")
    if factor == 0:
        return poses.copy()
    from ..sim.motion import perturb_odometry

    return perturb_odometry(poses, np.random.default_rng(seed), factor)


def write_imported(run, sources: list[Path], out, overwrite: bool = False, progress: bool = True,
                   photometric: str | dict | None = None) -> Path:
    """Write an imported run (from an importer's ``load_*``) with its source images to ``out``, atomically.

    Each image is decoded once to check it; the source bytes are written unchanged unless
    ``photometric`` asks for a transform (a preset of :data:`.photometric.PRESETS`, or a dict of
    :data:`.photometric.NIGHT` keys),
    which is recorded in the run's metadata.
    """
    from ..run import write_run

    transform = None
    if photometric is not None:
        from .photometric import photometric_transform

        transform, desc = photometric_transform(photometric)
        run.metadata["photometric_transform"] = desc
    images = checked_image_bytes(sources, run.camera.size, transform=transform,
                                 progress=f"import {run.name}" if progress else None)
    return write_run(run, out, images=images, overwrite=overwrite)


def odometry_note(source: str, conf: dict) -> dict:
    """The run metadata that says where the odometry came from and how it was perturbed."""
    noise = float(conf["odometry_noise"])
    text = source + (f"; perturbed by the VO error model x{noise} (seed {conf['odometry_seed']})" if noise else "")
    return {"odometry": text, "odometry_noise": noise, "odometry_seed": int(conf["odometry_seed"])}


def odometry_from_groundtruth(poses: np.ndarray, conf: dict, what: str = "the ground truth"):
    """(odometry poses, ``odometry_source``, metadata) for formats without an odometer: the ground truth,
    drifted by ``conf['odometry_noise']`` -- stated as not independent in both the source and the note."""
    noise = float(conf["odometry_noise"])
    odo = odometry_with_noise(poses, noise, int(conf["odometry_seed"]))
    return odo, "groundtruth" + ("+noise" if noise else ""), odometry_note(f"{what} itself: NOT an independent sensor", conf)
