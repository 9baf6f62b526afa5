"""The online localisation pipeline (McManus et al. 2015, §3.3, Fig. 6): the localiser block.

Three blocks, as in the paper's Fig. 6:

* **Detector** -- finds a method's measurements in a live image for the current place
  (:meth:`scenesig.localiser.methods.WeakLocaliser.detect`; for scene signatures
  :class:`scenesig.localiser.detector.Detector`);
* **Solver** -- turns them into a localisation constraint with covariance, or none
  (:meth:`scenesig.localiser.methods.WeakLocaliser.solve`; for scene signatures the eq. 10 solver of
  :mod:`scenesig.localiser.solver`);
* **Localiser** (:class:`Localiser`, this module) -- integrates odometry at its full rate into a sliding-window
  pose graph (:class:`scenesig.localiser.posegraph.PoseGraph`), adds the localisation constraints, snaps every
  estimate to SE(2) on the local plane of the two nearest map places (:class:`scenesig.localiser.se2.PlaneSnapper`),
  chooses the nearest place (position and heading), hands the detector and solver their motion prior,
  and applies the failure rule: more than 20 m on dead reckoning since the last localisation -> reset
  from the oracle (the run's INS/GPS) and count a failure.

The weak-localiser interface (:class:`MotionPrior`, :class:`Measurement`, :class:`WeakLocaliser`) and the
method registry (:func:`register_method`, :func:`available_methods`, :func:`make_method`) live in
:mod:`scenesig.localiser.methods`; the scene-signature method (:class:`SignatureLocaliser`,
:data:`signature_default_config`) in :mod:`scenesig.localiser.signature_method`.  This module re-exports
them (the localiser's whole interface is importable from here); point features (ORB / SIFT / XFeat) and the
hybrid plug in as other registered implementations, and everything else (replay, failure rule, outputs,
metrics) is shared.

Driving the blocks in time order (deterministic or real-time) is :mod:`scenesig.localiser.replay`'s job.
"""
from __future__ import annotations

import bisect
import threading
import time
from collections import deque
from typing import Callable

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.geometry import invert, log_so3
from scenesig.surveys.settings import merge_settings

from .failure import FAILURE_DISTANCE_M, is_failure

# The interfaces, the registry and the scene-signature method: part of this module's interface (see above).
from .methods import Measurement, MotionPrior, WeakLocaliser, available_methods, make_method, register_method
from .posegraph import PoseGraph
from .se2 import PlaneSnapper
from .signature_method import SignatureLocaliser, signature_default_config
from .solver import LocalisationConstraint, pose_log
from .uncertainty import INNOVATION_FACTOR, INNOVATION_WINDOW, innovation_variance

__all__ = ["default_config", "signature_default_config", "MotionPrior", "Measurement", "WeakLocaliser", "SignatureLocaliser", "Localiser",
           "register_method", "make_method", "available_methods", "odometry_covariance"]

#: Localiser-block parameters.  Sigmas are in GTSAM's Pose3 order (rotation rad, then translation m),
#: in the vehicle frame (x forward, y left, z up).
default_config = {
    # Odometry noise: a random walk, variance growing linearly with the distance of each increment
    # (σ² · d) plus a per-sample floor (so standing still is not infinitely certain).
    "odometry_sigma_per_sqrt_m": [0.002, 0.002, 0.004, 0.04, 0.04, 0.02],
    "odometry_sigma_floor": [1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3],
    # An oracle (INS/GPS) pose: the start and every reset (a GPS-aided INS is good to ~2 m).
    "oracle_sigma": [0.01, 0.01, 0.02, 2.0, 2.0, 0.3],
    # P_x handed to the solver is the pose graph's marginal plus this (its floor): after many
    # localisations the marginal becomes tighter than the map itself is accurate, and the solver
    # would then gate good localisations as "inconsistent with the prior".
    "prior_floor_sigma": [0.003, 0.003, 0.005, 0.2, 0.2, 0.05],
    "failure_distance_m": FAILURE_DISTANCE_M,   # McManus et al. 2015, §4.3 (localiser.failure)
    "lost_after_m": 10.0,            # beyond this distance blind the detector searches the whole image
    "max_heading_diff_deg": 90.0,    # a place passed the other way round is not "nearest"
    # Without an oracle (``oracle=None``): the covariance of a pose found by global localisation or
    # relocalisation (the graph restarts from it); the sequence check already vetted it.
    "fix_sigma": [0.01, 0.01, 0.02, 0.5, 0.5, 0.2],
    # The stated covariance adds the planar variance the recent localisations' innovations show
    # (localiser.uncertainty.innovation_variance): the mean over this many, times this factor.  0 leaves
    # the marginal alone.
    "innovation_window": INNOVATION_WINDOW,
    "innovation_factor": INNOVATION_FACTOR,
    # A localisation enters the pose graph only from a new view: the camera moved this far or turned this
    # much (odometry) since the last one that entered.  A standing vehicle's frames see the same view, so
    # their errors are one error (the map's and that view's); counted as independent they shrink the
    # covariance while the error stays (issue 35: on one set of worlds 13 % of standing frames fell outside
    # their bound against 1.3 % of moving ones).  Above the odometry's drift standing still (~0.04 m,
    # ~0.4 deg over seconds), far below the spacing of frames in motion (~1 m at 5 m/s and 5 Hz).
    "view_baseline_m": 0.25,
    "view_turn_deg": 2.0,
    "posegraph": {},                 # overrides of localiser.posegraph.default_config
}


