"""Replay a survey run through the online localiser: ``scenesig localise MAP RUN --out DIR``.

The replay is a driver over :class:`scenesig.localiser.session.Session`, the per-frame step a robot drives
(prior, detect, solve, integrity, search when lost): it reads the run's images and odometry from disk,
feeds them in time order and records every frame (``tests/test_session.py`` holds its outputs to main's bytes
before the step moved there).  Two modes:

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
  solver finishes (possibly a few frames late; the graph carries them to the right time).  When the
  feed falls behind the data clock (a loaded CPU), the odometry samples already due wait in a queue
  of at most ``odometry_queue``; older ones are composed into one increment (exact in pose), so the
  backlog -- and the lag -- never grow without bound (``odometry_coalesced``, ``odometry_queue_max``,
  ``lag_max_s`` in ``metrics.json``).

In both modes a frame whose image fails strict decoding (truncated or corrupt:
:mod:`scenesig.surveys.images`) is skipped -- no detection, the odometry goes on -- named once in a warning
and counted (``frames_corrupt``, ``corrupt_frames``).

Outputs in DIR, whether or not the run has truth: ``trajectory.tum`` (the estimate at every frame time;
evo reads it), ``covariances.csv`` (each pose's planar covariance, :mod:`scenesig.localiser.uncertainty`),
``frames.csv`` (time, place, detections, inliers, localised, lateral_error, heading_error,
distance_since_localisation, the 95 % bounds, integrity_alert, and signature_inliers, point_inliers -- which
measurement types the solver kept; the errors NaN without truth), ``metrics.json`` (see
:func:`compute_metrics`) and ``trajectory.png``
(estimate, truth and INS/GPS on the map; lateral error over distance with the stretches within 10 m
of a localisation shaded and the resets marked).

Timings in ``metrics.json``: ``ms_per_detection`` is the detector block per frame (for point
features including the extraction, wherever it ran), ``ms_per_solve`` the solver, and
``realtime_factor`` the data duration over the wall time of the replay loop alone (opening the map
and the run, the evaluation and writing the outputs are not counted); ``cpu_seconds`` the process's
CPU time over the same loop (all threads) and ``cpu_ms_per_frame`` that per camera frame -- on a
shared machine less sensitive to the load than the wall time.

The run's INS/GPS poses (``groundtruth.tum``) are the *oracle* (``oracle="ins"``, the paper's
protocol and the default): they initialise the localiser and reset it after a failure, and are never
used to localise.  With ``oracle="none"`` the localiser opens neither ``groundtruth.tum`` nor
``gps.csv``: it finds itself on the map by global localisation and relocalises when lost
(:mod:`scenesig.localiser.relocalise`).  The exact truth (``truth.tum``) is read only by the evaluation,
after the replay.

Command line: ``scenesig localise MAP RUN --out DIR [--method signatures] [--oracle ins|none] [--every 4 | --realtime [--speed X]]``.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.errors import CorruptImageError, DataError
from scenesig.surveys.localisation import Localisation
from scenesig.surveys.run import SurveyRun, read_run
from scenesig.surveys.settings import merge_settings

from .methods import Measurement, WeakLocaliser
from .outputs import (  # noqa: F401  (re-exported)
    FRAMES_COLUMNS,
    TIMING_KEYS,
    compute_metrics,
    map_relative_truth,
    reference_path,
    write_outputs,
)
from .pipeline import Localiser
from .session import Session, _Job, check_layers

log = logging.getLogger(__name__)

__all__ = ["default_config", "DEFAULT_EVERY", "resolve_config", "method_settings", "ORACLES", "replay",
           "reference_path", "compute_metrics", "write_outputs", "localise", "localise_run", "FRAMES_COLUMNS",
           "TIMING_KEYS"]

#: Deterministic mode: the detector on every N-th frame -- McManus et al. 2015, §4.3: "every 4th image",
#: 5 Hz on a 20 Hz camera.  The one default of ``every`` (a call argument, like ``realtime`` and ``speed``).
DEFAULT_EVERY = 4

default_config = {
    "prefetch": True,            # deterministic mode: load and prepare (WeakLocaliser.prepare) the next
                                 # detector frame on a worker thread while the current one is processed
    "odometry_queue": 10,        # real-time mode: odometry samples allowed to wait; when the feed falls
                                 # further behind (CPU load), the oldest waiting samples are composed into
                                 # one increment (exact in pose), so the backlog never grows without bound
    "max_path_distance_m": None,  # frames further than this from the map are left out of the errors
    "oracle": "ins",             # "ins": start and reset from the run's INS/GPS; "none": no INS/GPS
    "localiser": {},             # overrides of localiser.pipeline.default_config
    "relocalise": {},            # overrides of localiser.relocalise.default_config (oracle "none")
    "method": {},                # method configuration (e.g. {"detector": {...}, "solver": {...}})
    "integrity": {},             # overrides of localiser.integrity.default_config
}

#: Where the localiser's first pose and its recovery after a failure come from.
ORACLES = ("ins", "none")


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
        self.signature_inliers = np.zeros(n, dtype=int)
        self.point_inliers = np.zeros(n, dtype=int)
        self.localised = np.zeros(n, dtype=bool)
        self.detector_ran = np.zeros(n, dtype=bool)
        self.distance = np.zeros(n)
        self.valid = np.zeros(n, dtype=bool)
        self.covariances = np.full((n, 6, 6), np.nan)   # the pose graph's marginal at each frame
        self.reasons: list = [None] * n
        self.ms_detect: list[float] = []
        self.ms_solve: list[float] = []
        self.alert = np.zeros(n, dtype=bool)           # the integrity monitor refused the frame's fix
        self.lock = threading.Lock()
        self.corrupt: dict[int, str] = {}   # frame -> why its image was rejected (skipped frames)
        self.probation_start: int | None = None         # first frame of a global fix awaiting confirmation

    def corrupt_frame(self, i: int, exc: CorruptImageError) -> None:
        """A frame whose image failed strict decoding: skipped (odometry goes on), named once."""
        with self.lock:
            if i in self.corrupt:
                return
            self.corrupt[i] = exc.message
        log.warning("skipped frame %d: %s", i, exc)

    def pose(self, i: int, loc: Localiser, t: float) -> None:
        if not loc.has_estimate:          # no oracle and no fix yet: not localised, no world pose
            with self.lock:
                self.poses[i] = np.nan
                self.distance[i] = loc.distance_since_localisation
            return
        T, C = loc.estimate_with_covariance(t)
        with self.lock:
            self.poses[i] = T
            self.covariances[i] = C
            self.valid[i] = True
            self.distance[i] = loc.distance_since_localisation
            if self.places[i] < 0:
                self.places[i] = loc.nearest_place(T)

    def discard(self, i0: int, i1: int, mark: bool = True) -> None:
        """Frames i0..i1 tracked a fix the integrity monitor rejected (``mark``: marked as refused) or
        never confirmed: no pose, not localised."""
        with self.lock:
            sl = slice(i0, i1 + 1)
            self.poses[sl] = np.nan
            self.covariances[sl] = np.nan
            self.valid[sl] = False
            self.localised[sl] = False
            if mark:
                self.alert[sl] |= self.detector_ran[sl]

    def measurement(self, i: int, place: int, m: Measurement, accepted: bool, ms_det: float, ms_solve: float) -> None:
        with self.lock:
            self.places[i] = place
            self.detector_ran[i] = True
            self.detections[i] = m.detections
            self.inliers[i] = m.inliers
            # which measurement types the solver kept (a method that says nothing: neither)
            self.signature_inliers[i] = int(m.extra.get("signature_inliers", 0))
            self.point_inliers[i] = int(m.extra.get("point_inliers", 0))
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


def _record(rec: _Recorder, i: int, rep) -> None:
    """What one frame's step (:class:`scenesig.localiser.session.FrameReport`) did, into the per-frame arrays."""
    if rep.alert:
        with rec.lock:
            rec.alert[i] = True
    if rep.withdrawn_from is not None:       # the integrity monitor refused the global fix these frames tracked
        rec.discard(rep.withdrawn_from, i)
    rec.measurement(i, rep.place, rep.measurement, rep.accepted, rep.ms_detect, rep.ms_solve)


