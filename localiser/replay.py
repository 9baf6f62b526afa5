"""Replay a survey run through the online localiser: ``scenesig localise MAP RUN --out DIR``.

Two modes (issue 5 §1):

* **deterministic** (default): images and odometry are fed in timestamp order on one thread; the
  detector runs on every ``every``-th frame (4: 5 Hz on a 20 Hz camera, as in the paper) and the
  output is the same on every run.  A frame is processed once the odometry covers its timestamp
  (as a vehicle buffers an image until the odometry that spans it arrives), so the motion prior is
  interpolated, never extrapolated.  The blocks run in that order on the main thread; only the
  next detector frame's decoding and image-only preparation (:meth:`WeakLocaliser.prepare`, e.g.
  ORB/SIFT extraction) run ahead on a worker thread, which changes no result.
* **real-time** (``--realtime``): the data are played at their own timestamps (``speed`` times
  faster if asked); the detector and the solver run in their own threads, each fed through a
  one-slot mailbox that keeps only the newest item, so a frame that arrives while the detector is
  busy replaces the waiting one (stale frames are dropped, as on a vehicle).  Odometry is integrated
  at its full rate on the feeding thread; localisations are added to the pose graph whenever the
  solver finishes (possibly a few frames late; the graph carries them to the right time).

Outputs in DIR: ``trajectory.tum`` (the estimate at every frame time; evo reads it),
``frames.csv`` (time, place, detections, inliers, localised, lateral_error, heading_error,
distance_since_localisation), ``metrics.json`` (see :func:`compute_metrics`) and ``trajectory.png``
(estimate, truth and INS/GPS on the map; lateral error over distance with the stretches within 10 m
of a localisation shaded and the resets marked).

Timings in ``metrics.json``: ``ms_per_detection`` is the detector block per frame (for point
features including the extraction, wherever it ran), ``ms_per_solve`` the solver, and
``realtime_factor`` the data duration over the wall time of the replay loop alone (opening the map
and the run, the evaluation and writing the outputs are not counted).

The run's INS/GPS poses (``groundtruth.tum``) are the *oracle* (``oracle="ins"``, the paper's
protocol and the default): they initialise the localiser and reset it after a failure, and are never
used to localise.  With ``oracle="none"`` the localiser opens neither ``groundtruth.tum`` nor
``gps.csv``: it finds itself on the map by global localisation and relocalises when lost
(:mod:`localiser.relocalise`).  The exact truth (``truth.tum``) is read only by the evaluation,
after the replay.

Command line: ``scenesig localise MAP RUN --out DIR [--method signatures] [--oracle ins|none] [--every 4 | --realtime [--speed X]]``.
"""
from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapping.store import MapStore
from surveys.errors import DataError
from surveys.run import SurveyRun, read_run
from surveys.tum import write_tum

from .evaluation import ReferencePath, evaluate
from .pipeline import Localiser, Measurement, WeakLocaliser, make_method

__all__ = ["default_config", "ORACLES", "ReplayResult", "replay", "reference_path", "compute_metrics", "write_outputs",
           "localise", "FRAMES_COLUMNS", "TIMING_KEYS"]

default_config = {
    "every": 4,                  # deterministic mode: detector on every N-th frame
    "prefetch": True,            # deterministic mode: load and prepare (WeakLocaliser.prepare) the next
                                 # detector frame on a worker thread while the current one is processed
    "speed": 1.0,                # real-time mode: playback speed (2 = twice as fast as recorded)
    "max_path_distance_m": None,  # frames further than this from the map are left out of the errors
    "oracle": "ins",             # "ins": start and reset from the run's INS/GPS; "none": no INS/GPS
    "localiser": {},             # overrides of localiser.pipeline.default_config
    "relocalise": {},            # overrides of localiser.relocalise.default_config (oracle "none")
    "method": {},                # method configuration (e.g. {"detector": {...}, "solver": {...}})
}

#: Columns of ``frames.csv``.
FRAMES_COLUMNS = ("time", "place", "detections", "inliers", "localised", "lateral_error", "heading_error",
                  "distance_since_localisation")
#: Where the localiser's first pose and its recovery after a failure come from.
ORACLES = ("ins", "none")
#: ``metrics.json`` entries that measure the machine rather than the result (they differ between runs).
TIMING_KEYS = ("ms_per_detection", "ms_per_solve", "ms_per_odometry_update", "ms_per_retrieval", "realtime_factor",
               "wall_seconds")
#: Accepted localisations further than this from the truth are ``false_fixes`` (metres).
FALSE_FIX_M = 5.0


