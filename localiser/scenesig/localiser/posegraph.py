"""Sliding-window pose graph of the localiser (McManus et al. 2015, §3.3.2, Fig. 6).

The graph holds vehicle poses ``T_world_vehicle`` at *keyframes* over the last ``window_seconds``
and three kinds of constraint: (i) odometry between consecutive keyframes, (ii) sparse
localisation constraints from the solver (a robust Huber prior in the world frame), and (iii) a
prior on the window's first pose -- the one set at :meth:`PoseGraph.reset`, and afterwards the
linear marginal that ``gtsam.IncrementalFixedLagSmoother`` keeps when it drops old keyframes.

Odometry arrives at ~20 Hz; keyframes are made at every localisation and otherwise every
``keyframe_interval_s`` (0.25 s).  Between two keyframes there is nothing but odometry, so
composing the increments into one between-factor (mean exactly, covariance to first order) loses
nothing that intermediate nodes would have carried, while the smoother's update cost stays fixed
per keyframe rather than per odometry message.  Poses between keyframes -- in particular the latest,
which the localiser publishes at the odometry rate -- are the nearest earlier keyframe's estimate
composed with the odometry since.

Conventions: GTSAM ``Pose3`` -- tangent ``(ω, v)``, right perturbation ``T = T̄·Exp(ξ)``; odometry
covariances are of the increment in its end frame, localisation covariances are of the pose in the
vehicle frame (what :mod:`scenesig.localiser.solver` produces).

The failure rule of the paper (§4.3) is the localiser block's, not the graph's: :mod:`scenesig.localiser.failure`.
"""
from __future__ import annotations

import bisect
import time

import gtsam
import numpy as np

from scenesig.surveys.geometry import invert
from scenesig.surveys.settings import merge_settings
from scenesig.surveys.validation import check_covariance, check_pose

from .solver import pose_exp, pose_log

__all__ = ["default_config", "PoseGraph"]

default_config = {
    "window_seconds": 5.0,        # smoother lag: keyframes older than this are marginalised
    "keyframe_interval_s": 0.25,  # a keyframe at least this often (and at every localisation)
    "huber_k": 3.0,               # Huber threshold on a localisation's 6-dof Mahalanobis norm
    "information_floor": 1e-6,    # added to a localisation's information: a direction the detections
                                  # do not see gets σ = 1000 m / rad instead of a singular system
    "relinearize_threshold": 0.01,
    "extra_iterations": 1,        # extra iSAM2 iterations after a localisation (it can move the window)
}


def _adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a pose in GTSAM's (ω, v) order: Exp(Ad_T ξ) = T Exp(ξ) T^{-1}."""
    return gtsam.Pose3(T).AdjointMap()


def _check_pose(T, name) -> np.ndarray:
    return check_pose(T, name, rigid=True)


def _check_spd(M, name) -> np.ndarray:
    return check_covariance(M, 6, name, symmetrise=True)