def _run_method(session: Session, run: SurveyRun, i: int, t: float, rec: _Recorder,
                frames: _FramePrefetcher | None = None) -> None:
    """The session's per-frame step for frame i at time t (deterministic mode: inline), the image from disk."""
    try:
        if frames is not None:
            img, ms_prepare = frames.get(i)
        else:
            img, ms_prepare = run.image(i, gray=not session.method.color), 0.0
    except CorruptImageError as exc:
        rec.corrupt_frame(i, exc)
        return
    # the image (or its prepare() result) as the method wants it; the search's retrieval reads the grey one
    session._frame(t, img, i, prepared=img, ms_prepare=ms_prepare, gray=lambda: run.image(i, gray=True))
    _record(rec, i, session.last_frame)


def _deterministic(session: Session, run, rec, every, progress, prefetch=True):
    from tqdm import tqdm

    ft = rec.times
    odo_t = np.asarray(run.odometry_times, dtype=float)
    incs = run.odometry_increments()
    t_start = float(odo_t[0])
    session.start(t_start)
    loc = session.localiser
    n = len(ft)
    fi = 0
    bar = tqdm(total=n, desc=f"localise {run.name}", unit="frame", disable=not progress)
    frames = _FramePrefetcher(run, session.method, range(0, n, every)) if prefetch else None

    def frame(i):
        t = max(float(ft[i]), t_start)       # frames before the first odometry: at the start pose
        if i % every == 0:
            _run_method(session, run, i, t, rec, frames)
        rec.pose(i, loc, t)
        bar.update(1)

    try:
        for k in range(1, len(odo_t)):
            # the failure rule for sample k-1 runs first, after the frames up to its time (Session's rule)
            session._odometry(float(odo_t[k]), incs[k - 1])
            while fi < n and ft[fi] <= odo_t[k]:
                frame(fi)
                fi += 1
        session.flush()                           # the failure rule for the last sample
        while fi < n:                             # frames after the last odometry sample
            frame(fi)
            fi += 1
    finally:
        if frames is not None:
            frames.close()
        bar.close()