def odometry_covariance(T_increment: np.ndarray, sigma_per_sqrt_m, sigma_floor) -> np.ndarray:
    """6x6 covariance of one odometry increment: ``diag(σ_d² · d + σ_0²)``, ``d`` its length (m)."""
    d = float(np.linalg.norm(np.asarray(T_increment)[:3, 3]))
    return np.diag(np.asarray(sigma_per_sqrt_m, float) ** 2 * d + np.asarray(sigma_floor, float) ** 2)


# ------------------------------------------------------------------------------------------------
# the localiser block
# ------------------------------------------------------------------------------------------------
class Localiser:
    """Odometry integration, pose graph, SE(2) snapping, place choice and the failure rule.

    Thread-safe: the real-time replay feeds odometry from one thread and measurements from another.

    Parameters
    ----------
    store : the map (places and their poses: the keyframes of the SE(2) snapping).
    oracle : ``oracle(t) -> T_world_vehicle``, the run's INS/GPS pose at time t, used to start and to
        reset after a failure (never to localise); the paper's protocol.  ``None``: no INS/GPS at all --
        the localiser starts *not localised* and dead-reckons from an arbitrary origin until a pose
        found from the map (:meth:`fix`, by :class:`scenesig.localiser.relocalise.Relocaliser`) starts the pose
        graph; after a failure it declares itself *lost*, keeps dead-reckoning and waits for the next
        fix (a relocalisation).
    config : overrides of :data:`default_config`.

    Attributes
    ----------
    oracle_reads : times the oracle was read (0 without one).
    failures : oracle resets (with an oracle) or times it declared itself lost (without).
    lost : True while not localised (before the first fix, or after a failure, without an oracle).
    first_fix_time : time of the first pose found from the map (without an oracle).
    relocalisations : ``(t_lost, t_found)`` of every recovery (without an oracle).
    """

    def __init__(self, store: MapStore, oracle: Callable[[float], np.ndarray] | None, config: dict | None = None):
        cfg = merge_settings(default_config, config, "localiser", open=("posegraph",))   # PoseGraph checks it
        self.config = cfg
        self.store = store
        if len(store) < 2:
            raise ValueError(f"map {store.root} has {len(store)} place(s); the localiser needs at least 2")
        self._place_ids = np.array(sorted(store.places), dtype=int)
        self.snapper = PlaneSnapper(np.stack([store.places[i].T_world_place for i in self._place_ids]))
        self.oracle = oracle
        self.oracle_reads = 0
        self.lost = oracle is None
        self.first_fix_time: float | None = None
        self.lost_time: float | None = None
        self.relocalisations: list[tuple[float, float]] = []
        self._fix_cov = np.diag(np.asarray(cfg["fix_sigma"], float) ** 2)
        # Dead reckoning on its own (the odometry source's arbitrary frame): the relocaliser's
        # sequence check compares poses found at different times through it, and without an
        # oracle it is all there is before the first fix.  A bounded history of cumulative poses.
        self._odo_t: list[float] = []
        self._odo_T: list[np.ndarray] = []
        self.graph = PoseGraph(config=cfg["posegraph"] or None)
        self._oracle_cov = np.diag(np.asarray(cfg["oracle_sigma"], float) ** 2)
        self._floor = np.diag(np.asarray(cfg["prior_floor_sigma"], float) ** 2)
        self._max_dyaw = np.radians(cfg["max_heading_diff_deg"])
        self._lock = threading.RLock()
        self.failures = 0
        self.reset_times: list[float] = []
        self.localisation_times: list[float] = []
        # Odometry distance: cumulative total and its history (for localisations that arrive late).
        self._cum = 0.0
        self._cum_t: list[float] = []
        self._cum_d: list[float] = []
        self._fix = 0.0                   # cumulative distance at the last localisation or reset
        self.odometry_seconds = 0.0
        self.n_odometry = 0
        # planar innovations (m) of the latest localisations: the stated covariance's innovation term
        self._innovations: deque[float] = deque(maxlen=max(int(cfg["innovation_window"]), 1))
        self._view_t: float | None = None     # time of the last view that entered the graph (a fix too)

    # --------------------------------------------------------------------------- state
    @property
    def started(self) -> bool:
        return self.graph.initialised

    @property
    def has_estimate(self) -> bool:
        """True once there is a world pose (from the oracle or from a fix)."""
        return self.graph.initialised

    def start(self, t: float) -> None:
        """Initialise from the oracle at time t (not a failure); without an oracle: not localised yet."""
        with self._lock:
            self._odo_t, self._odo_T = [float(t)], [np.eye(4)]
            self._cum_t, self._cum_d = [float(t)], [self._cum]
            if self.oracle is not None:
                self._reset(t)

    def _reset(self, t: float) -> None:
        T = np.asarray(self.oracle(t), dtype=float)
        self.oracle_reads += 1
        self.graph.reset(t, T, self._oracle_cov)
        self._view_t = None
        self._fix = self._cum
        self._cum_t, self._cum_d = [float(t)], [self._cum]

    def odometry_pose(self, t: float) -> np.ndarray:
        """Cumulative dead-reckoned pose at time t in the odometry's own frame (interpolated, clamped)."""
        from scenesig.surveys.geometry import interpolate_poses

        with self._lock:
            ts, Ts = self._odo_t, self._odo_T
            if not ts:
                raise RuntimeError("Localiser.start() first")
            if t <= ts[0]:
                return Ts[0].copy()
            if t >= ts[-1]:
                return Ts[-1].copy()
            i = bisect.bisect_left(ts, t)
            return interpolate_poses(np.array(ts[i - 1:i + 1]), np.stack(Ts[i - 1:i + 1]), float(t)).reshape(4, 4)

    def odometry_between(self, t_a: float, t_b: float) -> np.ndarray:
        """Dead-reckoned motion from time t_a to t_b (``T_{a,b}``)."""
        return invert(self.odometry_pose(t_a)) @ self.odometry_pose(t_b)

    def fix(self, t: float, T_world_vehicle: np.ndarray, covariance: np.ndarray | None = None) -> None:
        """A pose found from the map at time t (global localisation or relocalisation): (re)start the graph.

        The graph restarts at the latest odometry time from the fix carried forward by the odometry
        since; the localiser is localised again (and a recovery from lost is counted).
        """
        with self._lock:
            # what :meth:`discard` restores when the integrity monitor rejects this fix
            self._before_fix = (self.first_fix_time, len(self.relocalisations), self.lost_time)
            t_now = self._odo_t[-1]
            T_now = np.asarray(T_world_vehicle, float) @ self.odometry_between(t, t_now)
            cov = self._fix_cov if covariance is None else 0.5 * (covariance + covariance.T) + self._floor
            self.graph.reset(t_now, T_now, cov)
            self._view_t = float(t)
            self._fix = self.distance_at(t)
            self._cum_t, self._cum_d = [float(t_now)], [self._cum]
            self.localisation_times.append(float(t))
            if self.first_fix_time is None:
                self.first_fix_time = float(t)
            elif self.lost_time is not None:
                self.relocalisations.append((self.lost_time, float(t)))
            self.lost, self.lost_time = False, None

    def discard(self, t: float, undo_fix: bool = False) -> None:
        """Drop the pose: the integrity monitor (:mod:`scenesig.localiser.integrity`) found that the map does not
        explain the run.  The localiser has no world pose until the next fix (without an oracle) or
        resets from the oracle at the failure rule (with one: the graph is kept, the oracle's pose is
        independent of the map).  ``undo_fix``: the fix that started the graph was never confirmed --
        it is forgotten (first fix time, relocalisation)."""
        with self._lock:
            if self.oracle is not None:
                return
            if undo_fix and getattr(self, "_before_fix", None) is not None:
                self.first_fix_time, n, lost_time = self._before_fix
                del self.relocalisations[n:]
                self.lost_time = lost_time if lost_time is not None else float(t)
            elif self.lost_time is None:
                self.lost_time = float(t)
            self._before_fix = None
            self._view_t = None
            self.graph = PoseGraph(config=self.config["posegraph"] or None)
            self.lost = True

    @property
    def distance_since_localisation(self) -> float:
        """Odometry distance (m) since the last localisation or reset."""
        return self._cum - self._fix

    def distance_at(self, t: float) -> float:
        """Cumulative odometry distance at time t (interpolated; clamped to the history)."""
        i = bisect.bisect_left(self._cum_t, t)
        if i >= len(self._cum_t):
            return self._cum
        if i == 0:
            return self._cum_d[0]
        t0, t1 = self._cum_t[i - 1], self._cum_t[i]
        d0, d1 = self._cum_d[i - 1], self._cum_d[i]
        return d0 + (d1 - d0) * (t - t0) / (t1 - t0) if t1 > t0 else d1

    # ------------------------------------------------------------------------ odometry
    def add_odometry(self, t: float, T_increment: np.ndarray) -> None:
        """One odometry increment (vehicle at the previous sample -> vehicle at t), at the full rate."""
        cfg = self.config
        cov = odometry_covariance(T_increment, cfg["odometry_sigma_per_sqrt_m"], cfg["odometry_sigma_floor"])
        t0 = time.perf_counter()
        with self._lock:
            if self.graph.initialised:
                self.graph.add_odometry(t, T_increment, cov)
            self._odo_t.append(float(t))
            self._odo_T.append(self._odo_T[-1] @ np.asarray(T_increment, float))
            if len(self._odo_t) > 8192:      # the sequence check looks back tens of metres: bounded
                del self._odo_t[:4096]
                del self._odo_T[:4096]
            self._cum += float(np.linalg.norm(np.asarray(T_increment)[:3, 3]))
            self._cum_t.append(float(t))
            self._cum_d.append(self._cum)
            if len(self._cum_t) > 4096:      # the window is seconds long; keep a bounded history
                del self._cum_t[:2048]
                del self._cum_d[:2048]
        self.odometry_seconds += time.perf_counter() - t0
        self.n_odometry += 1

    def check_failure(self, t: float) -> bool:
        """The failure rule (:func:`scenesig.localiser.failure.is_failure`): blind for more than ``failure_distance_m``
        -> reset from the oracle at t, or, without an oracle, declare itself lost (once; dead reckoning goes
        on until a relocalisation)."""
        with self._lock:
            if self.lost or not is_failure(self.distance_since_localisation, self.config["failure_distance_m"]):
                return False
            self.failures += 1
            self.reset_times.append(float(t))
            if self.oracle is None:
                self.lost, self.lost_time = True, float(t)
            else:
                self._reset(t)
            return True

    # ------------------------------------------------------------------------- outputs
    def estimate(self, t: float | None = None) -> np.ndarray:
        """Snapped ``T_world_vehicle`` at time t (default: the latest)."""
        with self._lock:
            return self.snapper.snap(self._graph_estimate(t))

    def _graph_estimate(self, t: float | None) -> np.ndarray:
        # A time before the window (a frame from before a reset, in real-time mode) gets the
        # window's first pose: the graph cannot go back and the oracle must not be consulted.
        try:
            return self.graph.estimate(t)
        except ValueError:
            if t is None:
                raise
            return self.graph.estimate(float(self.graph.keyframes()[0][0]))

    def estimate_with_covariance(self, t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Snapped ``T_world_vehicle`` at time t and the 6x6 covariance of the pose there (vehicle frame, GTSAM
        order): the marginal (:meth:`scenesig.localiser.posegraph.PoseGraph.estimate_with_covariance`) plus the
        recent innovations' planar variance (:func:`scenesig.localiser.uncertainty.innovation_variance`).  A
        time before the window gets the window's first pose, as :meth:`estimate` does."""
        with self._lock:
            try:
                T, C = self.graph.estimate_with_covariance(t)
            except ValueError:
                if t is None:
                    raise
                T, C = self.graph.estimate_with_covariance(float(self.graph.keyframes()[0][0]))
            v = innovation_variance(self._innovations, self.config["innovation_factor"])
            if v > 0.0:
                C = C.copy()
                C[3, 3] += v         # vehicle-frame x, y: isotropic in the plane, so in the world too
                C[4, 4] += v
            return self.snapper.snap(T), C

    def covariance(self, t: float | None = None) -> np.ndarray:
        """6x6 marginal covariance of the pose at time t (see :meth:`estimate_with_covariance`)."""
        return self.estimate_with_covariance(t)[1]

    def nearest_place(self, T_world_vehicle: np.ndarray) -> int:
        return self.store.nearest_place(T_world_vehicle, max_heading_diff=self._max_dyaw)

    def place_ahead(self, place: int, T_world_vehicle: np.ndarray) -> int | None:
        """The neighbour of ``place`` that lies ahead of the vehicle (the next place to prefetch)."""
        meta = self.store.places[place]
        fwd = np.asarray(T_world_vehicle)[:3, 0]
        best, best_d = None, np.inf
        for n in meta.neighbours:
            d = self.store.places[n].position - meta.position
            along = float(d @ fwd)
            if along > 0 and along < best_d:
                best, best_d = n, along
        return best

    def prior(self, t: float) -> MotionPrior:
        """The motion prior for a frame at time t: snapped estimate, floored covariance, place."""
        with self._lock:
            T = self.snapper.snap(self._graph_estimate(t))
            P = self.graph.covariance() + self._floor
            blind = self.distance_since_localisation
        P = 0.5 * (P + P.T)
        place = self.nearest_place(T)
        return MotionPrior(float(t), T, P, place, self.store.places[place].T_world_place, self.place_ahead(place, T),
                           blind > self.config["lost_after_m"], blind)

    def add_measurement(self, t: float, measurement: Measurement | LocalisationConstraint | None) -> bool:
        """Add a weak localiser's answer for the frame at t; True if a localisation was accepted.

        A localisation from the view that last entered the graph (:meth:`same_view`) is accepted -- the
        frame is localised, the detections agree -- but adds nothing: neither a constraint nor an innovation.
        """
        m = Measurement.coerce(measurement)
        c = m.constraint
        if c is None:
            return False
        with self._lock:
            if self.lost:        # without an oracle only the relocaliser's vetted fixes end "lost"
                return False
            if self.same_view(t):
                ok = True
            else:
                if self.graph.initialised:
                    # the detections' pose against the prediction, as the integrity monitor's innovation
                    nu = pose_log(invert(self.snapper.snap(self._graph_estimate(t))) @ c.T_world_vehicle_detections)
                    self._innovations.append(float(np.linalg.norm(nu[3:5])))
                ok = self.graph.add_localisation(t, c.T_world_vehicle_detections, information=c.information_detections)
                if ok:
                    self._view_t = float(t)
            if ok:
                d = self.distance_at(t)
                # A late localisation (real-time mode) counts from its own time, never backwards.
                self._fix = max(self._fix, d)
                self.localisation_times.append(float(t))
            return ok

    def same_view(self, t: float) -> bool:
        """True if the camera at time t has moved less than ``view_baseline_m`` and turned less than
        ``view_turn_deg`` (odometry) since the last view that entered the graph."""
        if self._view_t is None:
            return False
        T = self.odometry_between(self._view_t, t)
        turn = np.degrees(np.linalg.norm(log_so3(T[:3, :3])))
        return bool(np.linalg.norm(T[:3, 3]) < self.config["view_baseline_m"] and turn < self.config["view_turn_deg"])

    @property
    def ms_per_odometry_update(self) -> float:
        return 1e3 * self.odometry_seconds / max(self.n_odometry, 1)
