"""Hybrid weak localiser: scene signatures and point features in one robust solve (McManus et al. 2015, eq. 10).

``scenesig localise MAP RUN --method hybrid`` (SIFT), ``hybrid-orb``, ``hybrid-sift-all``,
``hybrid-orb-all``.  Per detector frame, for the place the localiser chose and in the windows its
motion prior predicts (:func:`scenesig.localiser.detector.search_windows`, for both types):

* **signature detections** -- the place's bank fired in the live image, exactly as
  :class:`scenesig.localiser.signature_method.SignatureLocaliser` does (detection covariance of eq. 5);
* **point matches** -- the live image's ORB / SIFT features matched to the map's point landmarks,
  exactly as :class:`scenesig.localiser.pointmethod.PointLocaliser` does (keypoint noise ``pixel_sigma`` times
  the keypoint's octave scale).  Which keyframes: ``hybrid`` and ``hybrid-orb`` use the reference
  run's keyframe per place (the paper's baseline map); ``hybrid-sift-all`` / ``hybrid-orb-all`` a
  keyframe per training run, the one with the most matches used.  The map needs nothing new.

Both kinds of measurement are landmark measurements ``z_i = h(T, p_i) + noise``, so eq. 10 takes
them together: one Levenberg-Marquardt with the motion prior, each measurement whitened by its own
covariance, the same Huber kernel on every Mahalanobis norm and the same χ²(2) gate each round
(:func:`solve_hybrid`).  How point outliers are kept from dragging a signature-supported pose:

1. **point consensus first** -- the point matches enter only when the robust absolute pose
   (:mod:`scenesig.localiser.absolute_pose`, LO-RANSAC) finds a consensus of at least ``point_min_inliers``
   (the point method's own acceptance count) whose pose is consistent with the motion prior
   (χ²(6) gate); the solve starts from that pose with the consensus inliers;
2. **per-type noise, calibrated** -- each type's covariance is multiplied by a factor (its
   ``*_sigma_scale`` squared) chosen on training runs (``scenesig bench hybrid_calibration``: the
   scale that makes each type's own fixes statistically consistent with the truth relative to the
   map), so neither type's weight rests on an optimistic noise model;
3. **signatures as the gate when points are strong** -- with at least ``point_dominant_inliers``
   consensus inliers (chosen on training runs: from that count on, point fixes were more accurate
   than signature fixes), the signatures' covariance is inflated by ``signature_gate_scale``² so the
   point-feature accuracy is kept while the signatures still take part in the gating: where the
   signatures support a pose of their own, the joint pose must be one their solver would accept too
   (at least ``min_inliers`` and ``min_inlier_fraction`` of the detections within the χ² gate, counted
   at the joint pose under the calibrated signature noise), or the points are dropped and the
   signature-only solution is used (``point_rejection`` in the measurement's extra).

With no point consensus the answer's pose is the signature method's, bit for bit; with too few
signature detections to solve, the point method's.  Every answer reaches the pose graph with its
calibrated covariance (a single-type answer's covariance times its type's scale squared), so the graph
weighs signature-only, point-only and joint fixes on one scale.  ``Measurement.extra`` carries ``signature_inliers`` and
``point_inliers`` (``frames.csv``'s columns of the same names) and ``hybrid_mode`` (``signatures``,
``points``, ``joint``).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.geometry import Camera, invert
from scenesig.surveys.settings import merge_settings

from .absolute_pose import default_config as absolute_pose_default, estimate as estimate_absolute_pose
from .detector import Observation
from .methods import Measurement, MotionPrior, WeakLocaliser, register_method
from .pointmethod import LiveFrame, PointLocaliser, PointObservation
from .signature_method import SignatureLocaliser
from .solver import SolveResult, _Problem, _solve, default_config as solver_default, pose_log, solve, solve_pnp_prior

__all__ = ["default_config", "resolve_config", "HybridObservation", "HybridLocaliser", "HybridResult", "fuse",
           "solve_hybrid", "HYBRID_METHODS", "signature_agreement"]

#: method name -> (point-feature kind, point map)
HYBRID_METHODS = {"hybrid": ("sift", "reference"), "hybrid-orb": ("orb", "reference"),
                  "hybrid-sift-all": ("sift", "all"), "hybrid-orb-all": ("orb", "all")}

default_config = {
    "signatures": {},            # overrides of the signature method ({"detector", "solver", "prior_gating"})
    "points": {},                # overrides of localiser.pointmethod.default_config
    # σ multipliers of each type's own noise model, and the consensus from which points lead: chosen by
    # ``scenesig bench hybrid_calibration`` on a development run of the demo world (run11_morning: neither
    # a training run of the map nor a reported run; docs/hybrid.md), SIFT points.
    "signature_sigma_scale": 2.14,
    "point_sigma_scale": 1.75,
    "point_min_inliers": 12,     # consensus needed before points enter (the point method's acceptance)
    "point_dominant_inliers": 12,  # from this consensus on the signatures act as the gate (see above)
    "signature_gate_scale": 10.0,  # σ inflation of the signatures then: 1 % of their information
    "signature_min_detections": 4,   # fewer: no signature part (the point method answers alone)
    # the point consensus's RANSAC pose must pass the prior's χ²(6) gate before the points enter (False:
    # only the joint solve's own prior check after refinement, as the point method does)
    "consensus_prior_gate": True,
    "solver": {},                # overrides of localiser.solver.default_config for the joint solve
    # both parts' prior gating (what the paper preset and --no-prior-gating set for every method), unless
    # a part's own settings ("signatures" / "points") name theirs
    "prior_gating": True,
}


def _merge(config: dict | None) -> dict:
    return merge_settings(default_config, config, "hybrid method", open=("signatures", "points", "solver"))


def _parts(cfg: dict, point_map: str) -> tuple[dict, dict]:
    """The signature part's and the point part's overrides (``prior_gating`` under each part's own)."""
    gate = {"prior_gating": bool(cfg["prior_gating"])}
    return {**gate, **cfg["signatures"]}, {**gate, **cfg["points"], "point_map": point_map}


@dataclass
class HybridObservation:
    """One frame's signature detections and point matches (same place, same prior)."""

    signatures: Observation
    points: PointObservation
    ms: float = 0.0


@dataclass
class _HybridFrame:
    """:meth:`HybridLocaliser.prepare`'s result: each part's image-only preparation."""

    signatures: object
    points: LiveFrame


def signature_agreement(T_place_vehicle: np.ndarray, obs: Observation, camera: Camera, T_vehicle_camera,
                        sigma_scale: float = 1.0, gate_chi2: float = 9.21, min_depth_m: float = 0.05) -> np.ndarray:
    """(n,) bool: signature detections within the χ²(2) gate at a pose, under ``sigma_scale``² × their
    measurement covariance (eq. 5 plus the landmark's map covariance carried into the image)."""
    if not len(obs):
        return np.zeros(0, bool)
    cfg = {**solver_default, "min_depth_m": min_depth_m}
    k = sigma_scale ** 2
    prob = _Problem(obs.uv, obs.R * k, obs.landmarks, None if obs.landmark_cov is None else obs.landmark_cov * k,
                    camera, T_vehicle_camera, None, None, cfg)
    idx = np.arange(len(obs))
    _, c, front, _, _ = prob.residuals(T_place_vehicle, idx, prob.whitening(T_place_vehicle, idx))
    return front & (c * c <= gate_chi2)


def solve_hybrid(sig: Observation, pts: PointObservation, T_pnp: np.ndarray, point_inliers: np.ndarray,
                 T_prior: np.ndarray, P_prior: np.ndarray, camera: Camera, T_vehicle_camera,
                 signature_scale: float = 1.0, point_scale: float = 1.0, signature_active: np.ndarray | None = None,
                 config: dict | None = None) -> SolveResult:
    """Eq. 10 over signature detections and point matches together (module docstring).

    Parameters
    ----------
    sig, pts : the frame's signature detections and point matches (place frame).
    T_pnp : (4,4) ``T_place_vehicle`` of the point consensus: the solve starts there.
    point_inliers : (m,) bool, the consensus inliers (the starting point set).
    T_prior, P_prior : the motion prior (``T_place_vehicle``) and its covariance.
    signature_scale, point_scale : σ multipliers of each type's covariance.
    signature_active : (n,) bool starting signature set (default: all).
    config : overrides of :data:`scenesig.localiser.solver.default_config`.

    Returns
    -------
    SolveResult over the ``n + m`` measurements, signatures first; ``extra`` has ``n_signatures``.
    """
    t0 = time.perf_counter()
    cfg = merge_settings(solver_default, config, "solver")
    n, m = len(sig), len(pts)
    uv = np.concatenate([sig.uv.reshape(-1, 2), pts.uv.reshape(-1, 2)])
    R = np.concatenate([sig.R.reshape(-1, 2, 2) * signature_scale ** 2, pts.R.reshape(-1, 2, 2) * point_scale ** 2])
    L = np.concatenate([sig.landmarks.reshape(-1, 3), pts.xyz.reshape(-1, 3)])
    pcov = pts.cov if pts.cov is not None else np.zeros((m, 3, 3))
    scov = sig.landmark_cov if sig.landmark_cov is not None else np.zeros((n, 3, 3))
    # a type's scale multiplies its whole measurement covariance Σ_i = R_i + G_i P_l,i G_iᵀ
    Lcov = np.concatenate([scov.reshape(-1, 3, 3) * signature_scale ** 2, pcov.reshape(-1, 3, 3) * point_scale ** 2])
    prob = _Problem(uv, R, L, Lcov, camera, T_vehicle_camera, T_prior, P_prior, cfg)
    active = np.zeros(n + m, bool)
    active[:n] = True if signature_active is None else np.asarray(signature_active, bool)
    active[n:] = np.asarray(point_inliers, bool)
    res = _solve(prob, np.asarray(T_pnp, float), np.flatnonzero(active), t0, {"n_signatures": n})
    return res


def _prior_chi2(T: np.ndarray, T_prior: np.ndarray, P_prior: np.ndarray) -> float:
    q = pose_log(invert(T_prior) @ T)
    return float(q @ np.linalg.solve(P_prior, q))


@dataclass
class HybridResult:
    """What :func:`fuse` decided for one frame.

    Attributes
    ----------
    result : the solve whose pose is the answer (signature-only, point-only or joint), or None when
        no solve ran (too few measurements).
    reason : why there is no accepted pose (None: accepted).
    mode : ``"signatures"``, ``"points"`` or ``"joint"``.
    signature_inliers, point_inliers : inliers of each type at the answer (signatures counted under
        their calibrated noise, see :func:`signature_agreement`).
    rejection : why the points were left out (``"no_consensus"``, ``"disagrees_with_signatures"``,
        ``"joint_<reason>"``), or None.
    dominant : the point consensus was strong enough for the signatures to act as the gate.
    """

    result: SolveResult | None
    reason: str | None
    mode: str
    signature_inliers: int = 0
    point_inliers: int = 0
    rejection: str | None = None
    dominant: bool = False


def _calibrated(res: SolveResult | None, sigma_scale: float) -> SolveResult | None:
    """A single-type answer with its noise model calibrated like the joint solve's: the pose unchanged (the
    signature or point method's, bit for bit), its covariance × ``sigma_scale``² and its information ÷ it,
    so every fix the pose graph gets from the hybrid is weighted on the same calibrated scale."""
    if res is None or res.covariance is None or sigma_scale == 1.0:
        return res
    k = float(sigma_scale) ** 2
    return dataclasses.replace(res, covariance=res.covariance * k, information_detections=res.information_detections / k)


def _point_consensus(pts: PointObservation, T_prior, P_prior, camera, T_vehicle_camera, need: int,
                     min_matches: int, pnp: dict, prior_gate_chi2: float | None):
    """``(T_place_vehicle, inliers)`` of the point matches' robust absolute pose, or None (too few
    matches or consensus inliers, or a pose inconsistent with the motion prior)."""
    if len(pts) < max(min_matches, need, 4):
        return None
    ap = estimate_absolute_pose(pts.uv, pts.xyz, camera, pnp)
    if not ap.ok or ap.n_inliers < need:
        return None
    T = invert(np.asarray(T_vehicle_camera, float) @ ap.T_cam_place)
    if prior_gate_chi2 is not None and _prior_chi2(T, T_prior, P_prior) > prior_gate_chi2:
        return None
    return T, ap.inliers


def fuse(sig: Observation, pts: PointObservation, T_prior: np.ndarray, P_prior: np.ndarray, camera: Camera,
         T_vehicle_camera, config: dict | None = None, signature_solver: dict | None = None,
         point_method: dict | None = None) -> HybridResult:
    """One frame's hybrid answer (module docstring): signature-only, point-only or the joint eq. 10 solve.

    Parameters
    ----------
    sig, pts : signature detections and point matches of one place (its frame).
    T_prior, P_prior : motion prior ``T_place_vehicle`` and its covariance.
    config : overrides of :data:`default_config` (its ``signatures`` / ``points`` sub-dicts unused here).
    signature_solver : the signature method's solver settings (overrides of
        :data:`scenesig.localiser.solver.default_config`).
    point_method : the point method's settings (overrides of :data:`scenesig.localiser.pointmethod.default_config`).
    """
    from .pointmethod import _merge as point_merge

    cfg = _merge(config)
    s_cfg = merge_settings(solver_default, signature_solver, "solver")
    p_cfg = point_merge(point_method)
    j_cfg = merge_settings(solver_default, {"min_inlier_fraction": 0.0, **cfg["solver"]}, "solver")
    pnp = {k: v for k, v in {**absolute_pose_default, **p_cfg["pnp"]}.items() if k in absolute_pose_default}
    n, m = len(sig), len(pts)
    s_sig, s_pt = float(cfg["signature_sigma_scale"]), float(cfg["point_sigma_scale"])

    def signatures_alone(rejection):
        if n < s_cfg["min_inliers"]:
            return HybridResult(None, "too_few_detections", "signatures", 0, 0, rejection)
        r = solve(sig.uv, sig.R, sig.landmarks, T_prior, P_prior, camera, T_vehicle_camera,
                  landmark_cov=sig.landmark_cov, config=s_cfg)
        return HybridResult(_calibrated(r, s_sig), r.reason, "signatures", r.n_inliers, 0, rejection)

    if n < int(cfg["signature_min_detections"]):
        # no signature part: the point method's answer
        if m < max(int(p_cfg["min_matches"]), 4):
            return HybridResult(None, "too_few_matches", "points")
        r = solve_pnp_prior(pts.uv, pts.xyz, camera, T_vehicle_camera, T_prior, P_prior, R=pts.R, points_cov=pts.cov,
                            config=p_cfg["solver"] or None, pnp_config=p_cfg["pnp"] or None)
        return HybridResult(_calibrated(r, s_pt), r.reason, "points", 0, r.n_inliers)
    cons = _point_consensus(pts, T_prior, P_prior, camera, T_vehicle_camera, int(cfg["point_min_inliers"]),
                            int(p_cfg["min_matches"]), pnp,
                            j_cfg["prior_gate_chi2"] if cfg["consensus_prior_gate"] else None)
    if cons is None:
        return signatures_alone("no_consensus")
    T_pnp, p_in = cons
    dominant = int(p_in.sum()) >= int(cfg["point_dominant_inliers"])
    s_joint = s_sig * (float(cfg["signature_gate_scale"]) if dominant else 1.0)
    # the signature-only solution: the pose the points must not drag away
    alone = signatures_alone(None)
    start = None
    if alone.result is not None and alone.result.ok:
        start = signature_agreement(alone.result.T_place_vehicle, sig, camera, T_vehicle_camera, s_sig,
                                    j_cfg["gate_chi2"], j_cfg["min_depth_m"])
    res = solve_hybrid(sig, pts, T_pnp, p_in, T_prior, P_prior, camera, T_vehicle_camera, s_joint, s_pt,
                       signature_active=start if start is not None and start.sum() >= 4 else None, config=j_cfg)
    agree = signature_agreement(res.T_place_vehicle, sig, camera, T_vehicle_camera, s_sig, j_cfg["gate_chi2"],
                                j_cfg["min_depth_m"])
    k_sig, k_pt = int(agree.sum()), int(res.inliers[n:].sum())
    reason = res.reason
    if reason is None:
        sig_ok = k_sig >= s_cfg["min_inliers"] and k_sig >= s_cfg["min_inlier_fraction"] * n
        if not (k_pt >= int(cfg["point_min_inliers"]) or sig_ok):
            reason = "too_few_inliers"
    # the gate: where the signatures support a pose of their own, the joint pose must be one they would
    # accept too -- their own acceptance rule (at least min_inliers, and min_inlier_fraction of the
    # detections) counted at the joint pose under their calibrated noise
    if start is not None and k_sig < max(s_cfg["min_inliers"], s_cfg["min_inlier_fraction"] * n):
        alone.rejection = "disagrees_with_signatures"
        return alone
    if reason is not None:
        alone.rejection = f"joint_{reason}"
        return alone
    return HybridResult(res, None, "joint", k_sig, k_pt, None, dominant)


class HybridLocaliser(WeakLocaliser):
    """Scene signatures and point features in one eq. 10 solve (a :class:`scenesig.localiser.methods.WeakLocaliser`).

    Parameters
    ----------
    store : the map (banks and point features).
    camera, T_vehicle_camera : the live camera.
    config : overrides of :data:`default_config`.
    kind : ``"sift"`` or ``"orb"``; ``point_map`` ``"reference"`` or ``"all"``.
    """

    def __init__(self, store: MapStore, camera: Camera, T_vehicle_camera: np.ndarray, config: dict | None = None,
                 kind: str = "sift", point_map: str = "reference"):
        cfg = _merge(config)
        self.config = cfg
        self.store = store
        self.camera = camera
        self.T_vehicle_camera = np.asarray(T_vehicle_camera, dtype=float)
        sig_cfg, pt_cfg = _parts(cfg, point_map)
        self.signatures = SignatureLocaliser(store, camera, T_vehicle_camera, sig_cfg or None)
        self.points = PointLocaliser(store, camera, T_vehicle_camera, pt_cfg,
                                     kind=kind)
        self.kind, self.point_map = kind, point_map
        self.name = next(k for k, v in HYBRID_METHODS.items() if v == (kind, point_map))
        self.color = self.signatures.color          # point extraction converts to gray itself
        self.solver_config = merge_settings(solver_default, {"min_inlier_fraction": 0.0, **cfg["solver"]},
                                            "solver")

    def method_config(self) -> dict:
        c = self.config
        return {"method": self.name, "family": "hybrid: scene signatures + point features in one eq. 10 solve",
                "point_map": self.point_map,
                "keyframes": ("the reference run's keyframe per place" if self.point_map == "reference" else
                              "a keyframe per training run; the one with the most matches"),
                **{k: c[k] for k in ("signature_sigma_scale", "point_sigma_scale", "point_min_inliers",
                                     "point_dominant_inliers", "signature_gate_scale", "signature_min_detections",
                                     "consensus_prior_gate")},
                "joint_solver": dict(self.solver_config),
                "signatures": self.signatures.method_config(), "points": self.points.method_config()}

    def prefetch(self, place):
        self.signatures.prefetch(place)
        self.points.prefetch(place)

    def prepare(self, image):
        """Both parts' image-only work: the HOG resizes and the point features (the point features
        come from the active :func:`scenesig.signatures.pointfeatures.feature_cache` when a point method of
        the same kind replaying this run extracted them already)."""
        if isinstance(image, _HybridFrame):
            return image
        return _HybridFrame(self.signatures.prepare(image), self.points.prepare(image))

    def detect(self, image, place: int, prior: MotionPrior) -> HybridObservation:
        t0 = time.perf_counter()
        frame = self.prepare(image)
        ms_ahead = frame.points.ms if frame is image else 0.0    # extracted ahead: count it (as PointLocaliser)
        sig = self.signatures.detect(frame.signatures, place, prior)
        pts = self.points.detect(frame.points, place, prior)
        return HybridObservation(sig, pts, ms_ahead + (time.perf_counter() - t0) * 1e3)

    # ------------------------------------------------------------------------------------ solver
    def solve(self, obs: HybridObservation, place: int, prior: MotionPrior) -> Measurement:
        t0 = time.perf_counter()
        sig, pts = obs.signatures, obs.points
        h = fuse(sig, pts, prior.T_place_vehicle, prior.covariance, self.camera, self.T_vehicle_camera,
                 self.config, self.signatures.solver_config, self.points.config)
        c = h.result.constraint(self.store.places[place].T_world_place) if h.result is not None else None
        extra = {"hybrid_mode": h.mode, "signature_inliers": h.signature_inliers, "point_inliers": h.point_inliers,
                 "signature_detections": len(sig), "point_matches": len(pts), "dominant_points": h.dominant}
        if h.rejection is not None:
            extra["point_rejection"] = h.rejection
        return Measurement(c, len(sig) + len(pts), h.signature_inliers + h.point_inliers, h.reason, obs.ms,
                           1e3 * (time.perf_counter() - t0), h.result is not None, extra)

    def close(self):
        self.signatures.close()
        self.points.close()


def _factory(kind, point_map):
    def make(store, camera, T_vehicle_camera, config=None):
        return HybridLocaliser(store, camera, T_vehicle_camera, config, kind=kind, point_map=point_map)
    make.__name__ = "make_" + next(k for k, v in HYBRID_METHODS.items() if v == (kind, point_map)).replace("-", "_")
    return make


def resolve_config(config: dict | None = None, kind: str = "sift", point_map: str = "reference") -> dict:
    """Every setting of a hybrid method: ``config`` (overrides of :data:`default_config`) with its
    signature part's, point part's (``kind`` on the ``point_map``) and joint solver's resolved as
    :class:`HybridLocaliser` uses them."""
    from .pointmethod import resolve_config as point_config
    from .signature_method import resolve_config as signature_config

    cfg = _merge(config)
    sig_cfg, pt_cfg = _parts(cfg, point_map)
    return {**cfg, "signatures": signature_config(sig_cfg or None), "points": point_config(pt_cfg),
            "solver": merge_settings(solver_default, {"min_inlier_fraction": 0.0, **cfg["solver"]}, "solver")}


def _settings(kind, point_map):
    def settings(config=None):
        return resolve_config(config, kind, point_map)
    return settings


for _name, (_kind, _pm) in HYBRID_METHODS.items():
    register_method(_name, _factory(_kind, _pm), _settings(_kind, _pm))
