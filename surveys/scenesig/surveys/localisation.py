"""One localised run: what ``scenesig localise`` holds in memory and writes, and reads back.

:class:`Localisation` is the one type for a run localised against a map -- the replay returns it
(:func:`scenesig.localiser.replay.replay`), the front door hands it out (:func:`scenesig.localise`),
``scenesig map update`` reads it back (:meth:`Localisation.from_folder`) and the localiser's outputs write
it.  It holds arrays, not text: the frame times, the poses ``(N, 4, 4)``, the pose graph's covariances, the
per-frame table (:data:`FRAMES_COLUMNS` as typed numpy columns) and the metrics dict.  Computing the
metrics and the errors against truth is the localiser's (:func:`scenesig.localiser.outputs.compute_metrics`);
it lives below the mapping layer because a map update consumes localisations.

The files (:meth:`Localisation.write`, each atomic, the trajectory first):

* ``trajectory.tum`` -- the estimate at every frame with a world pose (evo reads it);
* ``covariances.csv`` -- :data:`COVARIANCE_COLUMNS`: per pose of the trajectory the upper triangle of the
  planar ``(x, y, yaw)`` covariance in the world frame (:mod:`scenesig.localiser.uncertainty`);
* ``frames.csv`` -- :data:`FRAMES_COLUMNS`, one row per frame;
* ``metrics.json`` -- the metrics.

:meth:`Localisation.from_folder` reads exactly those (a :class:`DataError` naming the file when one is
missing or wrong); what only the replay knows (which frames the detector ran on, the solver's rejection
reasons, the 6x6 marginals, the integrity monitor's per-frame statistics) is not in the files and is None
or empty after a read.
"""
from __future__ import annotations

import csv
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .errors import DataError
from .io import atomic_write_text, make_dirs
from .run import SurveyRun
from .tum import format_tum, read_tum, write_tum
from .validation import csv_header

__all__ = ["FRAMES_COLUMNS", "BOUND_COLUMNS", "COVARIANCE_COLUMNS", "TIMING_KEYS", "Localisation",
           "read_frames_csv", "frames_csv_text", "read_covariances_csv", "covariances_csv_text"]

#: Columns of ``frames.csv`` (the errors are NaN without truth; the bounds NaN without a pose; ``integrity_alert``
#: 1 where the integrity monitor refused the frame's fix, :mod:`scenesig.localiser.integrity`).
FRAMES_COLUMNS = ("time", "place", "detections", "inliers", "localised", "lateral_error", "heading_error",
                  "distance_since_localisation", "lateral_bound_95_m", "longitudinal_bound_95_m",
                  "heading_bound_95_deg", "integrity_alert", "signature_inliers", "point_inliers")
#: the 95 % bounds (NaN without a pose)
BOUND_COLUMNS = FRAMES_COLUMNS[8:11]
#: integer columns (``place`` is -1 where no place was chosen) and flags; the rest are floats
_INT_COLUMNS = ("place", "detections", "inliers", "signature_inliers", "point_inliers")
_BOOL_COLUMNS = ("localised", "integrity_alert")
#: the columns an output folder written before the bounds existed has (still read)
_FRAMES_REQUIRED = FRAMES_COLUMNS[:8]
#: ``covariances.csv``'s columns: time, then the upper triangle of the planar (x, y, yaw) covariance
COVARIANCE_COLUMNS = ("time", "xx", "xy", "xyaw", "yy", "yyaw", "yawyaw")
#: ``metrics.json`` entries that measure the machine rather than the result (they differ between runs).
TIMING_KEYS = ("ms_per_detection", "ms_per_solve", "ms_per_odometry_update", "ms_per_retrieval", "realtime_factor",
               "wall_seconds", "cpu_seconds", "cpu_ms_per_frame")


def _column(name: str, values) -> np.ndarray:
    if name in _BOOL_COLUMNS:
        return np.nan_to_num(np.asarray(values, float)) != 0
    if name in _INT_COLUMNS:
        return np.nan_to_num(np.asarray(values, float)).astype(np.int64)
    return np.asarray(values, dtype=float)


