"""The online localiser, one frame at a time: :class:`Session` (what a robot, a notebook or a ROS 2 node drives).

A session holds the three blocks of McManus et al. 2015 (§3.3, Fig. 6) for one vehicle -- the weak localiser
(detector + solver, :mod:`scenesig.localiser.methods`), the localiser block with its sliding-window pose graph
(:class:`scenesig.localiser.pipeline.Localiser`), the integrity monitor (:mod:`scenesig.localiser.integrity`) and,
without INS/GPS, the global search (:mod:`scenesig.localiser.relocalise`) -- and is fed as the sensors deliver::

    s = Session(store, camera, T_vehicle_camera, method="signatures", oracle="gnss")
    s.add_gnss(t, T_world_vehicle)            # optional prior (the oracle of the paper's protocol)
    s.add_odometry(t, T_increment)            # at the odometry rate (first call: the start, increment ignored)
    fix = s.add_image(t, image)               # a numpy array (grey or BGR), never a file; Fix or None
    est = s.pose(t)                           # latest estimate + covariance, by odometry between fixes
    s.state                                   # "searching" | "tracking" | "lost" | "alert"

The replay of a recorded run (:mod:`scenesig.localiser.replay`: ``scenesig localise``, ``--realtime``,
``compare``, the demo) is a driver over this class, so a run fed frame by frame through :meth:`add_image`
gives the replay's poses.

**Conventions.**  Poses are ``T_world_vehicle`` (4x4, the map's world frame; vehicle x forward, y left,
z up; metres).  ``T_increment`` is the vehicle at the previous odometry sample -> the vehicle at ``t``
(``T_prev⁻¹ T_t``).  Covariances are 6x6 in the vehicle frame, GTSAM's ``Pose3`` order -- rotation (rad)
then translation (m): ``(rx, ry, rz, tx, ty, tz)`` -- the pose graph's marginal.  Times are seconds on
one clock shared by all inputs (any epoch).  ``lateral_bound_95_m`` is the 95 % bound across the map's
reference path (:mod:`scenesig.localiser.uncertainty`, inflation included).

**Time rules** (the replay's, so that both give the same poses):

* A frame is processed once the odometry covers its time -- the motion prior is interpolated, never
  extrapolated.  A frame newer than the latest odometry sample is *held* (one slot; a newer frame
  replaces it, counted in ``frames_dropped``) and processed by the :meth:`add_odometry` call that reaches
  its time (that call returns its :class:`Fix`); :meth:`flush` processes it at once (end of the data).
* A frame may arrive late, or out of order, by up to ``max_latency_s`` (default 0.2 s: one detector period
  at the paper's 5 Hz, §4.3) behind the latest odometry: it is localised at its own time (the pose graph
  carries a past constraint through the stored odometry, :meth:`PoseGraph.add_localisation`).  Older frames
  are dropped (``frames_too_late``): their prior would rest on odometry the window may no longer hold.
* The failure rule (20 m on dead reckoning, McManus et al. 2015 §4.3; :mod:`scenesig.localiser.failure`) is
  applied to an odometry sample when the next one arrives (or at :meth:`flush`), so that a frame up to that
  sample's time is heard before the vehicle is declared failed.

**Oracle.**  ``oracle=None``: no INS/GPS -- the session finds itself on the map by global localisation and
relocalises when lost (state ``searching`` until then).  ``oracle="gnss"``: the poses given to
:meth:`add_gnss` start the localiser and reset it after a failure (the paper's protocol; interpolated between
samples, held at the ends); the session starts at the first odometry sample after the first GNSS pose.
A callable ``oracle(t) -> T_world_vehicle`` does the same from a pose known at any time (the replay's INS/GPS).
An oracle is never used to localise.
"""
from __future__ import annotations

import bisect
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.settings import merge_settings
from scenesig.surveys.validation import check_image, check_pose

from .methods import Measurement, MotionPrior, WeakLocaliser, make_method
from .pipeline import Localiser

__all__ = ["default_config", "STATES", "Estimate", "Fix", "FrameReport", "Session", "check_layers"]