@dataclass
class ReplayResult:
    """Per-frame outputs of one replay and its timings."""

    run: SurveyRun
    method: str
    mode: str
    every: int | None
    times: np.ndarray                 # (N,) frame times
    poses: np.ndarray                 # (N,4,4) estimates T_world_vehicle (snapped)
    places: np.ndarray                # (N,) place used (nearest place for frames without detection)
    detections: np.ndarray            # (N,) detections (0 where the detector did not run)
    inliers: np.ndarray               # (N,)
    localised: np.ndarray             # (N,) bool: a localisation from this frame was accepted
    resets: np.ndarray                # (N,) bool: an oracle reset happened since the previous frame
    detector_ran: np.ndarray          # (N,) bool
    distance_since_localisation: np.ndarray  # (N,) odometry distance since the last fix or reset (m)
    reasons: list                     # (N,) solver's rejection reason or None
    failures: int
    reset_times: list = field(default_factory=list)   # times of the oracle resets (odometry times)
    timings: dict = field(default_factory=dict)
    oracle: str = "ins"
    oracle_reads: int = 0
    valid: np.ndarray | None = None   # (N,) bool: the localiser had a world pose at this frame
    first_fix_time: float | None = None      # oracle "none": the first pose found from the map
    relocalisations: list = field(default_factory=list)  # oracle "none": (t_lost, t_found) pairs

    def __post_init__(self):
        if self.valid is None:
            self.valid = np.ones(len(self.times), dtype=bool)


def _oracle(run: SurveyRun):
    if run.groundtruth_times is None:
        folder = run.root if run.root is not None else Path(run.name)
        raise DataError(Path(folder) / "groundtruth.tum",
                        "missing: the localiser needs the run's INS/GPS poses to initialise and to reset after a "
                        "failure (the oracle)")
    return lambda t: run.pose_at(t, "groundtruth")


def _check_compatible(store: MapStore, run: SurveyRun) -> None:
    cam, mcam = run.camera, store.camera
    if (cam.width, cam.height) != (mcam.width, mcam.height):
        where = (run.root / "run.toml") if run.root is not None else Path(run.name)
        raise DataError(where, f"camera is {cam.width}x{cam.height} but the map {store.root} was built from "
                               f"{mcam.width}x{mcam.height} images")
    if len(run.odometry_times) < 2:
        where = (run.root / "odometry.csv") if run.root is not None else Path(run.name)
        raise DataError(where, "needs at least 2 odometry samples")


class _Mailbox:
    """One-slot queue that keeps only the newest item (a put replaces a waiting item: a drop)."""

    def __init__(self):
        self._cond = threading.Condition()
        self._item = None
        self._has = False
        self._closed = False
        self.dropped = 0
        self.delivered = 0

    def put(self, item) -> None:
        with self._cond:
            if self._has:
                self.dropped += 1
            self._item, self._has = item, True
            self._cond.notify()

    def get(self):
        """The newest item; None once closed and empty."""
        with self._cond:
            while not self._has and not self._closed:
                self._cond.wait()
            if not self._has:
                return None
            item, self._item, self._has = self._item, None, False
            self.delivered += 1
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class _Recorder:
    """Per-frame bookkeeping shared by both modes."""

    def __init__(self, run: SurveyRun):
        n = len(run)
        self.times = np.asarray(run.frame_times, dtype=float)
        self.poses = np.tile(np.eye(4), (n, 1, 1))
        self.places = np.full(n, -1, dtype=int)
        self.detections = np.zeros(n, dtype=int)
        self.inliers = np.zeros(n, dtype=int)
        self.localised = np.zeros(n, dtype=bool)
        self.detector_ran = np.zeros(n, dtype=bool)
        self.distance = np.zeros(n)
        self.valid = np.zeros(n, dtype=bool)
        self.reasons: list = [None] * n
        self.ms_detect: list[float] = []
        self.ms_solve: list[float] = []
        self.lock = threading.Lock()

    def pose(self, i: int, loc: Localiser, t: float) -> None:
        if not loc.has_estimate:          # no oracle and no fix yet: not localised, no world pose
            with self.lock:
                self.poses[i] = np.nan
                self.distance[i] = loc.distance_since_localisation
            return
        T = loc.estimate(t)
        with self.lock:
            self.poses[i] = T
            self.valid[i] = True
            self.distance[i] = loc.distance_since_localisation
            if self.places[i] < 0:
                self.places[i] = loc.nearest_place(T)

    def measurement(self, i: int, place: int, m: Measurement, accepted: bool, ms_det: float, ms_solve: float) -> None:
        with self.lock:
            self.places[i] = place
            self.detector_ran[i] = True
            self.detections[i] = m.detections
            self.inliers[i] = m.inliers
            self.localised[i] = accepted
            self.reasons[i] = m.reason if not accepted else None
            self.ms_detect.append(ms_det)
            if m.solved:
                self.ms_solve.append(ms_solve)


