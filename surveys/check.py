"""Vet a survey run before a long job: every file parsed, every image decoded strictly, timing sane.

:func:`check_run` does not stop at the first problem as :func:`surveys.run.read_run` does: it reads
each file on its own and reports every problem it finds as a :class:`Problem` (file, line, reason),
so one pass over a copied camera log lists everything to fix.

Checked:

* ``run.toml``, ``frames.csv``, ``odometry.csv``, ``gps.csv`` and the TUM files parse (the same
  readers and rules as :func:`surveys.run.read_run`);
* every image listed in ``frames.csv`` decodes strictly (:mod:`surveys.images`) at the size
  ``run.toml`` states;
* rates: each stream's measured rate (median interval) against its nominal rate in ``run.toml``
  (``camera_hz``, ``odometry_hz``, ``ins_hz``, ``gps_hz``) -- more than 10 % off is a warning;
* coverage: a gap longer than ``max_gap_s`` between two images, two odometry samples or two INS/GPS
  poses is an error (the localiser runs blind over it); frames outside the odometry's time span are
  a warning (their poses are clamped, not measured).

Errors make ``scenesig check`` exit 2; warnings are printed but do not.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .errors import CorruptImageError, DataError

__all__ = ["Problem", "check_run", "is_run", "DEFAULT_MAX_GAP_S", "RATE_TOLERANCE"]

#: Default longest tolerated interval (s) between two samples of a stream.
DEFAULT_MAX_GAP_S = 1.0
#: Relative difference between a stream's measured and nominal rate above which it is reported.
RATE_TOLERANCE = 0.10

#: Stream name -> (file, key of its nominal rate in run.toml's [rates]).
_STREAMS = {"images": ("frames.csv", "camera_hz"), "odometry": ("odometry.csv", "odometry_hz"),
            "INS/GPS poses": ("groundtruth.tum", "ins_hz"), "GPS fixes": ("gps.csv", "gps_hz")}


@dataclass(frozen=True)
class Problem:
    """One problem: the file, the 1-based line (None: the whole file), the reason and its severity."""

    file: str
    line: int | None
    reason: str
    severity: str = "error"        # "error" (exit 2) or "warning"

    def __str__(self) -> str:
        where = self.file + (f":{self.line}" if self.line is not None else "")
        return f"{where}: {self.severity}: {self.reason}"

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_error(cls, exc: DataError) -> "Problem":
        return cls(str(exc.path) if exc.path is not None else "<input>", exc.line, exc.message)


def is_run(folder) -> bool:
    """True if ``folder`` looks like a survey run (has ``run.toml`` or ``frames.csv``)."""
    folder = Path(folder)
    return (folder / "run.toml").is_file() or (folder / "frames.csv").is_file()


def _attempt(problems: list, fn, *args):
    try:
        return fn(*args)
    except DataError as exc:
        problems.append(Problem.from_error(exc))
        return None


def _decode_all(root: Path, files, lines, camera, jobs: int, progress: bool, name: str) -> list[Problem]:
    """Strictly decode every image (threads: libjpeg-turbo and OpenCV release the GIL)."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from .images import read_image

    def one(item):
        n, f = item
        path = root / f
        try:
            img = read_image(path, gray=True)
        except CorruptImageError as exc:
            return Problem(str(path), None, f"{exc.message} (frames.csv line {n})")
        if camera is not None and img.shape[:2] != (camera.height, camera.width):
            return Problem(str(path), None, f"image is {img.shape[1]}x{img.shape[0]} but run.toml says "
                                            f"{camera.width}x{camera.height} (frames.csv line {n})")
        return None

    out = []
    with ThreadPoolExecutor(max_workers=max(1, int(jobs))) as pool:
        for p in tqdm(pool.map(one, list(zip(lines, files)), chunksize=8), total=len(files), unit="image",
                      desc=f"check {name}", disable=not progress):
            if p is not None:
                out.append(p)
    return out