#: The session's own settings; ``localiser``, ``relocalise``, ``method``, ``integrity`` are the replay's
#: sub-dicts (:data:`scenesig.localiser.replay.default_config`), so one configuration serves both.
default_config = {
    "max_latency_s": 0.2,     # frames later than this behind the newest odometry are dropped (one detector
                              # period at 5 Hz; None: never)
    "localiser": {},          # overrides of localiser.pipeline.default_config
    "relocalise": {},         # overrides of localiser.relocalise.default_config (oracle None)
    "method": {},             # the method's configuration
    "integrity": {},          # overrides of localiser.integrity.default_config
}

#: What :attr:`Session.state` says.
STATES = ("searching", "tracking", "lost", "alert")


@dataclass
class Estimate:
    """The vehicle pose at a time, with its uncertainty (:meth:`Session.pose`).

    Attributes
    ----------
    t : time (s).
    pose : (4,4) ``T_world_vehicle`` in the map's world frame (snapped to SE(2) on the local plane, §3.3.3).
    covariance : (6,6) marginal covariance, vehicle frame, GTSAM order (rx, ry, rz, tx, ty, tz).
    lateral_bound_95_m : 95 % bound across the map's reference path (m).
    distance_since_localisation : odometry distance since the last fix or reset (m).
    state : the session's :attr:`Session.state` when it was made.
    """

    t: float
    pose: np.ndarray
    covariance: np.ndarray
    lateral_bound_95_m: float
    distance_since_localisation: float
    state: str


@dataclass
class Fix(Estimate):
    """A localisation from one image (:meth:`Session.add_image`): the :class:`Estimate` at the image's time
    after the pose graph took the frame's constraint, and what made it.

    Attributes
    ----------
    place : the map's place the image was localised against.
    inliers : the solver's inliers (signature detections and/or point matches).
    integrity : ``"trusted"`` (a localisation), or ``"probation"`` (a global fix tracked but not yet
        confirmed by the integrity monitor: the pose is used, not yet called localised).
    """

    place: int = -1
    inliers: int = 0
    integrity: str = "trusted"


@dataclass
class FrameReport:
    """Everything one processed image did (:attr:`Session.last_frame`): what the replay records per frame.

    ``key`` is the caller's name for the frame (default its time); ``withdrawn_from`` the key of the first
    frame whose pose the integrity monitor withdrew with this one (a global fix it refused), else None.
    """

    key: object
    t: float
    place: int
    measurement: Measurement
    accepted: bool
    alert: bool = False
    withdrawn_from: object = None
    ms_detect: float = 0.0
    ms_solve: float = 0.0
    searched: bool = False        # a global search frame (no pose yet, no INS/GPS)
    fix: Fix | None = None


@dataclass
class _Job:
    """A frame between the detector and the solver stages."""

    key: object
    t: float
    prior: MotionPrior
    observation: object
    ms_detect: float