class _FramePrefetcher:
    """Loads and prepares the detector's frames one ahead, on a worker thread (deterministic mode).

    Decoding the next detector frame and the method's image-only work on it
    (:meth:`WeakLocaliser.prepare`, e.g. feature extraction) need neither the place nor the prior,
    so they overlap with the current frame's detection, solve and pose-graph update -- on a
    two-core machine the other core is otherwise idle during the single-threaded parts.  The
    results are the same as loading inline; the preparation time is still counted as detection.
    """

    def __init__(self, run: SurveyRun, method: WeakLocaliser, frames):
        from concurrent.futures import ThreadPoolExecutor

        self.run, self.method = run, method
        self._frames = [int(i) for i in frames]
        self._next = {a: b for a, b in zip(self._frames, self._frames[1:])}
        self._pending: dict = {}
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-prefetch")

    def _load(self, i: int):
        img = self.run.image(i, gray=not self.method.color)
        t0 = time.perf_counter()
        prepared = self.method.prepare(img)
        return prepared, 1e3 * (time.perf_counter() - t0)

    def get(self, i: int):
        """``(prepared image, ms spent preparing it)`` of frame i; starts loading the next one."""
        fut = self._pending.pop(i, None)
        if fut is None:
            fut = self._pool.submit(self._load, i)
        nxt = self._next.get(i)
        if nxt is not None and nxt not in self._pending:
            self._pending[nxt] = self._pool.submit(self._load, nxt)
        return fut.result()

    def close(self) -> None:
        for fut in self._pending.values():
            fut.cancel()
        self._pending.clear()
        self._pool.shutdown(wait=True)


def _search(reloc, run: SurveyRun, i: int, t: float, img, rec: _Recorder, ms_prepare: float, method) -> None:
    """Global search for frame i (not localised, no oracle): retrieval, verification, sequence check."""
    raw = img if isinstance(img, np.ndarray) else run.image(i, gray=True)
    r = reloc.search(img, t, raw)
    rec.measurement(i, r.place, r.measurement, r.accepted, ms_prepare + r.ms_retrieval + r.ms_detect, r.ms_solve)


def _run_method(method: WeakLocaliser, loc: Localiser, run: SurveyRun, i: int, t: float, rec: _Recorder,
                frames: _FramePrefetcher | None = None, reloc=None) -> None:
    """Detector + solver for frame i at time t (deterministic mode: inline)."""
    if frames is not None:
        img, ms_prepare = frames.get(i)
    else:
        img, ms_prepare = run.image(i, gray=not method.color), 0.0
    if reloc is not None and loc.lost:
        _search(reloc, run, i, t, img, rec, ms_prepare, method)
        return
    prior = loc.prior(t)
    method.prefetch(prior.next_place)
    t0 = time.perf_counter()
    obs = method.detect(img, prior.place, prior)      # an image or its prepare() result
    t1 = time.perf_counter()
    m = Measurement.coerce(method.solve(obs, prior.place, prior))
    t2 = time.perf_counter()
    accepted = loc.add_measurement(t, m)
    rec.measurement(i, prior.place, m, accepted, ms_prepare + 1e3 * (t1 - t0), 1e3 * (t2 - t1))


def _deterministic(method, loc, run, rec, every, progress, prefetch=True, reloc=None):
    from tqdm import tqdm

    ft = rec.times
    odo_t = np.asarray(run.odometry_times, dtype=float)
    incs = run.odometry_increments()
    t_start = float(odo_t[0])
    loc.start(t_start)
    n = len(ft)
    fi = 0
    bar = tqdm(total=n, desc=f"localise {run.name}", unit="frame", disable=not progress)
    frames = _FramePrefetcher(run, method, range(0, n, every)) if prefetch else None

    def frame(i):
        t = max(float(ft[i]), t_start)       # frames before the first odometry: at the start pose
        if i % every == 0:
            _run_method(method, loc, run, i, t, rec, frames, reloc)
        rec.pose(i, loc, t)
        bar.update(1)

    try:
        for k in range(1, len(odo_t)):
            loc.add_odometry(float(odo_t[k]), incs[k - 1])
            while fi < n and ft[fi] <= odo_t[k]:
                frame(fi)
                fi += 1
            loc.check_failure(float(odo_t[k]))
        while fi < n:                             # frames after the last odometry sample
            frame(fi)
            fi += 1
    finally:
        if frames is not None:
            frames.close()
        bar.close()