def _realtime(session: Session, run, rec, speed, progress, odometry_queue=10):
    from tqdm import tqdm

    ft = rec.times
    odo_t = np.asarray(run.odometry_times, dtype=float)
    incs = run.odometry_increments()
    t_start = float(odo_t[0])
    session.start(t_start)
    loc = session.localiser
    frames_box, solve_box = _Mailbox(), _Mailbox()
    errors: list[BaseException] = []

    def detector():
        try:
            while (i := frames_box.get()) is not None:
                t = max(float(ft[i]), t_start)
                try:
                    img = run.image(i, gray=not session.method.color)
                except CorruptImageError as exc:
                    rec.corrupt_frame(i, exc)
                    continue
                # detect() runs prepare() itself; not localised: the whole search (retrieval, verification,
                # sequence check) runs here and the frame is done
                out = session._detect_stage(t, img, i, 0.0, lambda i=i: run.image(i, gray=True))
                if isinstance(out, _Job):
                    solve_box.put(out)
                else:
                    _record(rec, i, out)
        except BaseException as exc:  # surfaced on the main thread
            errors.append(exc)
        finally:
            solve_box.close()

    def solver():
        try:
            while (job := solve_box.get()) is not None:
                _record(rec, job.key, session._solve_stage(job))
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
    odo_next = 1                 # next odometry sample to integrate
    queue_max = coalesced = 0
    lag_max = 0.0
    try:
        for t, kind, k in events:
            if errors:
                break
            if kind == 0 and k < odo_next:
                continue                     # already integrated as part of a composed increment
            delay = wall0 + (t - t0_data) / speed - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            now = t0_data + (time.perf_counter() - wall0) * speed      # the data clock
            lag_max = max(lag_max, now - t)
            if kind == 0:
                # the odometry queue: samples already due (timestamp passed) but not yet integrated
                due = int(np.searchsorted(odo_t, now, side="right")) - k
                queue_max = max(queue_max, due)
                last = k + max(0, due - odometry_queue)   # compose the oldest ones into one increment
                inc = incs[k - 1]
                for j in range(k + 1, last + 1):
                    inc = inc @ incs[j - 1]
                coalesced += last - k
                odo_next = last + 1
                t = float(odo_t[last])
                session._odometry(t, inc)
                while pending and ft[pending[0]] <= t:
                    i = pending.pop(0)
                    rec.pose(i, loc, max(float(ft[i]), t_start))
                    bar.update(1)
            else:
                pending.append(k)
                frames_box.put(k)            # replaces a frame still waiting: a stale frame dropped
        session.flush()
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
    return {"frames_dropped": frames_box.dropped + solve_box.dropped, "frames_detected": frames_box.delivered,
            "odometry_queue_max": queue_max, "odometry_coalesced": coalesced, "lag_max_s": lag_max}

