"""Vet a survey run before a long job: every file parsed, every image decoded strictly, timing sane.

:func:`check_run` does not stop at the first problem as :func:`scenesig.surveys.run.read_run` does: it reads
each file on its own and reports every problem it finds as a :class:`Problem` (file, line, reason),
so one pass over a copied camera log lists everything to fix.

Checked:

* ``run.toml``, ``frames.csv``, ``odometry.csv``, ``gps.csv`` and the TUM files parse, by the rules of
  :func:`scenesig.surveys.run.read_run` -- but a bad line does not end the file's check: every line is checked
  (column count, numbers, NaN/inf, quaternions) and every step where the timestamps do not increase is
  reported, so both a NaN and unsorted timestamps in one ``odometry.csv`` are listed (at most
  :data:`MAX_PER_KIND` lines per problem and file, then a count), and the images of a ``frames.csv``
  with a bad line are still checked (those of its readable lines);
* every image listed in ``frames.csv`` decodes strictly (:mod:`scenesig.surveys.images`) at the size
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

__all__ = ["Problem", "check_run", "is_run", "DEFAULT_MAX_GAP_S", "RATE_TOLERANCE", "MAX_PER_KIND"]

#: Default longest tolerated interval (s) between two samples of a stream.
DEFAULT_MAX_GAP_S = 1.0
#: Relative difference between a stream's measured and nominal rate above which it is reported.
RATE_TOLERANCE = 0.10

#: Lines reported per kind of problem in one file; the rest are counted in one more line.
MAX_PER_KIND = 5

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


class _Found:
    """Problems of one file, grouped by kind so each kind lists at most :data:`MAX_PER_KIND` lines."""

    def __init__(self, path: Path):
        self.path = path
        self._kinds: dict[str, list] = {}

    def add(self, kind: str, line: int | None, reason: str) -> None:
        self._kinds.setdefault(kind, []).append((line, reason))

    def problems(self) -> list[Problem]:
        out = []
        for kind, items in self._kinds.items():
            out += [Problem(str(self.path), line, reason) for line, reason in items[:MAX_PER_KIND]]
            if len(items) > MAX_PER_KIND:
                out.append(Problem(str(self.path), None, f"{kind}: {len(items) - MAX_PER_KIND} more lines"))
        return sorted(out, key=lambda p: (p.line is None, p.line or 0))


def _scan_table(path: Path, header: list[str] | None, n_numeric: int, tum: bool = False):
    """Every line of a CSV (``header``; the first ``n_numeric`` columns numbers) or TUM file checked.

    Returns ``(problems, lines, values, texts)``: the readable lines' numbers, their numeric columns
    (K, n_numeric) and their remaining columns; the problems of every other line, and every step where
    the timestamps (first column) do not strictly increase.
    """
    import csv
    import math

    found = _Found(path)
    lines, values, texts = [], [], []
    if not path.is_file():
        return [Problem(str(path), None, "file not found")], [], np.zeros((0, n_numeric)), []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        return [Problem(str(path), None, f"not UTF-8 text ({exc.reason} at byte {exc.start})")], [], \
            np.zeros((0, n_numeric)), []
    raw = text.splitlines()
    if tum:
        rows = [(n, s.replace(",", " ").split()) for n, s in enumerate((r.strip() for r in raw), start=1)
                if s and not s.startswith("#")]
        width = 8
    else:
        try:
            parsed = list(csv.reader(raw))
        except csv.Error as exc:
            return [Problem(str(path), None, f"not valid CSV ({exc})")], [], np.zeros((0, n_numeric)), []
        if not parsed:
            return [Problem(str(path), 1, "empty file")], [], np.zeros((0, n_numeric)), []
        if [h.strip() for h in parsed[0]] != header:
            found.add("header", 1, f"header must be {','.join(header)!r}, found {','.join(parsed[0])!r}")
        rows = [(n, [c.strip() for c in r]) for n, r in enumerate(parsed[1:], start=2)
                if r and any(c.strip() for c in r)]
        width = len(header)
    for n, row in rows:
        if len(row) != width:
            found.add("column count", n, f"expected {width} columns, found {len(row)}")
            continue
        try:
            nums = [float(v) for v in row[:n_numeric]]
        except ValueError:
            found.add("non-numeric", n, f"non-numeric value in {','.join(row)!r}")
            continue
        if not all(math.isfinite(x) for x in nums):
            found.add("NaN", n, "NaN or infinite value")
            continue
        if n_numeric >= 8:
            q = float(np.linalg.norm(nums[4:8]))
            if not q > 1e-9:
                found.add("quaternion", n, "zero or non-normalisable quaternion")
                continue
        lines.append(n)
        values.append(nums)
        texts.append(row[n_numeric:])
    if not rows:
        found.add("empty", None, "no data rows" if not tum else "no poses")
    vals = np.asarray(values, dtype=float).reshape(-1, n_numeric)
    if len(vals):
        for k in np.flatnonzero(np.diff(vals[:, 0]) <= 0) + 1:
            found.add("order", lines[k], f"timestamps must strictly increase: {float(vals[k, 0])!r} after "
                                          f"{float(vals[k - 1, 0])!r} (line {lines[k - 1]})")
    return found.problems(), lines, vals, texts


def _scan_frames(path: Path, problems: list):
    """``frames.csv``: (times, files, lines) of its readable lines (the images listed there get checked
    even when other lines are bad), its problems appended to ``problems``; None when nothing is readable."""
    found, lines, vals, texts = _scan_table(path, ["timestamp", "file"], 1)
    files = []
    for n, t in zip(lines, texts):
        f = t[0]
        if not f or Path(f).is_absolute() or ".." in Path(f).parts:
            found.append(Problem(str(path), n, f"image file {f!r} must be a path inside the run folder"))
        files.append(f)
    problems += sorted(found, key=lambda p: (p.line is None, p.line or 0))
    if not lines:
        return None
    keep = [i for i, f in enumerate(files) if f and not Path(f).is_absolute() and ".." not in Path(f).parts]
    return vals[keep, 0], [files[i] for i in keep], [lines[i] for i in keep]


def _scan_times(path: Path, header, n_numeric: int, problems: list, tum: bool = False):
    """Times of the readable lines of ``odometry.csv``, ``gps.csv`` or a TUM file (None when none), its
    problems appended to ``problems``."""
    found, lines, vals, _ = _scan_table(path, header, n_numeric, tum=tum)
    problems += found
    return vals[:, 0] if len(lines) else None


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
    from .run import read_meta

    root = Path(folder)
    problems: list[Problem] = []
    stats = {"frames": 0, "images_checked": 0, "odometry_samples": 0, "duration_s": 0.0}
    if not root.is_dir():
        return [Problem(str(root), None, "survey run folder not found")], stats
    meta = _attempt(problems, read_meta, root / "run.toml")
    frames = _scan_frames(root / "frames.csv", problems)
    odo_t = _scan_times(root / "odometry.csv", ["timestamp", "x", "y", "z", "qx", "qy", "qz", "qw"], 8, problems)
    odo = None if odo_t is None else (np.sort(odo_t),)
    streams = {}
    if frames is not None:
        order = np.argsort(frames[0], kind="stable")      # unsorted lines are reported above; time them sorted
        streams["images"] = (frames[0][order], np.asarray(frames[2])[order])
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
            tum_t = _scan_times(root / name, None, 8, problems, tum=True)
            if tum_t is not None and name == "groundtruth.tum":
                streams["INS/GPS poses"] = (np.sort(tum_t), None)
    if (root / "gps.csv").exists():
        gps_t = _scan_times(root / "gps.csv", ["timestamp", "x", "y", "z"], 4, problems)
        if gps_t is not None:
            streams["GPS fixes"] = (np.sort(gps_t), None)
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