class PoseGraph:
    """Sliding-window smoother of ``T_world_vehicle`` with odometry and localisation constraints.

    Parameters
    ----------
    window_seconds, keyframe_interval_s, huber_k :
        shortcuts for the :data:`default_config` entries of the same name.
    config : further overrides of :data:`default_config`.

    Examples
    --------
    >>> g = PoseGraph(window_seconds=5.0)
    >>> g.reset(0.0, T0, np.diag([1e-4] * 3 + [1e-2] * 3))
    >>> g.add_odometry(0.05, T_inc, cov_inc)            # at the odometry rate
    >>> g.add_localisation(0.2, c.T_world_vehicle_detections, information=c.information_detections)
    >>> T = g.estimate()                                 # latest pose
    """

    def __init__(self, window_seconds: float | None = None, keyframe_interval_s: float | None = None,
                 huber_k: float | None = None, config: dict | None = None):
        cfg = merge_settings(default_config, config, "pose-graph")
        for k, v in (("window_seconds", window_seconds), ("keyframe_interval_s", keyframe_interval_s),
                     ("huber_k", huber_k)):
            if v is not None:
                cfg[k] = float(v)
        if cfg["window_seconds"] <= cfg["keyframe_interval_s"]:
            raise ValueError("window_seconds must exceed keyframe_interval_s")
        self.config = cfg
        self._smoother = None
        self._marginals: dict = {}
        self._next_index = 0
        self.n_updates = 0
        self.update_seconds = 0.0   # total time spent in smoother updates (for ms per update)

    # ------------------------------------------------------------------------ state helpers
    @property
    def initialised(self) -> bool:
        return self._smoother is not None

    def _require(self):
        if self._smoother is None:
            raise RuntimeError("PoseGraph: call reset(t, T_world_vehicle, cov) before anything else")

    @property
    def latest_time(self) -> float:
        """Time of the latest odometry (or keyframe) the graph knows."""
        self._require()
        return self._odo_times[-1] if self._odo_times else self._kf_times[-1]

    def _new_key(self) -> int:
        key = gtsam.symbol("x", self._next_index)
        self._next_index += 1
        return key

    # ------------------------------------------------------------------------------ reset
    def reset(self, t: float, T_world_vehicle: np.ndarray, cov: np.ndarray) -> None:
        """(Re)start the graph at time ``t`` with a prior pose (initialisation, or an oracle reset).

        Everything before is forgotten.
        """
        T = _check_pose(T_world_vehicle, "T_world_vehicle")
        cov = _check_spd(cov, "cov")
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config["relinearize_threshold"])
        params.relinearizeSkip = 1
        self._smoother = gtsam.IncrementalFixedLagSmoother(self.config["window_seconds"], params)
        key = self._new_key()
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(key, gtsam.Pose3(T), gtsam.noiseModel.Gaussian.Covariance(cov)))
        values = gtsam.Values()
        values.insert(key, gtsam.Pose3(T))
        self._kf_times = [float(t)]
        self._kf_keys = [key]
        self._update(graph, values, {key: float(t)})
        self._kf_pose = T.copy()          # cached estimate of the latest keyframe
        # Odometry samples (t_i, increment from the previous sample, covariance), kept for the
        # window so that poses at past times (late localisations) can be reached from a keyframe.
        self._odo_times: list[float] = []
        self._odo: list[tuple[np.ndarray, np.ndarray]] = []
        self._odo_start = float(t)        # time the first stored increment starts from
        # Running odometry from the latest keyframe to the latest sample.
        self._acc_T = np.eye(4)
        self._acc_cov = np.zeros((6, 6))

    # --------------------------------------------------------------------------- odometry
    def add_odometry(self, t: float, T_increment: np.ndarray, cov: np.ndarray) -> None:
        """One odometry increment ``T_{prev,t}`` (vehicle at the previous sample -> vehicle at ``t``).

        Parameters
        ----------
        t : time of the sample; strictly after the previous one and the latest keyframe.
        T_increment : (4,4) relative pose, e.g. ``SurveyRun.odometry_increments()[k-1]``.
        cov : (6,6) its covariance (positive definite).
        """
        self._require()
        t = float(t)
        if t <= self.latest_time:
            raise ValueError(f"odometry at t={t} is not after the latest time {self.latest_time}")
        inc = _check_pose(T_increment, "T_increment")
        cov = _check_spd(cov, "odometry cov")
        self._odo_times.append(t)
        self._odo.append((inc, cov))
        Ad = _adjoint(invert(inc))
        self._acc_cov = Ad @ self._acc_cov @ Ad.T + cov
        self._acc_T = self._acc_T @ inc
        if t - self._kf_times[-1] >= self.config["keyframe_interval_s"] - 1e-9:
            self._add_keyframe()

    def _add_keyframe(self) -> int:
        """Keyframe at the latest odometry time from the running odometry; returns its key."""
        key = self._insert_keyframe(self._odo_times[-1], self._acc_T, self._acc_cov)
        self._acc_T = np.eye(4)
        self._acc_cov = np.zeros((6, 6))
        return key

    def _update(self, graph, values, timestamps, extra_iterations: int = 0) -> None:
        t0 = time.perf_counter()
        self._smoother.update(graph, values, timestamps)
        for _ in range(extra_iterations):
            self._smoother.update()
        self.update_seconds += time.perf_counter() - t0
        self.n_updates += 1
        self._marginals = {}              # keyframe marginals change with every update
        self._kf_pose = self._smoother.calculateEstimatePose3(self._kf_keys[-1]).matrix()

    def _prune(self) -> None:
        """Forget keyframes the smoother marginalised, and odometry older than the oldest kept one."""
        alive = set(int(k) for k in self._smoother.timestamps().keys())
        while len(self._kf_keys) > 1 and self._kf_keys[0] not in alive:
            self._kf_keys.pop(0)
            self._kf_times.pop(0)
        t_old = self._kf_times[0]
        drop = bisect.bisect_right(self._odo_times, t_old)
        if drop:
            self._odo_start = self._odo_times[drop - 1]
            del self._odo_times[:drop]
            del self._odo[:drop]

    def _odometry(self, t_a: float, t_b: float, covariance: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Relative pose ``T_a_b`` and its covariance from stored odometry, ``t_a <= t_b``.

        A sample's increment is split linearly in its tangent space where a time falls inside it.
        With ``covariance=False`` the covariance is not propagated (None; the pose is the same).
        """
        if t_b < t_a:
            raise ValueError("t_b must not precede t_a")
        T = np.eye(4)
        C = np.zeros((6, 6))
        # Samples ending at or before t_a contribute nothing: start after them (the window holds
        # ~100 samples and this runs for every frame's estimate).
        j = bisect.bisect_right(self._odo_times, t_a)
        prev = self._odo_times[j - 1] if j > 0 else self._odo_start
        for ti, (inc, cov) in zip(self._odo_times[j:], self._odo[j:]):
            lo, hi = max(prev, t_a), min(ti, t_b)
            if hi > lo:
                frac = (hi - lo) / (ti - prev)
                if frac < 1.0 - 1e-12:
                    piece, pcov = pose_exp(frac * pose_log(inc)), frac * cov
                else:
                    piece, pcov = inc, cov
                if covariance:
                    Ad = _adjoint(invert(piece))
                    C = Ad @ C @ Ad.T + pcov
                T = T @ piece
            if ti >= t_b:
                break
            prev = ti
        return T, (C if covariance else None)

    # ----------------------------------------------------------------------- localisation
    def add_localisation(self, t: float, T_world_vehicle: np.ndarray, cov: np.ndarray | None = None,
                         information: np.ndarray | None = None) -> bool:
        """A localisation constraint on the vehicle pose at time ``t`` (robust Huber prior in the world).

        Give either ``cov`` (e.g. the solver's posterior covariance) or ``information`` (PSD, may
        be singular; e.g. ``LocalisationConstraint.information_detections`` with
        ``T_world_vehicle_detections``, which does not count the motion prior twice).

        Where ``t`` is at or after the latest keyframe the constraint gets its own keyframe (at ``t``,
        or at the latest odometry time if ``t`` is later -- feed odometry up to ``t`` first); an older
        ``t`` inside the window is carried to the nearest keyframe through the stored odometry.

        Returns
        -------
        bool
            False when ``t`` is older than the window (the constraint is dropped).
        """
        self._require()
        t = float(t)
        T = _check_pose(T_world_vehicle, "T_world_vehicle")
        if (cov is None) == (information is None):
            raise ValueError("give exactly one of cov or information")
        if cov is not None:
            info = np.linalg.inv(_check_spd(cov, "localisation cov"))
        else:
            info = np.asarray(information, dtype=float)
            if info.shape != (6, 6) or not np.all(np.isfinite(info)):
                raise ValueError(f"information must be a finite 6x6 matrix, got {info.shape}")
            info = 0.5 * (info + info.T)
            if np.linalg.eigvalsh(info).min() < -1e-9 * max(1.0, np.abs(info).max()):
                raise ValueError("information must be positive semi-definite")
        if t < self._kf_times[0]:
            return False
        if t >= self._kf_times[-1]:
            key = self._keyframe_at(t)
        else:
            # Nearest keyframe in time; carry the constraint there along the odometry:
            # T_world_k = T_world_t · T_t_k, so ξ_k = Ad(T_k_t) ξ_t + η with η the odometry noise
            # of T_t_k expressed in frame k (C_k).
            i = int(np.argmin(np.abs(np.asarray(self._kf_times) - t)))
            key, t_k = self._kf_keys[i], self._kf_times[i]
            if t_k <= t:
                T_k_t, C_t = self._odometry(t_k, t)
                Ad = _adjoint(T_k_t)
                C_k = Ad @ C_t @ Ad.T
                T_t_k = invert(T_k_t)
            else:
                T_t_k, C_k = self._odometry(t, t_k)
            Ad_tk = _adjoint(T_t_k)                 # = Ad(T_k_t)^{-1}
            info = Ad_tk.T @ info @ Ad_tk
            if np.any(C_k):
                # (Λ^{-1} + C)^{-1} without inverting a possibly singular Λ (Woodbury).
                info = info - info @ np.linalg.solve(info + np.linalg.inv(C_k + 1e-12 * np.eye(6)), info)
            info = 0.5 * (info + info.T)
            T = T @ T_t_k
        info = info + self.config["information_floor"] * np.eye(6)
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.config["huber_k"]),
                                               gtsam.noiseModel.Gaussian.Information(info))
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(key, gtsam.Pose3(T), noise))
        self._update(graph, gtsam.Values(), {}, extra_iterations=int(self.config["extra_iterations"]))
        return True

    def _keyframe_at(self, t: float) -> int:
        """Key of a keyframe at time ``t`` >= the latest keyframe, splitting the odometry if needed."""
        if t <= self._kf_times[-1] + 1e-9 or not self._odo_times or self._odo_times[-1] <= self._kf_times[-1]:
            return self._kf_keys[-1]         # no odometry since the last keyframe: same pose
        if t >= self._odo_times[-1]:
            return self._add_keyframe()
        # t falls inside the odometry since the last keyframe: split the sample that spans t so the
        # stored odometry has a boundary at t, make the keyframe there, keep the rest running.
        j = bisect.bisect_left(self._odo_times, t)
        if self._odo_times[j] != t:
            inc_j, cov_j = self._odo[j]
            t_prev = self._odo_times[j - 1] if j > 0 else self._odo_start
            frac = (t - t_prev) / (self._odo_times[j] - t_prev)
            first = pose_exp(frac * pose_log(inc_j))
            self._odo_times.insert(j, t)
            self._odo[j:j + 1] = [(first, frac * cov_j), (invert(first) @ inc_j, (1 - frac) * cov_j)]
        T_a, C_a = self._odometry(self._kf_times[-1], t)
        T_b, C_b = self._odometry(t, self._odo_times[-1])
        key = self._insert_keyframe(t, T_a, C_a)
        self._acc_T, self._acc_cov = T_b, C_b
        return key

    def _insert_keyframe(self, t: float, T_rel: np.ndarray, C_rel: np.ndarray) -> int:
        """New keyframe at ``t`` linked to the latest one by odometry ``T_rel`` (cov ``C_rel``)."""
        key = self._new_key()
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(self._kf_keys[-1], key, gtsam.Pose3(T_rel),
                                           gtsam.noiseModel.Gaussian.Covariance(_check_spd(C_rel, "odometry"))))
        values = gtsam.Values()
        values.insert(key, gtsam.Pose3(self._kf_pose @ T_rel))
        self._kf_times.append(t)
        self._kf_keys.append(key)
        self._update(graph, values, {key: t})
        self._prune()
        return key

    # --------------------------------------------------------------------------- outputs
    def estimate(self, t: float | None = None) -> np.ndarray:
        """``T_world_vehicle`` at time ``t`` (default: the latest odometry time).

        The nearest keyframe at or before ``t`` (smoothed) composed with the odometry since; times
        after the latest odometry are not extrapolated (the latest pose is returned).
        """
        self._require()
        if t is None or t >= self.latest_time:
            return self._kf_pose @ self._acc_T
        t = float(t)
        if t < self._kf_times[0]:
            raise ValueError(f"t={t} is before the window (oldest keyframe at {self._kf_times[0]})")
        i = bisect.bisect_right(self._kf_times, t) - 1
        T_k = self._smoother.calculateEstimatePose3(self._kf_keys[i]).matrix()
        return T_k @ self._odometry(self._kf_times[i], t, covariance=False)[0]

    def covariance(self) -> np.ndarray:
        """6x6 marginal covariance of the latest pose (vehicle frame, GTSAM convention).

        The latest keyframe's marginal propagated through the odometry since -- the natural motion
        prior ``P_x`` for the solver.
        """
        self._require()
        C = self._marginal(self._kf_keys[-1])
        Ad = _adjoint(invert(self._acc_T))
        return Ad @ C @ Ad.T + self._acc_cov

    def _marginal(self, key) -> np.ndarray:
        """A keyframe's marginal covariance, computed once per smoother update (the solver's prior and
        every frame's uncertainty ask for it between two updates)."""
        C = self._marginals.get(key)
        if C is None:
            C = self._marginals[key] = self._smoother.marginalCovariance(key)
        return C

    def estimate_with_covariance(self, t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`estimate` at time ``t`` and its 6x6 marginal covariance (vehicle frame, GTSAM order:
        rotation, then translation): the nearest keyframe at or before ``t`` -- its smoothed pose and its
        marginal in the window -- carried through the odometry since, in one pass."""
        self._require()
        if t is None or t >= self.latest_time:
            return self._kf_pose @ self._acc_T, self.covariance()
        t = float(t)
        if t < self._kf_times[0]:
            raise ValueError(f"t={t} is before the window (oldest keyframe at {self._kf_times[0]})")
        i = bisect.bisect_right(self._kf_times, t) - 1
        T, C_odo = self._odometry(self._kf_times[i], t)
        Ad = _adjoint(invert(T))
        T_k = self._smoother.calculateEstimatePose3(self._kf_keys[i]).matrix()
        return T_k @ T, Ad @ self._marginal(self._kf_keys[i]) @ Ad.T + C_odo

    def covariance_at(self, t: float | None = None) -> np.ndarray:
        """6x6 marginal covariance of the pose at time ``t`` (see :meth:`estimate_with_covariance`)."""
        return self.estimate_with_covariance(t)[1]

    def keyframes(self) -> tuple[np.ndarray, np.ndarray]:
        """Times (K,) and smoothed poses (K,4,4) of the keyframes in the window."""
        self._require()
        poses = np.stack([self._smoother.calculateEstimatePose3(k).matrix() for k in self._kf_keys])
        return np.asarray(self._kf_times), poses

    @property
    def ms_per_update(self) -> float:
        """Mean wall time of a smoother update (ms)."""
        return 1e3 * self.update_seconds / max(self.n_updates, 1)