def resolve_config(config: dict | None = None, method: str = "signatures") -> dict:
    """Every setting of a replay, resolved: ``config`` (overrides of :data:`default_config`) merged with
    the defaults of each stage it configures -- ``localiser`` (:data:`scenesig.localiser.pipeline.default_config`,
    its ``posegraph`` :data:`scenesig.localiser.posegraph.default_config`), ``relocalise``
    (:data:`scenesig.localiser.relocalise.default_config`) and ``method`` (:func:`method_settings`).  A misspelt
    key anywhere is a ``ValueError`` naming it."""
    from .integrity import default_config as integrity_default
    from .pipeline import default_config as localiser_default
    from .posegraph import default_config as posegraph_default
    from .relocalise import default_config as relocalise_default

    cfg = merge_settings(default_config, config, "replay", open=("localiser", "method", "relocalise", "integrity"))
    if cfg["oracle"] not in ORACLES:
        raise ValueError(f"oracle must be one of {', '.join(ORACLES)}, got {cfg['oracle']!r}")
    loc = merge_settings(localiser_default, cfg["localiser"], "localiser", open=("posegraph",))
    loc["posegraph"] = merge_settings(posegraph_default, loc["posegraph"], "pose-graph")
    cfg["localiser"] = loc
    cfg["relocalise"] = merge_settings(relocalise_default, cfg["relocalise"], "relocalisation")
    cfg["integrity"] = merge_settings(integrity_default, cfg["integrity"], "integrity")
    cfg["method"] = method_settings(method, cfg["method"])
    return cfg


def method_settings(method: str, config: dict | None = None) -> dict:
    """The resolved settings of a registered method, by the resolver it registered with
    (:func:`scenesig.localiser.methods.method_settings`: scene signatures with their detector's and
    solver's, the point-feature and hybrid methods with every sub-stage's); a method registered
    without one, or an unregistered name, gets its overrides as given."""
    from .methods import method_settings as registered_settings

    return registered_settings(method, config)


def _settings(cfg: dict, every: int | None, realtime: bool, speed: float, oracle: str) -> dict:
    """``metrics.json``'s ``settings``: the replay's, the localiser's, the pose graph's, the
    relocaliser's (without INS/GPS only), the integrity monitor's and the method's, each resolved."""
    loc = {k: v for k, v in cfg["localiser"].items() if k != "posegraph"}
    replay_cfg = {k: v for k, v in cfg.items() if k not in ("localiser", "method", "relocalise", "integrity")}
    out = {"replay": {**replay_cfg, "oracle": oracle, "every": every, "realtime": bool(realtime),
                      "speed": float(speed) if realtime else None},
           "localiser": loc, "posegraph": cfg["localiser"]["posegraph"], "method": cfg["method"],
           "integrity": cfg["integrity"]}
    if oracle == "none":
        out["relocalise"] = cfg["relocalise"]
    return _json_safe(out)


