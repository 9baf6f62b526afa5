"""Integrity monitoring: does the map explain the run?  (fault detection, as GNSS RAIM does it)

The localiser of McManus et al. (2015, §3.3) trusts that it was given the right map and a right
calibration: its solver gates outliers *within* a frame (χ² on each detection, χ² of the pose against
the motion prior), but a map of another place, a wrong focal length or a scene changed beyond
recognition still yields poses that pass those gates -- the detector only searches windows around the
landmarks' predicted projections, so whatever fires there agrees with the prediction well enough.
This module watches what the solver and the pose graph report over successive detector frames, from
images, odometry and the map alone, and decides whether the localisations can be trusted.

**Test statistics** (per detector frame that the solver accepted; :class:`FrameStats`):

* ``residual`` -- the solver's own residual test: the sum of its inliers' squared Mahalanobis
  residuals (against the detection covariance of eq. 5 plus the landmark's) over their degrees of
  freedom, ``Σ c_i² / (2 n - 6)``.  Detections of the map's own signatures land within their stated
  covariance; chance firings in a search window of another place spread over the window and, after
  the χ²(2) gate, sit near its edge.
* ``nis`` -- the normalised innovation squared of the pose the detections alone point to against the
  pose graph's prediction from the odometry (``ν = Log(T̂⁻¹ T_det)``, ``S = P + Λ_det⁺``), the odometry
  consistency of successive fixes: a right map's fixes agree with the odometry carrying the last ones
  forward, a wrong map's jump.
* ``support`` -- inliers over classifiers searched: the share of the place's signatures the frame
  confirms.

Each is tested over a sliding window of ``window`` detector frames (sums, as RAIM sums residuals over
satellites), so a single unlucky frame neither raises nor clears an alert.

**Decisions.**  A fix found by global localisation or relocalisation (:mod:`scenesig.localiser.relocalise`) is
*tentative* until ``probation_frames`` solved frames at ``probation_places`` places or more have passed
the residual and innovation tests, their support over the whole probation is at least
``probation_min_support`` and at most ``probation_misses`` frames failed to solve in between (a look-alike
place on another map fires its own bank, but the next place's signatures hardly fire); only then is it
accepted and the frames from then on are localised.  A global search that goes ``max_search_m`` without
a confirmed fix raises an alert too (once per search).  A probation that fails raises an **alert**: the fix is discarded, the
frames that tracked it lose their poses, and the localiser is lost again.  While tracking, a window whose
statistics fail raises an alert as well: no fix is accepted; without INS/GPS the localiser is lost
(and must pass probation again), with INS/GPS it dead-reckons on its oracle until ``probation_frames``
frames pass again.  The first alert is said once on stderr (what was seen, where); ``integrity_alerts``
in ``metrics.json`` counts them, ``frames.csv``'s ``integrity_alert`` marks the refused frames.

Thresholds and the data that chose them: ``docs/integrity.md``, "Integrity monitoring".
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np

from scenesig.surveys.geometry import invert
from scenesig.surveys.settings import merge_settings

from .solver import pose_log

__all__ = ["default_config", "FrameStats", "Alert", "IntegrityMonitor", "frame_stats"]

log = logging.getLogger(__name__)

default_config = {
    "enabled": True,
    "methods": ["signatures"],     # the methods whose statistics the thresholds were chosen for
    # Every threshold was chosen on development runs that are not reported (docs/integrity.md,
    # "Integrity monitoring"): the right map's largest / smallest value there, and another world's.
    "window": 4,                   # detector frames in the tracking window
    "max_residual": 2.5,           # windowed Σ c² / Σ dof of the solver's inliers (right map: at most 2.01)
    "max_nis": 40.0,               # windowed mean NIS, detections-only pose vs the odometry (right map: <= 17.9)
    "min_support": 0.15,           # windowed Σ inliers / Σ classifiers searched (right map: >= 0.28)
    "probation_frames": 6,         # solved frames a global fix needs before it is accepted ...
    "probation_places": 2,         # ... at this many places (a look-alike rarely continues at the next place)
    "probation_min_support": 0.22,  # Σ inliers / Σ searched over the probation (right map >= 0.31, other
                                   # world <= 0.16)
    "probation_misses": 2,         # frames without a solution tolerated during probation (right map: 0)
    "max_search_m": 100.0,         # searched this far (odometry) without a confirmed fix: the map does not
                                   # explain what the camera sees (an alert, once per search; right map: <= 10 m)
}


@dataclass
class FrameStats:
    """What one detector frame told the monitor (NaN where the solver gave no pose)."""

    t: float
    place: int
    detections: int
    inliers: int
    searched: int
    solved: bool           # the solver returned a constraint
    residual_chi2: float   # Σ c² of the inliers
    residual_dof: float    # 2 n_inliers - 6
    nis: float             # innovation of the detections-only pose against the prediction
    innovation_m: float    # its planar size (m)


@dataclass
class Alert:
    """One integrity alert: when, where, and what the window held."""

    t: float
    place: int
    reason: str
    frames: int            # detector frames whose fixes it refused (a failed probation's, or the window)

    def as_dict(self) -> dict:
        return asdict(self)


def frame_stats(t: float, place: int, prior, m) -> FrameStats:
    """:class:`FrameStats` of a measurement ``m`` (:class:`scenesig.localiser.methods.Measurement`) made with the
    motion prior ``prior`` (:class:`scenesig.localiser.methods.MotionPrior`)."""
    c = m.constraint
    ex = m.extra or {}
    searched = int(ex.get("searched", 0) or 0)
    r2 = float(ex.get("residual_chi2", np.nan))
    dof = float(max(2 * int(m.inliers) - 6, 1))
    nis = inn = np.nan
    if c is not None:
        nu = pose_log(invert(np.asarray(prior.T_world_vehicle, float)) @ np.asarray(c.T_world_vehicle_detections, float))
        L = 0.5 * (c.information_detections + c.information_detections.T)
        w, V = np.linalg.eigh(L)
        keep = w > 1e-9 * max(float(w.max()), 1e-300)
        C_det = (V[:, keep] / w[keep]) @ V[:, keep].T
        S = np.asarray(prior.covariance, float) + C_det
        try:
            nis = float(nu @ np.linalg.solve(S, nu))
        except np.linalg.LinAlgError:
            nis = np.inf
        inn = float(np.linalg.norm(nu[3:5]))
    return FrameStats(float(t), int(place), int(m.detections), int(m.inliers), searched, c is not None, r2, dof,
                      nis, inn)


class IntegrityMonitor:
    """Watches the solved detector frames and says whether fixes may be accepted (module docstring).

    Parameters
    ----------
    config : overrides of :data:`default_config`.
    method : the weak localiser's name; a method not in ``methods`` is not monitored.
    t0 : the run's start time (messages say how far into the run an alert came).

    Attributes
    ----------
    state : ``"trusted"``, ``"probation"`` (a global fix awaiting confirmation) or ``"alerted"``.
    alerts : every :class:`Alert`.
    history : every frame's :class:`FrameStats` (for the thresholds' calibration, ``docs/integrity.md``).
    """

    def __init__(self, config: dict | None = None, method: str = "signatures", t0: float = 0.0):
        self.config = merge_settings(default_config, config, "integrity")
        self.t0 = float(t0)
        self.active = bool(self.config["enabled"]) and method in self.config["methods"]
        self.state = "trusted"
        self.alerts: list[Alert] = []
        self.history: list[FrameStats] = []
        self._window: deque = deque(maxlen=max(1, int(self.config["window"])))
        self._probation: list[FrameStats] = []
        self._probation_misses = 0
        self._said = False
        self._search_from: float | None = None     # odometry distance where the current search began
        self._search_frames = 0
        self._search_verified = 0
        self._search_alerted = False

    # ------------------------------------------------------------------------------ tests
    def failing(self, frames, min_support: float | None = None) -> list[str]:
        """The tests a set of detector frames fails (empty: all pass), each saying what it saw: the
        residual and innovation tests over the solved frames, the support over all of them."""
        cfg = self.config
        frames = list(frames)
        solved = [f for f in frames if f.solved]
        why = []
        r2 = np.array([f.residual_chi2 for f in solved])
        dof = np.array([f.residual_dof for f in solved])
        ok = np.isfinite(r2)
        if ok.any():
            res = float(r2[ok].sum() / dof[ok].sum())
            if res > cfg["max_residual"]:
                why.append(f"detection residuals {res:.2f} per degree of freedom (at most {cfg['max_residual']:g} "
                           f"when the map explains the images)")
        nis = np.array([f.nis for f in solved])
        if (~np.isnan(nis)).any():
            mean = float(np.mean(nis[~np.isnan(nis)]))
            if mean > cfg["max_nis"]:
                why.append(f"fixes disagree with the odometry: innovation χ² {mean:.1f} on 6 dof (at most "
                           f"{cfg['max_nis']:g}), {np.nanmedian([f.innovation_m for f in solved]):.2f} m")
        searched = sum(f.searched for f in frames)
        need = cfg["min_support"] if min_support is None else min_support
        if searched:
            support = sum(f.inliers for f in frames) / searched
            if support < need:
                why.append(f"{support:.0%} of the signatures searched confirmed over {len(frames)} frames "
                           f"(at least {need:.0%})")
        return why

    # -------------------------------------------------------------------------- decisions
    def searching(self, t: float, place: int, distance_m: float, verified: int) -> bool:
        """A frame of global search (not localised, no INS/GPS) at odometry distance ``distance_m``, with
        ``verified`` places verified; True when this raises the alert that the search has gone on for
        ``max_search_m`` without a fix being confirmed."""
        if not self.active:
            return False
        if self._search_from is None:
            self._search_from = float(distance_m)
            self._search_frames = self._search_verified = 0
            self._search_alerted = False
        self._search_frames += 1
        self._search_verified += int(verified)
        far = float(distance_m) - self._search_from
        if self._search_alerted or far <= self.config["max_search_m"]:
            return False
        self._search_alerted = True
        self._alert(FrameStats(float(t), int(place), 0, 0, 0, False, np.nan, 1.0, np.nan, np.nan),
                    [f"searched {far:.0f} m ({self._search_frames} frames) without a place its images and the "
                     f"odometry agree on ({self._search_verified} single-frame verifications, none confirmed)"], 0)
        return True

    def begin_probation(self, t: float) -> None:
        """A global fix was found at t: it stays tentative until confirmed (:meth:`assess`)."""
        if not self.active:
            return
        self.state = "probation"
        self._probation = []
        self._probation_misses = 0
        self._window.clear()

    def assess(self, stats: FrameStats) -> str:
        """Decide on one tracked detector frame: ``"accept"`` (its fix may be used), ``"tentative"``
        (probation: use it for tracking, do not call it localised), ``"refuse"`` (alerted: do not use it)
        or ``"alert"`` (an alert is raised now: drop what the suspect fixes built)."""
        if not self.active:
            return "accept"
        self.history.append(stats)
        if len(self.history) > 100000:     # a bounded record (calibration reads it; a long run must not grow it)
            del self.history[:50000]
        cfg = self.config
        if self.state == "probation":
            self._probation.append(stats)
            solved = [f for f in self._probation if f.solved]
            misses = len(self._probation) - len(solved)
            if misses > cfg["probation_misses"]:
                return self._alert(stats, [f"{misses} of {len(self._probation)} tracked frames found no pose"],
                                   len(self._probation))
            why = self.failing(solved[-int(cfg["window"]):])        # residuals, innovations: as tracking
            done = (len(solved) >= cfg["probation_frames"]
                    and len({f.place for f in solved}) >= cfg["probation_places"])
            support = self._support(self._probation)
            if done and support < cfg["probation_min_support"]:     # over the whole probation
                why.append(f"{support:.0%} of the signatures searched confirmed over the {len(self._probation)} "
                           f"frames since the global fix (at least {cfg['probation_min_support']:.0%})")
            if why:
                return self._alert(stats, why, len(self._probation))
            if done:
                self.state = "trusted"
                self._search_from = None          # found: the next search starts afresh
                self._window.extend(self._probation[-int(cfg["window"]):])
                return "accept"
            return "tentative"
        self._window.append(stats)
        why = self.failing(self._window) if len(self._window) >= cfg["window"] else []
        if self.state == "alerted":
            if not stats.solved or why or len(self._window) < cfg["window"]:
                return "refuse"
            self.state = "trusted"
            return "accept"
        if why:
            return self._alert(stats, why, len(self._window))
        return "accept"

    @staticmethod
    def _support(frames) -> float:
        searched = sum(f.searched for f in frames)
        return sum(f.inliers for f in frames) / searched if searched else 1.0

    def _alert(self, stats: FrameStats, why: list[str], frames: int) -> str:
        self.state = "alerted"
        self._window.clear()
        self._probation = []
        a = Alert(stats.t, stats.place, "; ".join(why), int(frames))
        self.alerts.append(a)
        if not self._said:
            self._said = True
            log.warning("integrity alert %.1f s into the run, near the map's place %d: the map does not explain "
                        "the run (%s); no fix is accepted while it does not", a.t - self.t0, a.place, a.reason)
        return "alert"

    def summary(self) -> dict:
        return {"integrity_alerts": len(self.alerts), "integrity_alert_list": [a.as_dict() for a in self.alerts[:20]]}