def _realtime(method, loc, run, rec, speed, progress, reloc=None):
    from tqdm import tqdm

    ft = rec.times
    odo_t = np.asarray(run.odometry_times, dtype=float)
    incs = run.odometry_increments()
    t_start = float(odo_t[0])
    loc.start(t_start)
    frames_box, solve_box = _Mailbox(), _Mailbox()
    errors: list[BaseException] = []

    def detector():
        try:
            while (i := frames_box.get()) is not None:
                t = max(float(ft[i]), t_start)
                img = run.image(i, gray=not method.color)
                if reloc is not None and loc.lost:
                    # not localised: the whole search (retrieval, verification, sequence check) here
                    _search(reloc, run, i, t, img, rec, 0.0, method)
                    continue
                prior = loc.prior(t)
                method.prefetch(prior.next_place)
                t0 = time.perf_counter()
                obs = method.detect(img, prior.place, prior)   # detect() runs prepare() itself
                solve_box.put((i, t, prior, obs, 1e3 * (time.perf_counter() - t0)))
        except BaseException as exc:  # surfaced on the main thread
            errors.append(exc)
        finally:
            solve_box.close()

    def solver():
        try:
            while (item := solve_box.get()) is not None:
                i, t, prior, obs, ms_det = item
                t0 = time.perf_counter()
                m = Measurement.coerce(method.solve(obs, prior.place, prior))
                ms = 1e3 * (time.perf_counter() - t0)
                accepted = loc.add_measurement(t, m)
                rec.measurement(i, prior.place, m, accepted, ms_det, ms)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=detector, name="detector", daemon=True),
               threading.Thread(target=solver, name="solver", daemon=True)]
    for th in threads:
        th.start()
    # Events in time order; at equal times odometry first (so a frame's prior covers its time).
    events = sorted([(float(t), 0, k) for k, t in enumerate(odo_t) if k > 0] +
                    [(float(t), 1, i) for i, t in enumerate(ft)])
    t0_data = events[0][0] if events else 0.0
    wall0 = time.perf_counter()
    pending: list[int] = []
    bar = tqdm(total=len(ft), desc=f"localise {run.name} (real time x{speed:g})", unit="frame", disable=not progress)
    try:
        for t, kind, k in events:
            if errors:
                break
            delay = wall0 + (t - t0_data) / speed - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            if kind == 0:
                loc.add_odometry(t, incs[k - 1])
                while pending and ft[pending[0]] <= t:
                    i = pending.pop(0)
                    rec.pose(i, loc, max(float(ft[i]), t_start))
                    bar.update(1)
                loc.check_failure(t)
            else:
                pending.append(k)
                frames_box.put(k)
        for i in pending:
            rec.pose(i, loc, max(float(ft[i]), t_start))
            bar.update(1)
    finally:
        frames_box.close()
        for th in threads:
            th.join()
        bar.close()
    if errors:
        raise errors[0]
    return {"frames_dropped": frames_box.dropped + solve_box.dropped, "frames_detected": frames_box.delivered}