def replay(store: MapStore, run: SurveyRun, method: WeakLocaliser | str = "signatures", every: int = DEFAULT_EVERY,
           realtime: bool = False, speed: float = 1.0, config: dict | None = None,
           progress: bool = False, oracle: str | None = None, retrieval=None) -> Localisation:
    """Localise one run against a map: a :class:`scenesig.surveys.localisation.Localisation` holding every
    frame's record, without metrics yet (:func:`scenesig.localiser.outputs.evaluate_localisation` adds them).

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
        :class:`scenesig.localiser.relocalise.PlaceRetrieval`).
    """
    cfg = merge_settings(default_config, config, "replay", open=("localiser", "method", "relocalise", "integrity"))
    resolved = resolve_config(config, method if isinstance(method, str) else method.name)
    oracle = oracle or cfg["oracle"]
    if oracle not in ORACLES:
        raise ValueError(f"oracle must be one of {ORACLES}, got {oracle!r}")
    every = int(every)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if not speed > 0:
        raise ValueError(f"speed must be > 0, got {speed}")
    _check_compatible(store, run)
    oracle_pose = _oracle(run) if oracle == "ins" else None     # a missing INS/GPS stops us before replaying
    # the per-frame step is the online Session's; frames reach it once the odometry covers them (no latency
    # limit: a recorded run's odometry may be sparser than one detector period)
    session = Session(store, run.camera, run.T_vehicle_camera, method, oracle=oracle_pose, retrieval=retrieval,
                      config={"max_latency_s": None, **{k: cfg[k] for k in ("localiser", "method", "relocalise",
                                                                              "integrity")}})
    method, loc, reloc = session.method, session.localiser, session.relocaliser
    rec = _Recorder(run)
    extra = {}
    wall0 = time.perf_counter()
    cpu0 = time.process_time()        # every thread of the process: less load-sensitive than the wall time
    try:
        if realtime:
            extra = _realtime(session, run, rec, float(speed), progress, int(cfg["odometry_queue"]))
        else:
            _deterministic(session, run, rec, every, progress, bool(cfg["prefetch"]))
    finally:
        session.close()
    wall = time.perf_counter() - wall0
    cpu = time.process_time() - cpu0
    monitor = session.monitor
    if len(rec.times):
        k0 = session.end(float(rec.times[-1]))
        if k0 is not None:      # the run ended before the tracked frames confirmed the last global fix
            rec.discard(k0, len(rec.times) - 1, mark=False)
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
        "cpu_seconds": cpu,
        "cpu_ms_per_frame": 1e3 * cpu / len(run) if len(run) else None,
        "duration_s": duration,
        **extra,
    }
    if reloc is not None and reloc.ms_retrieval:
        timings["ms_per_retrieval"] = float(np.mean(reloc.ms_retrieval))
        timings["global_searches"] = int(reloc.searches)
    poses = rec.poses.copy()
    poses[~rec.valid] = np.nan        # no world pose: nothing to report (the recorder may hold a placeholder)
    frames = {"time": rec.times, "place": rec.places, "detections": rec.detections, "inliers": rec.inliers,
              "localised": rec.localised, "distance_since_localisation": rec.distance,
              "integrity_alert": rec.alert.copy(), "signature_inliers": rec.signature_inliers,
              "point_inliers": rec.point_inliers}
    return Localisation(
        run=run, method=method.name, mode="realtime" if realtime else "deterministic",
        every=None if realtime else every, times=rec.times, poses=poses, valid=rec.valid.copy(), frames=frames,
        resets=resets, covariances=rec.covariances, detector_ran=rec.detector_ran, reasons=rec.reasons,
        failures=loc.failures, reset_times=list(loc.reset_times), corrupt=dict(sorted(rec.corrupt.items())),
        timings=timings, method_config=_json_safe(method.method_config()), oracle=oracle,
        oracle_reads=loc.oracle_reads, first_fix_time=loc.first_fix_time, relocalisations=list(loc.relocalisations),
        settings=_settings(resolved, None if realtime else every, realtime, speed, oracle),
        integrity_alerts=[a.as_dict() for a in monitor.alerts], integrity_stats=list(monitor.history),
        integrity_probations=dict(monitor.probations))


def _warn_weak_places(store: MapStore, run: SurveyRun) -> None:
    """Say before replaying when the route passes places too weak to localise (mapping.coverage)."""
    from scenesig.mapping.coverage import MIN_SIGNATURES, weak_places_on_route

    weak = weak_places_on_route(store, run)
    if weak:
        log.warning("map %s: %d place(s) on this run's route have fewer than %d signatures and will rarely "
                    "localise (expect dead reckoning and failures there): %s", store.root, len(weak),
                    MIN_SIGNATURES, ", ".join(map(str, weak)))


#: the layer check, kept under its old name (``scenesig.localiser.session.check_layers``)
_check_layers = check_layers