def _timing(path: Path, times: np.ndarray, lines, nominal: float | None, rate_key: str, meta_path: Path,
            what: str, max_gap_s: float) -> list[Problem]:
    out = []
    if len(times) < 2:
        return out
    dt = np.diff(times)
    if nominal:
        measured = 1.0 / float(np.median(dt))
        if abs(measured / nominal - 1.0) > RATE_TOLERANCE:
            out.append(Problem(str(meta_path), None, f"rates.{rate_key} is {nominal:g} Hz but {path.name} has "
                                                     f"{measured:.3g} Hz (median interval {np.median(dt):.4g} s)",
                               "warning"))
    for k in np.flatnonzero(dt > max_gap_s):
        out.append(Problem(str(path), None if lines is None else int(lines[k + 1]),
                           f"gap of {dt[k]:.3f} s in the {what} ({float(times[k])!r} -> {float(times[k + 1])!r}; "
                           f"longest allowed {max_gap_s:g} s)"))
    return out


def check_run(folder, max_gap_s: float = DEFAULT_MAX_GAP_S, images: bool = True, jobs: int = 1,
              progress: bool = False) -> tuple[list[Problem], dict]:
    """Every problem of a survey-run folder, and counts of what was checked.

    Parameters
    ----------
    folder : the run folder.
    max_gap_s : longest tolerated interval between two samples of a stream (images, odometry, INS/GPS).
    images : decode every image strictly (the slow part: ~3 ms per VGA frame).
    jobs : threads decoding images.

    Returns
    -------
    problems : list of Problem, in file order.
    stats : ``{"frames": int, "images_checked": int, "odometry_samples": int, "duration_s": float}``.
    """
    from .run import read_frames, read_gps, read_meta, read_odometry
    from .tum import read_tum

    root = Path(folder)
    problems: list[Problem] = []
    stats = {"frames": 0, "images_checked": 0, "odometry_samples": 0, "duration_s": 0.0}
    if not root.is_dir():
        return [Problem(str(root), None, "survey run folder not found")], stats
    meta = _attempt(problems, read_meta, root / "run.toml")
    frames = _attempt(problems, read_frames, root / "frames.csv")
    odo = _attempt(problems, read_odometry, root / "odometry.csv")
    streams = {}
    if frames is not None:
        streams["images"] = (frames[0], frames[2])
        stats["frames"] = len(frames[0])
        if images:
            problems += _decode_all(root, frames[1], frames[2], meta["camera"] if meta else None, jobs, progress,
                                    root.name)
            stats["images_checked"] = len(frames[1])
    if odo is not None:
        streams["odometry"] = (odo[0], None)
        stats["odometry_samples"] = len(odo[0])
    for name in ("groundtruth.tum", "truth.tum"):
        if (root / name).exists():
            tum = _attempt(problems, read_tum, root / name)
            if tum is not None and name == "groundtruth.tum":
                streams["INS/GPS poses"] = (tum[0], None)
    if (root / "gps.csv").exists():
        gps = _attempt(problems, read_gps, root / "gps.csv")
        if gps is not None:
            streams["GPS fixes"] = (gps[:, 0], None)
    rates = meta["rates"] if meta else {}
    for what, (times, lines) in streams.items():
        fname, key = _STREAMS[what]
        problems += _timing(root / fname, times, lines, rates.get(key), key, root / "run.toml", what, max_gap_s)
    if frames is not None and odo is not None:
        ft, fl = frames[0], frames[2]
        outside = np.flatnonzero((ft < odo[0][0]) | (ft > odo[0][-1]))
        if len(outside):
            problems.append(Problem(str(root / "frames.csv"), int(fl[outside[0]]),
                                    f"{len(outside)} frames lie outside the odometry's time span "
                                    f"({float(odo[0][0])!r} .. {float(odo[0][-1])!r}): their poses are clamped",
                                    "warning"))
    spans = [t for t, _ in streams.values() if len(t)]
    if spans:
        stats["duration_s"] = float(max(t[-1] for t in spans) - min(t[0] for t in spans))
    return problems, stats