def replay(store: MapStore, run: SurveyRun, method: WeakLocaliser | str = "signatures", every: int = 4,
           realtime: bool = False, speed: float = 1.0, config: dict | None = None,
           progress: bool = False, oracle: str | None = None, retrieval=None) -> ReplayResult:
    """Localise one run against a map.

    Parameters
    ----------
    store : the map.
    run : the live run (needs odometry, and INS/GPS poses with ``oracle="ins"``; truth only for the
        metrics).
    method : a :class:`WeakLocaliser` or a registered method name.
    every : deterministic mode: detector on every ``every``-th frame.
    realtime : threads and mailboxes, paced by the data timestamps (``speed`` times faster).
    config : overrides of :data:`default_config` (``localiser``, ``method``, ``relocalise`` sub-dicts).
    progress : show a tqdm bar.
    oracle : ``"ins"`` or ``"none"`` (default: ``config["oracle"]``, else ``"ins"``).
    retrieval : the coarse place retrieval for ``oracle="none"`` (default: the map's descriptors,
        :class:`localiser.relocalise.PlaceRetrieval`).
    """
    cfg = {**default_config, **(config or {})}
    unknown = set(config or {}) - set(default_config)
    if unknown:
        raise ValueError(f"unknown replay option(s) {sorted(unknown)}; known: {sorted(default_config)}")
    every = int(every)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if not speed > 0:
        raise ValueError(f"speed must be > 0, got {speed}")
    oracle = oracle or cfg["oracle"]
    if oracle not in ORACLES:
        raise ValueError(f"oracle must be one of {ORACLES}, got {oracle!r}")
    _check_compatible(store, run)
    own = isinstance(method, str)
    if own:
        method = make_method(method, store, run.camera, run.T_vehicle_camera, cfg["method"] or None)
    loc = Localiser(store, _oracle(run) if oracle == "ins" else None, cfg["localiser"] or None)
    reloc = None
    if oracle == "none":
        from .relocalise import Relocaliser

        reloc = Relocaliser(store, method, loc, cfg["relocalise"] or None, retrieval=retrieval)
    rec = _Recorder(run)
    extra = {}
    wall0 = time.perf_counter()
    try:
        if realtime:
            extra = _realtime(method, loc, run, rec, float(speed), progress, reloc)
        else:
            _deterministic(method, loc, run, rec, every, progress, bool(cfg["prefetch"]), reloc)
    finally:
        if own:
            method.close()
    wall = time.perf_counter() - wall0
    resets = np.zeros(len(run), dtype=bool)
    if len(run):
        for tr in loc.reset_times:
            resets[min(int(np.searchsorted(rec.times, tr, side="right")), len(run) - 1)] = True
    t_all = np.concatenate([rec.times, run.odometry_times])
    duration = float(t_all.max() - t_all.min()) if len(t_all) else 0.0
    timings = {
        "ms_per_detection": float(np.mean(rec.ms_detect)) if rec.ms_detect else None,
        "ms_per_solve": float(np.mean(rec.ms_solve)) if rec.ms_solve else None,
        "ms_per_odometry_update": loc.ms_per_odometry_update,
        "realtime_factor": duration / wall if wall > 0 else None,
        "wall_seconds": wall,
        "duration_s": duration,
        **extra,
    }
    if reloc is not None and reloc.ms_retrieval:
        timings["ms_per_retrieval"] = float(np.mean(reloc.ms_retrieval))
        timings["global_searches"] = int(reloc.searches)
    return ReplayResult(run, method.name, "realtime" if realtime else "deterministic", None if realtime else every,
                        rec.times, rec.poses, rec.places, rec.detections, rec.inliers, rec.localised, resets,
                        rec.detector_ran, rec.distance, rec.reasons, loc.failures, list(loc.reset_times), timings,
                        oracle, loc.oracle_reads, rec.valid.copy(), loc.first_fix_time, list(loc.relocalisations))


# ------------------------------------------------------------------------------------------------
# metrics and outputs
# ------------------------------------------------------------------------------------------------
def reference_path(store: MapStore) -> ReferencePath:
    """The reference path: the map's places in order, closed if the route is a loop."""
    ids = sorted(store.places)
    poses = np.stack([store.places[i].T_world_place for i in ids])
    if len(ids) > 2 and ids[-1] in store.places[ids[0]].neighbours:
        poses = np.concatenate([poses, poses[:1]])
    return ReferencePath(poses)


def map_relative_truth(store: MapStore, truth_poses: np.ndarray) -> np.ndarray | None:
    """Truth expressed in the map's frame, or None when the map does not record its places' truth.

    The map's frame is realised by the training runs' INS (combined per place by
    :mod:`mapping.georef`), whose error (metres, for a GPS-aided INS) every place carries.  A simulated map records each place's exact pose (``extra["T_truth_place"]``),
    so a true pose can be carried into the map frame through the nearest place:
    ``T_world_place · T_truth_place⁻¹ · T_truth``.  Errors against that are the localiser's own;
    errors against the raw truth add the map's georeferencing error, which no localiser can remove.
    """
    ids = sorted(store.places)
    if not ids or any("T_truth_place" not in store.places[i].extra for i in ids):
        return None
    Tw = np.stack([store.places[i].T_world_place for i in ids])
    Tt = np.stack([np.asarray(store.places[i].extra["T_truth_place"], float) for i in ids])
    P = np.asarray(truth_poses, float).reshape(-1, 4, 4)
    near = np.argmin(np.linalg.norm(P[:, None, :3, 3] - Tt[None, :, :3, 3], axis=2), axis=1)
    corr = Tw @ np.linalg.inv(Tt)             # (K,4,4) truth -> map frame at each place
    return corr[near] @ P