def empty_frames(times) -> dict:
    """The per-frame table of ``times`` before anything is known: no place (-1), zero counts, NaN errors and bounds."""
    n = len(times)
    out = {c: _column(c, np.full(n, np.nan)) for c in FRAMES_COLUMNS}
    out["time"] = np.asarray(times, float)
    out["place"] = np.full(n, -1, dtype=np.int64)
    return out


def _fmt(v: float) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.6f}"


def frames_csv_text(frames: dict) -> str:
    """The text of ``frames.csv`` from a per-frame table (:data:`FRAMES_COLUMNS`)."""
    f = frames
    lines = [",".join(FRAMES_COLUMNS)]
    for i, t in enumerate(f["time"]):
        lines.append(",".join([f"{t:.6f}", *(str(int(f[c][i])) for c in ("place", "detections", "inliers",
                                                                        "localised")),
                               *(_fmt(f[c][i]) for c in ("lateral_error", "heading_error",
                                                         "distance_since_localisation", *BOUND_COLUMNS)),
                               *(str(int(f[c][i])) for c in ("integrity_alert", "signature_inliers",
                                                             "point_inliers"))]))
    return "\n".join(lines) + "\n"


def read_frames_csv(path) -> dict:
    """``frames.csv`` as ``{column: (N,) array}`` typed as :class:`Localisation` holds them (counts and
    ``place`` integers, ``localised`` and ``integrity_alert`` booleans, the rest floats); a :class:`DataError`
    naming the file and line when a column is missing or a value is not a number.  Folders written before
    the bounds, the integrity flag or the inlier types existed are read with those columns NaN / 0."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "missing")
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = csv_header(reader, path, _FRAMES_REQUIRED)
            cols: dict[str, list] = {h: [] for h in header}
            for ln, row in enumerate(reader, start=2):
                if not row:
                    continue
                if len(row) != len(header):
                    raise DataError(path, f"expected {len(header)} values, got {len(row)}", line=ln)
                for h, v in zip(header, row):
                    try:
                        cols[h].append(float(v))
                    except ValueError:
                        raise DataError(path, f"column {h!r}: {v!r} is not a number", line=ln) from None
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text: {exc}") from None
    out = empty_frames(cols["time"])
    out.update({h: _column(h, v) for h, v in cols.items()})
    return out


def covariances_csv_text(times, planar) -> str:
    """The text of ``covariances.csv`` (:data:`COVARIANCE_COLUMNS`), one row per (time, planar 3x3 covariance)."""
    P = np.asarray(planar, float).reshape(-1, 3, 3)
    iu = np.triu_indices(3)
    lines = [",".join(COVARIANCE_COLUMNS)]
    for t, c in zip(np.asarray(times, float), P):
        lines.append(",".join([f"{t:.9f}"] + [repr(float(v)) for v in c[iu]]))
    return "\n".join(lines) + "\n"


def read_covariances_csv(path) -> tuple[np.ndarray, np.ndarray]:
    """``(times (N,), covariances (N,3,3))`` of a ``covariances.csv``; DataError naming the file and line."""
    path = Path(path)
    times, rows = [], []
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            if tuple(header) != COVARIANCE_COLUMNS:
                raise DataError(path, f"header must be {','.join(COVARIANCE_COLUMNS)}, got {','.join(header)}",
                                line=1)
            for ln, row in enumerate(reader, start=2):
                if not row:
                    continue
                try:
                    vals = [float(v) for v in row]
                except ValueError:
                    raise DataError(path, "not a number", line=ln) from None
                if len(vals) != len(COVARIANCE_COLUMNS) or not np.all(np.isfinite(vals)):
                    raise DataError(path, f"expected {len(COVARIANCE_COLUMNS)} finite numbers", line=ln)
                times.append(vals[0])
                rows.append(vals[1:])
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text: {exc}") from None
    P = np.zeros((len(rows), 3, 3))
    iu = np.triu_indices(3)
    for k, r in enumerate(rows):
        P[k][iu] = r
        P[k] = P[k] + np.triu(P[k], 1).T
    return np.asarray(times), P


def _metrics_text(metrics: dict) -> str:
    return json.dumps(metrics, indent=2, allow_nan=False) + "\n"


@dataclass(kw_only=True, eq=False)
class Localisation:
    """One run localised against a map: per-frame arrays, the metrics, the settings (see the module docstring).

    Attributes
    ----------
    method, mode, every : the localisation method, ``"deterministic"`` or ``"realtime"``, the detector's
        frame step (None in real-time mode).
    times : (N,) frame times.
    poses : (N, 4, 4) estimates ``T_world_vehicle``; NaN where the localiser had no world pose (before a
        first fix without INS/GPS, or a fix the integrity monitor refused).
    valid : (N,) bool, the frames with a world pose.
    frames : the per-frame table, ``{column: (N,) array}`` of :data:`FRAMES_COLUMNS` (``place``, ``detections``,
        ``inliers`` ... as integers, ``localised``, ``integrity_alert`` as booleans; errors NaN without truth).
    covariances : (N, 6, 6) the pose graph's marginal of each pose (vehicle frame, GTSAM order), or None
        (read from a folder).
    planar_covariances : (N, 3, 3) covariance of ``(x, y, yaw)`` in the world frame, inflated as the bounds
        (``covariances.csv``), or None until the localiser computed it.
    resets : (N,) bool, an oracle reset happened since the previous frame.
    metrics : ``metrics.json``'s content, or None until the localiser evaluated the run.
    run : the live run (:class:`scenesig.surveys.run.SurveyRun`), or None (read from a folder).
    folder : where it was read from (None in memory).
    """

    method: str
    times: np.ndarray
    poses: np.ndarray
    frames: dict
    mode: str = "deterministic"
    every: int | None = None
    valid: np.ndarray | None = None
    resets: np.ndarray | None = None
    covariances: np.ndarray | None = None
    planar_covariances: np.ndarray | None = None
    metrics: dict | None = None
    run: SurveyRun | Any = None
    folder: Path | None = None
    # what the replay knows besides the files (also recorded in metrics.json where it matters)
    detector_ran: np.ndarray | None = None     # (N,) bool; None after a read
    reasons: list = field(default_factory=list)  # (N,) the solver's rejection reason or None
    failures: int = 0
    reset_times: list = field(default_factory=list)    # times of the oracle resets (odometry times)
    corrupt: dict = field(default_factory=dict)        # frame -> why its image failed strict decoding
    timings: dict = field(default_factory=dict)
    method_config: dict = field(default_factory=dict)  # the method's settings (WeakLocaliser.method_config)
    oracle: str = "ins"
    oracle_reads: int = 0
    first_fix_time: float | None = None     # oracle "none": the first pose found from the map
    relocalisations: list = field(default_factory=list)  # oracle "none": (t_lost, t_found) pairs
    settings: dict = field(default_factory=dict)   # every setting of the replay, resolved
    camera_check: dict | None = None        # what the camera check found (mapping.camera_check.assess)
    integrity_alerts: list = field(default_factory=list)   # localiser.integrity.Alert dicts
    integrity_stats: list = field(default_factory=list)    # localiser.integrity.FrameStats of every tracked frame
    integrity_probations: dict = field(default_factory=dict)  # probations started, accepted, refused
    # draws trajectory.png (path, localisation): set by the localiser, which has the map the figure shows
    figure: Callable | None = field(default=None, repr=False)

    def __post_init__(self):
        self.times = np.asarray(self.times, float)
        n = len(self.times)
        self.poses = np.asarray(self.poses, float).reshape(n, 4, 4)
        if self.valid is None:
            self.valid = np.isfinite(self.poses[:, :3, 3]).all(axis=1)
        self.valid = np.asarray(self.valid, bool)
        self.resets = np.zeros(n, dtype=bool) if self.resets is None else np.asarray(self.resets, bool)
        full = empty_frames(self.times)
        full.update({c: _column(c, v) for c, v in self.frames.items()})
        bad = {c: len(v) for c, v in full.items() if len(v) != n}
        if bad or self.valid.shape != (n,) or self.resets.shape != (n,):
            raise ValueError(f"{n} frame times but per-frame arrays of other lengths: {bad or 'valid/resets'}")
        self.frames = full

    def __repr__(self) -> str:
        run = getattr(self.run, "name", None) or (self.metrics or {}).get("run")
        return (f"Localisation(run={run!r}, method={self.method!r}, frames={len(self.times)}, "
                f"localised={int(np.sum(self.localised))}, failures={self.failures})")

    # the per-frame table's columns by name
    @property
    def places(self) -> np.ndarray:
        return self.frames["place"]

    @property
    def detections(self) -> np.ndarray:
        return self.frames["detections"]

    @property
    def inliers(self) -> np.ndarray:
        return self.frames["inliers"]

    @property
    def localised(self) -> np.ndarray:
        return self.frames["localised"]

    @property
    def distance_since_localisation(self) -> np.ndarray:
        return self.frames["distance_since_localisation"]

    @property
    def integrity_alert(self) -> np.ndarray:
        return self.frames["integrity_alert"]

    @property
    def signature_inliers(self) -> np.ndarray:
        return self.frames["signature_inliers"]

    @property
    def point_inliers(self) -> np.ndarray:
        return self.frames["point_inliers"]

    @property
    def bounds(self) -> dict:
        """``{column: (N,)}`` of the 95 % bounds (:data:`BOUND_COLUMNS`)."""
        return {c: self.frames[c] for c in BOUND_COLUMNS}

    def write(self, folder, figure: bool = True) -> dict:
        """Write ``trajectory.tum``, ``covariances.csv``, ``frames.csv`` and ``metrics.json`` into ``folder``
        (each atomically, the trajectory first), and ``trajectory.png`` with ``figure`` when the localiser
        attached its drawing; returns the metrics.  The metrics must be there (the localiser's evaluation,
        :func:`scenesig.localiser.outputs.evaluate_localisation`)."""
        if self.metrics is None:
            raise ValueError("no metrics yet: evaluate the localisation first "
                             "(scenesig.localiser.outputs.evaluate_localisation)")
        folder = make_dirs(folder)
        v = self.valid
        write_tum(folder / "trajectory.tum", self.times[v], self.poses[v])
        planar = self.planar_covariances
        if planar is None:
            planar = np.full((len(self.times), 3, 3), np.nan)
        atomic_write_text(folder / "covariances.csv", covariances_csv_text(self.times[v], planar[v]))
        self.write_results(folder)
        if figure and self.figure is not None:
            self.figure(folder / "trajectory.png", self)
        return self.metrics

    def write_results(self, folder) -> None:
        """``frames.csv`` and ``metrics.json`` only: what a later evaluation changes (the trajectory and its
        covariances are what the localiser produced and stay as written)."""
        folder = Path(folder)
        atomic_write_text(folder / "frames.csv", frames_csv_text(self.frames))
        atomic_write_text(folder / "metrics.json", _metrics_text(self.metrics))

    @classmethod
    def from_folder(cls, folder) -> Localisation:
        """Read what :meth:`write` wrote; a :class:`DataError` naming the file when one is missing or wrong
        (``covariances.csv`` may be missing: folders written before it existed)."""
        folder = Path(folder)
        metrics = _read_metrics(folder / "metrics.json")
        frames = read_frames_csv(folder / "frames.csv")
        n = len(frames["time"])
        ft = frames["time"]
        tpath = folder / "trajectory.tum"
        if not tpath.is_file():
            raise DataError(tpath, "missing")
        blind = metrics.get("oracle") == "none"
        if blind and not any(ln.strip() and not ln.lstrip().startswith("#")
                             for ln in tpath.read_text(encoding="utf-8").splitlines()):
            times, poses = np.zeros(0), np.zeros((0, 4, 4))     # never localised: no pose at all
        else:
            times, poses = read_tum(tpath)
        if len(times) != n and not blind:
            raise DataError(tpath, f"{len(times)} poses but frames.csv has {n} frames")
        # without INS/GPS there is no pose before the first fix, nor after the integrity monitor dropped one
        # (localiser.integrity): the trajectory holds the frames that have a pose
        k = np.clip(np.searchsorted(ft, times - 1e-3), 0, max(n - 1, 0))
        if len(times) > n or (len(times) and (np.max(np.abs(ft[k] - times)) > 1e-3 or np.any(np.diff(k) <= 0))):
            if len(times) == n:
                raise DataError(tpath, "times differ from frames.csv's")
            raise DataError(tpath, f"its {len(times)} poses are not at frames of frames.csv's {n}")
        full = np.full((n, 4, 4), np.nan)
        full[k] = poses.reshape(-1, 4, 4)
        valid = np.zeros(n, dtype=bool)
        valid[k] = True
        planar = np.full((n, 3, 3), np.nan)
        cpath = folder / "covariances.csv"
        if cpath.is_file():
            ct, cp = read_covariances_csv(cpath)
            if len(ct) != len(times) or (len(ct) and np.max(np.abs(ct - times)) > 1e-3):
                raise DataError(cpath, f"{len(ct)} rows not at trajectory.tum's {len(times)} poses")
            planar[k] = cp
        # a pose at every frame: the trajectory's times (more digits than frames.csv's)
        all_times = times if len(times) == n else ft
        resets = np.zeros(n, dtype=bool)
        for tr in metrics.get("reset_times") or []:     # as the replay marks them
            resets[min(int(np.searchsorted(all_times, tr, side="right")), n - 1)] = True
        return cls(method=metrics["method"], mode=metrics.get("mode", "deterministic"), every=metrics.get("every"),
                   times=all_times, poses=full, valid=valid, frames=frames, resets=resets, planar_covariances=planar,
                   metrics=metrics, folder=folder, failures=int(metrics.get("failures", 0)),
                   reset_times=list(metrics.get("reset_times") or []),
                   method_config=metrics.get("method_config") or {}, oracle=metrics.get("oracle", "ins"),
                   oracle_reads=int(metrics.get("oracle_reads", 0)), first_fix_time=metrics.get("first_fix_time"),
                   relocalisations=[tuple(p) for p in metrics.get("relocalisation_times") or []],
                   settings=metrics.get("settings") or {}, camera_check=metrics.get("camera_check"),
                   integrity_alerts=list(metrics.get("integrity_alert_list") or []))

    def digest(self) -> str:
        """SHA-256 of what the localisation found, not of the machine or the folders: the written trajectory
        and frames, and the metrics without timings and paths (what makes two map updates the same).
        Read from the folder's files when it was read from one."""
        h = hashlib.sha256()
        m = self.metrics or {}
        v = self.valid
        for name in ("metrics.json", "trajectory.tum", "frames.csv"):
            if name == "metrics.json":
                data = json.dumps({k: x for k, x in m.items() if k not in (*TIMING_KEYS, "map", "run_path")},
                                  sort_keys=True).encode()
            elif self.folder is not None:
                data = (self.folder / name).read_bytes()
            elif name == "frames.csv":
                data = frames_csv_text(self.frames).encode()
            else:
                data = format_tum(self.times[v], self.poses[v]).encode()
            h.update(hashlib.sha256(data).digest())
        return h.hexdigest()


def _read_metrics(mpath: Path) -> dict:
    if not mpath.is_file():
        raise DataError(mpath, "missing: not a `scenesig localise` output folder")
    try:
        metrics = json.loads(mpath.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DataError(mpath, f"invalid JSON: {exc.msg}", line=exc.lineno) from None
    except UnicodeDecodeError as exc:
        raise DataError(mpath, f"not UTF-8 text: {exc}") from None
    if not isinstance(metrics, dict) or "method" not in metrics or "run" not in metrics:
        raise DataError(mpath, "expected an object with at least 'method' and 'run'")
    return metrics