class Session:
    """Localise one vehicle online against a map, frame by frame (module docstring).

    Parameters
    ----------
    map : the map: a :class:`scenesig.mapping.store.MapStore` or its folder.
    camera : the camera (:class:`scenesig.surveys.geometry.Camera`); its image size must be the map's.
    T_vehicle_camera : (4,4) the camera's pose on the vehicle.
    method : a registered method name (``signatures``, ``orb``, ``hybrid``, ...) or a
        :class:`scenesig.localiser.methods.WeakLocaliser` (then the caller closes it).
    oracle : None (no INS/GPS: global localisation), ``"gnss"`` (the poses of :meth:`add_gnss`) or a callable
        ``oracle(t) -> T_world_vehicle``.
    config : overrides of :data:`default_config`.
    retrieval : the coarse place retrieval without an oracle (default: the map's descriptors).

    Attributes
    ----------
    localiser, monitor, relocaliser, method : the blocks (read them; the session drives them).
    last_frame : the :class:`FrameReport` of the latest processed image.
    frames_dropped : held frames replaced by a newer one before the odometry reached them.
    frames_too_late : frames later than ``max_latency_s``.
    frames_held : frames that arrived before the odometry reached them (processed later).

    The calls are made from one thread (a ROS 2 node's single-threaded executor; the replay's real-time mode
    runs the detector and solver stages on two threads through the session's own lock).
    """

    def __init__(self, map, camera, T_vehicle_camera, method: WeakLocaliser | str = "signatures", oracle=None,
                 config: dict | None = None, retrieval=None):
        from .integrity import IntegrityMonitor

        cfg = merge_settings(default_config, config, "session", open=("localiser", "method", "relocalise", "integrity"))
        self.config = cfg
        self.store = map if isinstance(map, MapStore) else MapStore.open(Path(map))
        if (camera.width, camera.height) != (self.store.camera.width, self.store.camera.height):
            raise ValueError(f"camera is {camera.width}x{camera.height} but the map {self.store.root} was built from "
                             f"{self.store.camera.width}x{self.store.camera.height} images")
        self.camera = camera
        self.T_vehicle_camera = check_pose(T_vehicle_camera, "T_vehicle_camera")
        self._gnss_t: list[float] = []
        self._gnss_T: list[np.ndarray] = []
        if oracle is None or callable(oracle):
            self._oracle = oracle
        elif oracle == "gnss":
            self._oracle = self._gnss_pose
        else:
            raise ValueError(f"oracle must be None, 'gnss' or a callable t -> T_world_vehicle, got {oracle!r}")
        self.oracle_kind = "gnss" if oracle == "gnss" else ("none" if oracle is None else "callable")
        self._own = isinstance(method, str)
        if self._own:
            check_layers(self.store, method)
            method = make_method(method, self.store, camera, self.T_vehicle_camera, cfg["method"] or None)
        self.method = method
        self.localiser = Localiser(self.store, self._oracle, cfg["localiser"] or None)
        self.relocaliser = None
        if self._oracle is None:
            from .relocalise import Relocaliser

            self.relocaliser = Relocaliser(self.store, method, self.localiser, cfg["relocalise"] or None,
                                           retrieval=retrieval)
        self.monitor: IntegrityMonitor | None = None    # made at the start (it says times from the start)
        self._monitor_cfg = cfg["integrity"] or None
        self._decide_lock = threading.Lock()   # the monitor's state: shared by the detector and solver stages
        self._path = None
        self.started = False
        self.t_start: float | None = None
        self.t_odometry: float | None = None   # the latest odometry sample
        self._pending_failure: float | None = None
        self._held: tuple | None = None        # (t, image, key) waiting for the odometry to reach t
        self.probation_key = None              # the frame whose global fix awaits confirmation
        self.last_frame: FrameReport | None = None
        self.frames_dropped = 0
        self.frames_too_late = 0
        self.frames_held = 0

    # ------------------------------------------------------------------------------ inputs
    def add_gnss(self, t: float, T_world_vehicle) -> None:
        """A GNSS/INS pose at time ``t`` (``oracle="gnss"``): it starts the localiser and resets it after a
        failure; never used to localise.  Samples may come in any order."""
        if self.oracle_kind != "gnss":
            raise ValueError("add_gnss needs a session made with oracle='gnss' (this one has "
                             f"oracle={self.oracle_kind!r})")
        T = check_pose(T_world_vehicle, "T_world_vehicle", rigid=True)
        t = _check_time(t)
        k = bisect.bisect_right(self._gnss_t, t)
        self._gnss_t.insert(k, t)
        self._gnss_T.insert(k, T)
        if len(self._gnss_t) > 20000:     # a long drive: the oracle is read at the start and at resets, now
            del self._gnss_t[:10000]
            del self._gnss_T[:10000]

    def _gnss_pose(self, t: float) -> np.ndarray:
        from scenesig.surveys.geometry import interpolate_poses

        return interpolate_poses(np.asarray(self._gnss_t), np.stack(self._gnss_T), float(t))

    def add_odometry(self, t: float, T_increment) -> Fix | None:
        """One odometry sample: the vehicle's motion from the previous sample to ``t``.  The first sample
        starts the session (its increment, the motion before it, is ignored); with ``oracle="gnss"`` samples
        before the first GNSS pose are ignored.  Returns the :class:`Fix` of a held frame this sample reached
        (None otherwise)."""
        t = _check_time(t)
        inc = check_pose(T_increment, "T_increment", rigid=True)
        if not self.started:
            if self.oracle_kind == "gnss" and not self._gnss_t:
                return None
            self.start(t)
            return None
        if t <= self.t_odometry:
            raise ValueError(f"odometry at t={t} is not after the previous sample (t={self.t_odometry}): samples must "
                             "come in time order")
        self._odometry(t, inc)
        fix = None
        if self._held is not None and self._held[0] <= t:
            th, img, key = self._held
            self._held = None
            fix = self._frame(max(th, self._t_start()), img, key)   # a frame before the start: at the start pose
        return fix

    def _t_start(self) -> float:
        if self.t_start is None:
            raise RuntimeError("the session has not started: give it an odometry sample first")
        return self.t_start

    def start(self, t: float) -> None:
        """Start at time ``t`` (the first odometry sample does it): from the oracle's pose, or not localised."""
        from .firing import load as load_firing
        from .integrity import IntegrityMonitor

        self.localiser.start(float(t))
        # the places' firing rates learnt at training drive the monitor's sequential test (docs/integrity.md)
        self.monitor = IntegrityMonitor(self._monitor_cfg, self.method.name, t0=float(t), firing=load_firing(self.store))
        self.started, self.t_start, self.t_odometry = True, float(t), float(t)

    def _odometry(self, t: float, inc: np.ndarray) -> None:
        """Integrate one sample; the failure rule for the previous one first (module docstring)."""
        if self._pending_failure is not None:
            self.localiser.check_failure(self._pending_failure)
        self.localiser.add_odometry(t, inc)
        self.t_odometry = t
        self._pending_failure = t

    def add_image(self, t: float, image, key=None) -> Fix | None:
        """Localise one camera image taken at ``t``: a uint8 numpy array, grey (H, W) or BGR (H, W, 3), of the
        camera's size.  Returns the :class:`Fix` when the frame localised the vehicle (or tracks a global fix
        on probation), else None -- also when the frame is held for the odometry or dropped as too late (the
        time rules, module docstring); :attr:`last_frame` says what the frame did.  ``key`` names the frame in
        :attr:`last_frame` (default ``t``)."""
        t = _check_time(t)
        img = check_image(image, "image", uint8=True)
        if img.shape[:2] != (self.camera.height, self.camera.width):
            raise ValueError(f"image is {img.shape[1]}x{img.shape[0]} but the camera is "
                             f"{self.camera.width}x{self.camera.height}")
        if img.ndim == 3 and img.shape[2] not in (1, 3):
            raise ValueError(f"image must be grey (H, W) or BGR (H, W, 3), got shape {img.shape}")
        key = t if key is None else key
        if not self.started or t > self.t_odometry:
            if self._held is not None:
                self.frames_dropped += 1
                if self._held[0] > t:        # out of order: keep the newer one
                    return None
            self._held = (t, img, key)
            self.frames_held += 1
            return None
        lim = self.config["max_latency_s"]
        if lim is not None and t < self.t_odometry - float(lim):
            self.frames_too_late += 1
            return None
        return self._frame(max(t, self._t_start()), img, key)

    def flush(self) -> Fix | None:
        """End of the data (or a pause): apply the failure rule to the latest odometry sample and process a
        held frame at once (its prior then ends at the latest odometry: not extrapolated)."""
        if self._pending_failure is not None:
            self.localiser.check_failure(self._pending_failure)
            self._pending_failure = None
        if self._held is None or not self.started:
            return None
        t, img, key = self._held
        self._held = None
        return self._frame(max(t, self._t_start()), img, key)

    # ------------------------------------------------------------------------------ outputs
    @property
    def state(self) -> str:
        """``searching`` (no pose from the map yet, or a global fix on probation), ``tracking``, ``lost``
        (blind beyond the localiser's ``lost_after_m``, or lost after a failure without an oracle) or
        ``alert`` (the integrity monitor refuses fixes: the map does not explain the images)."""
        loc = self.localiser
        if not self.started:
            return "searching"
        if self.monitor is not None and self.monitor.state == "alerted":
            return "alert"
        if loc.lost:
            return "searching" if loc.first_fix_time is None else "lost"
        if self.monitor is not None and self.monitor.state == "probation":
            return "searching"
        if loc.distance_since_localisation > loc.config["lost_after_m"]:
            return "lost"
        return "tracking"

    def pose(self, t: float | None = None) -> Estimate | None:
        """The estimate at ``t`` (default: the latest odometry time) -- the pose graph's smoothed keyframe
        carried by the odometry, with its marginal covariance; not extrapolated past the latest odometry
        (that pose is returned); a time before the window gets the window's first pose.  None without a world
        pose (before the first fix without an oracle, or lost)."""
        loc = self.localiser
        if not self.started or not loc.has_estimate:
            return None
        t = self.t_odometry if t is None else _check_time(t)
        T, C = loc.estimate_with_covariance(t)
        return Estimate(float(t), T, C, self._lateral_bound(T, C), float(loc.distance_since_localisation), self.state)

    def _lateral_bound(self, T: np.ndarray, C: np.ndarray) -> float:
        from .evaluation import reference_path
        from .uncertainty import frame_bounds, planar_covariances

        if self._path is None:
            self._path = reference_path(self.store)
        b = frame_bounds(T[None], planar_covariances(T[None], C[None]), self._path)
        return float(b["lateral_bound_95_m"][0])

    # ------------------------------------------------------------------------------ the per-frame step
    def _frame(self, t: float, image, key, prepared=None, ms_prepare: float = 0.0, gray=None) -> Fix | None:
        """Detector, solver, integrity, pose graph for one frame at ``t`` (or the global search while lost
        without an oracle).  ``prepared``: the method's :meth:`WeakLocaliser.prepare` of ``image`` made ahead
        (the replay's prefetch), ``ms_prepare`` its time; ``gray``: a callable giving the grey image for the
        search's place retrieval (default: converted from ``image``)."""
        img = self._for_method(image) if prepared is None else prepared
        out = self._detect_stage(t, img, key, ms_prepare, image if gray is None else gray)
        if isinstance(out, _Job):
            out = self._solve_stage(out)
        return out.fix

    def _for_method(self, image):
        """The image as the method wants it: grey, or BGR (``method.color``)."""
        import cv2

        a = np.asarray(image)
        if a.ndim == 3 and a.shape[2] == 1:
            a = a[:, :, 0]
        if self.method.color and a.ndim == 2:
            return cv2.cvtColor(a, cv2.COLOR_GRAY2BGR)
        if not self.method.color and a.ndim == 3:
            return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
        return a

    def _detect_stage(self, t: float, img, key, ms_prepare: float = 0.0, gray=None):
        """The detector stage: a :class:`_Job` for :meth:`_solve_stage`, or -- a global search frame, done
        whole here -- its :class:`FrameReport`."""
        loc = self.localiser
        if self.relocaliser is not None and loc.lost:
            with self._decide_lock:
                return self._search(t, img, key, ms_prepare, gray)
        prior = loc.prior(t)
        self.method.prefetch(prior.next_place)
        t0 = time.perf_counter()
        obs = self.method.detect(img, prior.place, prior)      # an image or its prepare() result
        return _Job(key, t, prior, obs, ms_prepare + 1e3 * (time.perf_counter() - t0))

    def _solve_stage(self, job: _Job) -> FrameReport:
        """The solver stage, the integrity monitor's verdict and the pose graph: the frame's report."""
        t0 = time.perf_counter()
        m = Measurement.coerce(self.method.solve(job.observation, job.prior.place, job.prior))
        ms_solve = 1e3 * (time.perf_counter() - t0)
        with self._decide_lock:
            rep = FrameReport(job.key, job.t, job.prior.place, m, False, ms_detect=job.ms_detect, ms_solve=ms_solve)
            rep.accepted = self._decide(rep, job.prior)
            if m.constraint is not None and (rep.accepted or m.reason == "integrity_probation"):
                rep.fix = self._fix(rep, "trusted" if rep.accepted else "probation")
            self.last_frame = rep
        return rep

    def _search(self, t: float, img, key, ms_prepare: float, gray) -> FrameReport:
        """Global search for a frame (no pose, no oracle): retrieval, verification, sequence check."""
        if isinstance(img, np.ndarray):
            raw = img
        else:
            raw = gray() if callable(gray) else self._grey(gray)
        r = self.relocaliser.search(img, t, raw)
        accepted = r.accepted
        rep = FrameReport(key, t, r.place, r.measurement, False, searched=True,
                          ms_detect=ms_prepare + r.ms_retrieval + r.ms_detect, ms_solve=r.ms_solve)
        mon = self.monitor
        if mon.searching(t, r.place, self.localiser.distance_at(t), r.verified):
            rep.alert = True
        if accepted and mon.active:
            # a global fix is tentative until tracked frames confirm it (localiser.integrity)
            mon.begin_probation(t)
            self.probation_key = key
            accepted = False
            r.measurement.reason = "integrity_probation"
        rep.accepted = accepted
        if r.accepted:
            rep.fix = self._fix(rep, "trusted" if accepted else "probation")
        self.last_frame = rep
        return rep

    @staticmethod
    def _grey(image) -> np.ndarray:
        import cv2

        a = np.asarray(image)
        return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY) if a.ndim == 3 and a.shape[2] == 3 else a.reshape(a.shape[:2])

    def _decide(self, rep: FrameReport, prior) -> bool:
        """The integrity monitor's verdict on a tracked frame's measurement, applied; True if accepted."""
        loc, mon, m, t = self.localiser, self.monitor, rep.measurement, rep.t
        if mon is None or not mon.active:
            return loc.add_measurement(t, m)
        from .integrity import frame_stats

        verdict = mon.assess(frame_stats(t, prior.place, prior, m, loc.distance_at(t)))
        if verdict == "accept":
            self.probation_key = None
            return loc.add_measurement(t, m)
        if verdict == "tentative":          # probation: tracks the tentative fix, not yet a localisation
            loc.add_measurement(t, m)
            if m.constraint is not None:
                m.reason = "integrity_probation"
            return False
        m.reason = "integrity_alert"
        rep.alert = True
        if verdict == "alert" and loc.oracle is None:
            k0 = self.probation_key
            loc.discard(t, undo_fix=k0 is not None)
            if k0 is not None:
                rep.withdrawn_from = k0
            self.probation_key = None
        return False

    def _fix(self, rep: FrameReport, integrity: str) -> Fix | None:
        loc = self.localiser
        if not loc.has_estimate:
            return None
        T, C = loc.estimate_with_covariance(rep.t)
        return Fix(rep.t, T, C, self._lateral_bound(T, C), float(loc.distance_since_localisation), self.state,
                   int(rep.place), int(rep.measurement.inliers), integrity)

    def end(self, t: float | None = None):
        """The data ended (at ``t``, default the latest odometry time): a global fix still on probation was
        never confirmed -- it is forgotten.  Returns the key of the first frame whose pose that withdraws (None
        when nothing is)."""
        mon = self.monitor
        if mon is not None and mon.state == "probation" and self.probation_key is not None:
            self.localiser.discard(float(self.t_odometry if t is None else t), undo_fix=True)
            k0, self.probation_key = self.probation_key, None
            return k0
        return None

    def close(self) -> None:
        """Release the method's threads and caches (a method given as an object is the caller's to close)."""
        if self._own:
            self.method.close()

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_layers(store: MapStore, method: str) -> None:
    """A method whose map layer the map lacks is an error naming the map, the layer and the fix."""
    from scenesig.mapping.layers import method_layers, missing_layers, store_layers
    from scenesig.surveys.errors import DataError

    try:
        method_layers(method)
    except ValueError:
        return                     # a method registered by other code: it checks its own map data
    have = store_layers(store)
    missing = missing_layers(have, method)
    if missing:
        raise DataError(store.root / "manifest.json",
                        f"method {method!r} needs the map layer {', '.join(missing)}, which this map lacks (it has "
                        f"{', '.join(have)}); build the map with build-map --layers {','.join([*have, *missing])}, or "
                        f"add it with scenesig map add-layers {store.root} --reference RUN "
                        f"--layers {','.join(missing)}")


def _check_time(t) -> float:
    t = float(t)
    if not np.isfinite(t):
        raise ValueError(f"time must be finite, got {t}")
    return t