def compute_metrics(result: ReplayResult, store: MapStore, max_path_distance_m: float | None = None):
    """``metrics.json`` content and the evaluation behind it (per-frame errors).

    Keys: ``method``, ``run``, ``conditions``; ``lateral_error_m`` and ``heading_error_deg``
    (``{"median", "mean", "p95"}`` of absolute errors against the run's exact truth, lateral = across
    the reference path through the map's places; :mod:`localiser.evaluation`); ``localised_fraction``,
    ``failures`` (oracle resets), ``failures_per_km``, ``blind_fraction_over_20m``; where the map
    records its places' truth (simulated maps) also ``lateral_error_map_m``, ``heading_error_map_deg``
    (the same errors relative to the map, see :func:`map_relative_truth`) and
    ``map_georeference_error_m`` (how far the map's places are from their truth); timings
    ``ms_per_detection``, ``ms_per_solve``, ``ms_per_odometry_update``, ``realtime_factor`` (data
    duration / wall time of the replay), ``wall_seconds``; bookkeeping ``mode``, ``every``,
    ``distance_m``, ``duration_s``, ``frames``, ``frames_evaluated``, ``detector_frames``,
    ``localisations``, ``truth_source``, ``map``, and in real-time mode ``frames_dropped`` and
    ``frames_detected``.  Without ``truth.tum`` the errors are taken against ``groundtruth.tum``
    (``truth_source``).
    """
    run = result.run
    if run.truth_times is not None:
        tt, tp, source = run.truth_times, run.truth_poses, "truth"
    elif run.groundtruth_times is not None:
        tt, tp, source = run.groundtruth_times, run.groundtruth_poses, "groundtruth"
    else:
        raise DataError(run.root or Path(run.name), "no truth.tum or groundtruth.tum to evaluate against")
    ev = _evaluate_valid(result, tt, tp, store, max_path_distance_m)
    m = ev.metrics
    tm = result.timings
    map_errors = {}
    tmap = map_relative_truth(store, tp) if source == "truth" else None
    if tmap is not None:
        from .evaluation import summary

        evm = _evaluate_valid(result, tt, tmap, store, max_path_distance_m)
        # the map's own error: its places against their truth
        ids = sorted(store.places)
        off = [np.linalg.norm(store.places[i].T_world_place[:2, 3] - np.asarray(store.places[i].extra["T_truth_place"])[:2, 3])
               for i in ids]
        map_errors = {"lateral_error_map_m": evm.metrics["lateral_error_m"],
                      "heading_error_map_deg": evm.metrics["heading_error_deg"],
                      "map_georeference_error_m": summary(off)}
    metrics = {
        "method": result.method,
        "run": run.name,
        "conditions": list(run.conditions),
        "lateral_error_m": m["lateral_error_m"],
        "heading_error_deg": m["heading_error_deg"],
        "localised_fraction": m["localised_fraction"],
        "failures": int(result.failures),
        "failures_per_km": m["failures_per_km"],
        "blind_fraction_over_20m": m["blind_fraction_over_20m"],
        **_no_oracle_metrics(result, ev, tt, tp if tmap is None else tmap),
        **map_errors,
        "ms_per_detection": tm.get("ms_per_detection"),
        "ms_per_solve": tm.get("ms_per_solve"),
        "ms_per_odometry_update": tm.get("ms_per_odometry_update"),
        "ms_per_retrieval": tm.get("ms_per_retrieval"),
        "realtime_factor": tm.get("realtime_factor"),
        "wall_seconds": tm.get("wall_seconds"),
        "mode": result.mode,
        "every": result.every,
        "distance_m": m["distance_m"],
        "duration_s": tm.get("duration_s"),
        "frames": int(len(result.times)),
        "frames_evaluated": m["frames_evaluated"],
        "detector_frames": int(result.detector_ran.sum()),
        "localisations": int(result.localised.sum()),
        "truth_source": source,
        "map": str(store.root),
    }
    for k in ("frames_dropped", "frames_detected"):
        if k in tm:
            metrics[k] = tm[k]
    return metrics, ev


def _evaluate_valid(result: ReplayResult, truth_times, truth_poses, store: MapStore, max_path_distance_m):
    """:func:`localiser.evaluation.evaluate` over the frames with a world pose (all of them with an oracle;
    from the first fix on without one), its per-frame series put back on every frame (NaN elsewhere)."""
    from surveys.geometry import interpolate_poses

    from .evaluation import EvaluationResult, travelled

    v = np.asarray(result.valid, bool)
    if v.all():
        return evaluate(result.times, result.poses, truth_times, truth_poses, reference_path(store), result.localised,
                        result.resets, max_path_distance_m=max_path_distance_m)
    n = len(result.times)
    dist = travelled(interpolate_poses(truth_times, truth_poses, result.times).reshape(-1, 4, 4)[:, :3, 3])
    lat, hd, blind = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    if v.sum() >= 2:
        ev = evaluate(result.times[v], result.poses[v], truth_times, truth_poses, reference_path(store),
                      result.localised[v], result.resets[v], max_path_distance_m=max_path_distance_m)
        lat[v], hd[v], blind[v] = ev.lateral_m, ev.heading_deg, ev.blind_m
        metrics = ev.metrics
    else:   # never localised: nothing to evaluate but the distance driven
        from .evaluation import summary

        metrics = {"lateral_error_m": summary([]), "heading_error_deg": summary([]), "localised_fraction": 0.0,
                   "failures": int(result.failures), "failures_per_km": None, "blind_fraction_over_20m": None,
                   "distance_m": float(dist[-1]) if n else 0.0, "frames_evaluated": 0}
    return EvaluationResult(metrics, lat, hd, blind, dist)