def _json_safe(obj):
    """Settings as plain JSON types (tuples and numpy values become lists and numbers)."""
    return json.loads(json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def check_camera(store: MapStore, run: SurveyRun, consistency: bool = True):
    """The run's camera against the map's and against its own images and odometry
    (:func:`scenesig.mapping.camera_check.assess`): a :class:`DataError` naming ``run.toml`` when it is clearly
    incompatible (another image size, a calibration its own turns contradict), a warning on stderr for
    each difference worth knowing (another camera, another mounting, a doubtful calibration)."""
    from scenesig.mapping.camera_check import assess, run_toml

    found = assess(run, store, consistency=consistency)
    for f in found.warnings:
        log.warning("%s: camera differs from the map %s's -- %s: %s", run_toml(run), store.root, f.what, f.reason)
    if found.errors:
        raise DataError(run_toml(run), "camera incompatible with the map " + str(store.root) + ": "
                        + "; ".join(f"{f.what}: {f.reason}" for f in found.errors))
    return found


def localise(map_root, run_root, out, method: str = "signatures", every: int = DEFAULT_EVERY, realtime: bool = False,
             speed: float = 1.0, config: dict | None = None, progress: bool = True, figure: bool = True,
             oracle: str | None = None, camera_check: bool = True) -> dict:
    """Open the map and the run, replay, write the outputs; returns ``metrics.json``'s content.

    ``map_root`` is the map folder, or a :class:`MapStore` already open (replays of one map in one
    process then share its cache of decoded places).  With ``oracle="none"`` the localiser's run is
    read without ``groundtruth.tum``, ``gps.csv`` and ``truth.tum``; the truth is read for the
    evaluation after the replay.  Before replaying, the run's camera is checked (:func:`check_camera`;
    ``camera_check=False`` skips the calibration check against the run's own images and odometry, the
    comparison with the map's camera is always made): a clearly incompatible one is refused with a
    :class:`DataError` and nothing is written.
    """
    result, store = localise_run(map_root, run_root, method, every=every, realtime=realtime, speed=speed,
                                 config=config, progress=progress, oracle=oracle, camera_check=camera_check)
    cfg = merge_settings(default_config, config, "replay", open=("localiser", "method", "relocalise", "integrity"))
    return write_outputs(result, store, out, cfg["max_path_distance_m"], figure=figure)


def localise_run(map_root, run_root, method: str = "signatures", every: int = DEFAULT_EVERY, realtime: bool = False,
                 speed: float = 1.0, config: dict | None = None, progress: bool = True,
                 oracle: str | None = None, camera_check: bool = True) -> tuple[Localisation, MapStore]:
    """:func:`localise` without writing: ``(result, store)``.  ``run_root`` is a run folder or a
    :class:`SurveyRun` already read (it must then carry its INS/GPS for ``oracle="ins"``)."""
    import dataclasses

    store = map_root if isinstance(map_root, MapStore) else MapStore.open(map_root)
    cfg = merge_settings(default_config, config, "replay", open=("localiser", "method", "relocalise", "integrity"))
    oracle = oracle or cfg["oracle"]
    blind = oracle == "none"
    given = isinstance(run_root, SurveyRun)
    if given:
        run = run_root
        if blind:        # the localiser must not see the INS/GPS, nor the truth
            run = dataclasses.replace(run, groundtruth_times=None, groundtruth_poses=None, truth_times=None,
                                      truth_poses=None, gps=None)
    else:
        run = read_run(run_root, skip=("groundtruth", "gps", "truth") if blind else ())
    if run.odometry_source == "none":
        # an image folder (scenesig import images): odometry.csv holds the identity, which is no motion
        raise DataError((run.root or Path(run.name)) / "run.toml",
                        "odometry_source is 'none' (an image-folder import): the localiser needs odometry; "
                        "without it, match the run against reference traverses with scenesig bench sequence")
    if not blind:
        _oracle(run)          # no INS/GPS: say so before anything else (DataError naming groundtruth.tum)
    cam = check_camera(store, run, consistency=camera_check)
    _warn_weak_places(store, run)
    result = replay(store, run, method, every=every, realtime=realtime, speed=speed, config=config,
                    progress=progress, oracle=oracle)
    result.camera_check = cam.as_dict()
    if blind:       # the evaluation's truth, read only now
        truth = run_root if given else read_run(run_root, check_images=False, skip=("groundtruth", "gps"))
        result.run = dataclasses.replace(run, truth_times=truth.truth_times, truth_poses=truth.truth_poses)
    return result, store


def method_options(method: str, match: str | None = None, point_map: str | None = None,
                   prior_gating: bool = True) -> dict:
    """The ``method`` config of :func:`replay` from the command line's options (an error for options
    the method does not have)."""
    opts = {}
    if not prior_gating:
        opts["prior_gating"] = False
    if method == "signatures":
        given = [f"--{k}" for k, v in (("match", match), ("point-map", point_map)) if v is not None]
        if given:
            raise ValueError(f"{' and '.join(given)} apply to the point-feature methods, not to signatures")
        return opts
    if method.startswith("hybrid"):
        # the point part takes the point options; the point map is in the method's name
        if point_map is not None and point_map != ("all" if method.endswith("-all") else "reference"):
            raise ValueError(f"--point-map {point_map} contradicts --method {method}")
        points = {"match": match} if match is not None else {}
        if not prior_gating:
            points["prior_gating"] = False
            return {"signatures": {"prior_gating": False}, "points": points}
        return {"points": points} if points else {}
    if match is not None:
        opts["match"] = match
    if point_map is not None:
        if "-" in method and point_map != method.split("-", 1)[1]:
            raise ValueError(f"--point-map {point_map} contradicts --method {method}")
        opts["point_map"] = point_map
    return opts