def _no_oracle_metrics(result: ReplayResult, ev, truth_times, truth_poses) -> dict:
    """``oracle``, ``oracle_reads``, ``first_fix_m``, ``relocalisations``, ``false_fixes``, ``relocalise_m``.

    Distances are along the truth (``ev.distance_m``, from the first frame); a false fix is an accepted
    localisation whose estimate is more than :data:`FALSE_FIX_M` from the truth (relative to the map
    where the map records its places' truth, so the map's own georeferencing error does not count).
    """
    from surveys.geometry import interpolate_poses

    from .evaluation import summary

    s = np.asarray(ev.distance_m, float)

    def at(t):
        return float(np.interp(t, result.times, s)) if len(s) else 0.0

    first = None
    if result.oracle == "ins":
        first = 0.0
    elif result.first_fix_time is not None:
        first = at(result.first_fix_time) - (float(s[0]) if len(s) else 0.0)
    loc = np.asarray(result.localised, bool) & np.asarray(result.valid, bool)
    false = 0
    if loc.any():
        truth = interpolate_poses(truth_times, truth_poses, result.times[loc]).reshape(-1, 4, 4)
        err = np.linalg.norm(result.poses[loc][:, :2, 3] - truth[:, :2, 3], axis=1)
        false = int((err > FALSE_FIX_M).sum())
    found = [at(b) - at(a) for a, b in result.relocalisations]
    rel = summary(found)
    return {"oracle": result.oracle, "oracle_reads": int(result.oracle_reads), "first_fix_m": first,
            "relocalisations": len(found), "false_fixes": false,
            "relocalise_m": {"median": rel["median"], "max": float(max(found)) if found else None}}


def _fmt(v: float) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.6f}"


def write_frames_csv(path: Path, result: ReplayResult, ev) -> None:
    lines = [",".join(FRAMES_COLUMNS)]
    for i, t in enumerate(result.times):
        lines.append(",".join([f"{t:.6f}", str(int(result.places[i])), str(int(result.detections[i])),
                               str(int(result.inliers[i])), str(int(result.localised[i])),
                               _fmt(ev.lateral_m[i]), _fmt(ev.heading_deg[i]),
                               _fmt(result.distance_since_localisation[i])]))
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)


def plot_trajectory(path: Path, result: ReplayResult, store: MapStore, ev, metrics: dict) -> None:
    """``trajectory.png``: estimate vs truth vs INS on the map; lateral error over distance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = result.run
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 10), gridspec_kw={"height_ratios": [3, 1.4]})
    places = np.stack([store.places[i].T_world_place for i in sorted(store.places)])
    ax.plot(places[:, 0, 3], places[:, 1, 3], "o", ms=3, color="0.7", label="map places", zorder=1)
    if run.truth_times is not None:
        ax.plot(run.truth_poses[:, 0, 3], run.truth_poses[:, 1, 3], "-", color="k", lw=1.2, label="truth")
    if run.groundtruth_times is not None:
        ax.plot(run.groundtruth_poses[:, 0, 3], run.groundtruth_poses[:, 1, 3], "--", color="tab:orange", lw=1,
                label="INS/GPS")
    ax.plot(result.poses[:, 0, 3], result.poses[:, 1, 3], "-", color="tab:blue", lw=1, label="estimate")
    loc = result.localised
    ax.plot(result.poses[loc, 0, 3], result.poses[loc, 1, 3], ".", ms=3, color="tab:green", label="localised")
    what = "reset" if result.oracle == "ins" else "lost"
    if result.resets.any():
        ax.plot(result.poses[result.resets, 0, 3], result.poses[result.resets, 1, 3], "x", color="tab:red", ms=8,
                mew=2, label=f"{what} ({int(result.resets.sum())})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    lat = metrics["lateral_error_m"]["median"]
    hd = metrics["heading_error_deg"]["median"]
    ax.set_title(f"{run.name} [{', '.join(run.conditions)}] -- {result.method}: lateral median "
                 f"{'-' if lat is None else f'{lat:.2f} m'}, heading median {'-' if hd is None else f'{hd:.2f}°'}, "
                 f"failures {result.failures}"
                 + (f"\nrelative to the map: lateral median {metrics['lateral_error_map_m']['median']:.2f} m, heading "
                    f"median {metrics['heading_error_map_deg']['median']:.2f}° (map georeference error "
                    f"{metrics['map_georeference_error_m']['median']:.1f} m)"
                    if metrics.get("lateral_error_map_m", {}).get("median") is not None else ""), fontsize=10)
    ax.legend(loc="best", fontsize=8)
    s = ev.distance_m
    within = ev.blind_m <= 10.0
    if len(s) > 1:
        # shade the stretches within 10 m of a localisation (the localised_fraction definition)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], within.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            bx.axvspan(s[a], s[min(b, len(s) - 1)], color="tab:green", alpha=0.15, lw=0)
    bx.plot(s, ev.lateral_m, color="tab:blue", lw=1, label="lateral error")
    tmap = map_relative_truth(store, run.truth_poses) if run.truth_times is not None else None
    if tmap is not None:
        from .evaluation import lateral_heading_errors
        from surveys.geometry import interpolate_poses

        tm = interpolate_poses(run.truth_times, tmap, result.times).reshape(-1, 4, 4)
        lat_map = np.full(len(result.times), np.nan)
        if result.valid.any():
            lat_map[result.valid] = lateral_heading_errors(result.poses[result.valid], tm[result.valid],
                                                           reference_path(store))[0]
        bx.plot(s, lat_map, color="tab:purple", lw=1, label="lateral error relative to the map")
    if run.groundtruth_times is not None and run.truth_times is not None:
        from surveys.geometry import interpolate_poses
        from .evaluation import lateral_heading_errors

        ins = interpolate_poses(run.groundtruth_times, run.groundtruth_poses, result.times).reshape(-1, 4, 4)
        tru = interpolate_poses(run.truth_times, run.truth_poses, result.times).reshape(-1, 4, 4)
        ins_lat, _, _ = lateral_heading_errors(ins, tru, reference_path(store))
        bx.plot(s, ins_lat, color="tab:orange", lw=0.8, ls="--", label="INS/GPS lateral error")
    for sr in s[result.resets]:
        bx.axvline(sr, color="tab:red", lw=1)
    bx.axhline(0, color="0.5", lw=0.5)
    if result.oracle != "ins" and result.first_fix_time is not None:
        bx.axvline(float(np.interp(result.first_fix_time, result.times, s)), color="tab:green", lw=1, ls=":")
    bx.set_xlabel(f"distance travelled (m)  [green: within 10 m of a localisation; red: {what}"
                  + ("; dotted: first fix from the map" if result.oracle != "ins" else "") + "]")
    bx.set_ylabel("lateral error (m)")
    bx.legend(loc="best", fontsize=8)
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


def write_outputs(result: ReplayResult, store: MapStore, out, max_path_distance_m: float | None = None,
                  figure: bool = True) -> dict:
    """Write trajectory.tum, frames.csv, metrics.json (and trajectory.png) into ``out``; return the metrics."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    metrics, ev = compute_metrics(result, store, max_path_distance_m)
    write_tum(out / "trajectory.tum", result.times[result.valid], result.poses[result.valid])
    write_frames_csv(out / "frames.csv", result, ev)
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    tmp.replace(out / "metrics.json")
    if figure:
        plot_trajectory(out / "trajectory.png", result, store, ev, metrics)
    return metrics


def localise(map_root, run_root, out, method: str = "signatures", every: int = 4, realtime: bool = False,
             speed: float = 1.0, config: dict | None = None, progress: bool = True, figure: bool = True,
             oracle: str | None = None) -> dict:
    """Open the map and the run, replay, write the outputs; returns ``metrics.json``'s content.

    With ``oracle="none"`` the localiser's run is read without ``groundtruth.tum``, ``gps.csv`` and
    ``truth.tum``; the truth is read for the evaluation after the replay.
    """
    import dataclasses

    store = MapStore.open(map_root)
    cfg = {**default_config, **(config or {})}
    oracle = oracle or cfg["oracle"]
    blind = oracle == "none"
    run = read_run(run_root, skip=("groundtruth", "gps", "truth") if blind else ())
    result = replay(store, run, method, every=every, realtime=realtime, speed=speed, config=config,
                    progress=progress, oracle=oracle)
    if blind:       # the evaluation's truth, read only now
        truth = read_run(run_root, check_images=False, skip=("groundtruth", "gps"))
        result.run = dataclasses.replace(run, truth_times=truth.truth_times, truth_poses=truth.truth_poses)
    return write_outputs(result, store, out, cfg["max_path_distance_m"], figure=figure)
