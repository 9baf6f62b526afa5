"""Multi-run georeferencing of the map's places.

A place's frame is the reference run's vehicle frame at the place's reference image; the landmarks live
in it, so it is exact *relative* to the scene.  Where that frame sits in the world (``T_world_place``)
is only known through an INS: the paper takes it from the reference run's INS alone, which carries the
INS's per-run offset (metres for a GPS-aided INS, different every day) into every place and hence into
every localisation the map gives.

Every training run drove past the place with its own INS, whose error is independent of the reference
run's.  Each run ``k`` is therefore one more estimate of the place's world pose, once its *true*
displacement from the place frame is removed -- and that displacement is measured visually:

1. the place's kept signature bank is fired on run ``k``'s training image (its frame nearest the
   place) and the camera pose relative to the place frame is solved from the 2D detections and the
   3D landmarks (:func:`solve_relative_pose`: OpenCV PnP + RANSAC, then Gauss-Newton with a Huber cost
   on each detection's Mahalanobis norm, ``Σ_i = R_i + G_i P_l,i G_iᵀ`` with eq. 5's ``R_i`` and the
   landmark's map covariance, gating outliers by χ²(2));
2. ``T_world_place^(k) = T_world_vehicle^INS_k(t) · T_place_vehicle_k⁻¹`` (the reference run's own
   view needs no PnP: ``T_place_vehicle = I`` by definition of the place frame);
3. the estimates of runs with a good PnP are combined robustly (:func:`combine_estimates`): a Huber
   mean of the positions and of the yaw, roll and pitch kept from the reference run's INS (an INS's
   attitude error is hundredths of a degree, its heading error tenths);
4. the resulting correction of the reference INS pose is smoothed along the route
   (:func:`smooth_corrections`): INS errors wander slowly (random walk over hundreds of metres), so
   neighbouring places' corrections are strongly correlated, while PnP noise is not.

With ``N`` runs of independent INS offsets of ``σ`` per axis the map's georeferencing error falls to
about ``σ/√N`` -- it cannot fall further without an external reference (surveyed control points):
every run's GPS carries the same slow error as its INS.

INS poses are interpolated (linear / SLERP) at the image timestamps; the run's clocks are assumed
synchronised (a camera-INS latency ``dt`` would add ``v·dt`` along the track per run).

``build_place`` (:mod:`scenesig.mapping.build`) calls :func:`observe_place` and stores the per-run observations
in the place file's meta (``"georef"``), so a resumed build recombines them without recomputing;
``build_map`` calls :func:`georeference_places` before writing the manifest.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scenesig.mapping.geometry import detection_covariance_factor, ideal_camera, ideal_pixels, reference_area
from scenesig.mapping.refine import _huber_weight, default_config as refine_defaults
from scenesig.surveys.geometry import (
    Camera,
    exp_so3,
    interpolate_poses,
    invert,
    make_pose,
    point_pose_jacobian,
    rot_z,
    yaw_of,
)
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "resolve_config", "RelativePose", "solve_relative_pose", "observe_place", "combine_estimates",
           "smooth_corrections", "georeference_places", "METHODS"]

METHODS = ("runs", "reference")

default_config = {
    "method": "runs",            # "runs": combine every training run's INS (this module); "reference":
                                 # the reference run's INS alone (the paper)
    # -- relative pose of a training image to the place (robust PnP) --
    "min_probability": 0.5,      # λ below this: the classifier did not really fire (as the localiser)
    "ransac_reprojection_px": 8.0,
    "ransac_iterations": 300,
    "ransac_confidence": 0.999,
    "seed": 0,                   # OpenCV's RNG is global: seeded per call so builds repeat
    "huber_k": 1.5,              # Huber threshold in σ of a detection's Mahalanobis norm
    "gate_chi2": 9.21,           # χ²(2) 99 %: outlier after a round
    "max_rounds": 5,
    "max_iterations": 30,
    "min_depth_m": 0.5,          # landmarks closer than this in front of the camera are not used
    # -- is a run's estimate usable --
    "min_inliers": 8,
    "min_inlier_fraction": 0.4,
    "max_position_sigma_m": 0.5,  # PnP position uncertainty (largest σ) above this: weakly constrained
    "max_offset_m": 12.0,        # PnP and the two INS disagree by more than this: a wrong PnP solution
    "max_heading_offset_deg": 5.0,
    # -- combination over runs and along the route --
    "huber_m": 4.0,              # Huber threshold of the mean over runs (m); INS offsets are ~2 m per
                                 # axis, so only a gross disagreement is down-weighted
    "huber_deg": 1.0,            # the same for the yaw
    "smooth_m": 20.0,            # Gaussian σ (m along the route) of the smoothing of the corrections; 0: off
}


def resolve_config(config: dict | None = None) -> dict:
    """Every georeferencing setting: ``config`` (overrides of :data:`default_config`) resolved and checked."""
    cfg = merge_settings(default_config, config, "georeference")
    if cfg["method"] not in METHODS:
        raise ValueError(f"georeference method must be one of {METHODS}, got {cfg['method']!r}")
    return cfg


# ------------------------------------------------------------------------------------------------
# relative pose of one image to the place
# ------------------------------------------------------------------------------------------------
@dataclass
class RelativePose:
    """Pose of a training image's vehicle frame in the place frame, solved from signatures.

    Attributes
    ----------
    ok : whether the solution passed the checks (``reason`` says why not).
    T_place_vehicle : (4,4) or None.
    covariance : (6,6) ``(ω, v)`` covariance (right perturbation, vehicle frame) or None.
    detections : detections used as candidates (fired, with a landmark in front of the camera).
    inliers : detections explaining the pose.
    rms_px : RMS reprojection error of the inliers (ideal pixels).
    reason : ``"ok"`` or why the pose was not usable.
    """

    ok: bool
    T_place_vehicle: np.ndarray | None
    covariance: np.ndarray | None
    detections: int
    inliers: int
    rms_px: float
    reason: str
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool), repr=False)

    @property
    def position_sigma_m(self) -> float:
        """Largest standard deviation of the position (m); inf without a covariance."""
        if self.covariance is None:
            return float("inf")
        return float(np.sqrt(max(np.linalg.eigvalsh(self.covariance[3:, 3:]).max(), 0.0)))


class _PnP:
    """Projection residuals of landmarks (place frame) for a vehicle pose ``T_place_vehicle``.

    Perturbation on the right (vehicle frame): ``R ← R·Exp(ω)``, ``t ← t + R·v``; then
    ``P_v' ≈ P_v + [P_v]× ω - v`` for ``P_v = Rᵀ(p - t)``.
    """

    def __init__(self, uv, R, landmarks, landmark_cov, camera: Camera, T_vehicle_camera):
        self.uv, self.R, self.p, self.Pl = uv, R, landmarks, landmark_cov
        self.cam = camera
        self.R_cv = np.asarray(T_vehicle_camera, float)[:3, :3]
        self.t_cv = np.asarray(T_vehicle_camera, float)[:3, 3]

    def camera_points(self, T: np.ndarray, idx: np.ndarray):
        Rw, t = T[:3, :3], T[:3, 3]
        Pv = (self.p[idx] - t) @ Rw                   # Rᵀ (p - t), row-wise
        Pc = (Pv - self.t_cv) @ self.R_cv             # R_cvᵀ (P_v - t_cv)
        return Pv, Pc

    def whitening(self, T: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Cholesky factors ``L`` with ``Lᵀ L = Σ_i⁻¹`` at pose ``T`` (held fixed during a round)."""
        _, Pc = self.camera_points(T, idx)
        Pc = Pc.copy()
        Pc[:, 2] = np.maximum(Pc[:, 2], 1e-3)
        J = self.cam.project_jacobian(Pc)                       # (n,2,3)
        G = J @ (self.R_cv.T @ T[:3, :3].T)                     # d uv / d p_place
        S = self.R[idx] + G @ self.Pl[idx] @ np.swapaxes(G, 1, 2)
        info = np.linalg.inv(S)
        # Lᵀ L = info: L = chol(info)ᵀ
        return np.swapaxes(np.linalg.cholesky(info), 1, 2)

    def residuals(self, T, idx, W):
        """Whitened residuals (n,2), Mahalanobis norms (n,), in-front mask (n,)."""
        _, Pc = self.camera_points(T, idx)
        front = Pc[:, 2] > 1e-3
        uvp, _ = self.cam.project(np.where(front[:, None], Pc, [0.0, 0.0, 1.0]))
        e = np.einsum("nij,nj->ni", W, self.uv[idx] - uvp)
        c = np.linalg.norm(e, axis=1)
        c[~front] = 1e3
        return e, c, front

    def jacobian(self, T, idx, W):
        """Jacobian of the whitened residuals w.r.t. ``(ω, v)``, (n,2,6)."""
        Pv, Pc = self.camera_points(T, idx)
        J = self.cam.project_jacobian(Pc) @ self.R_cv.T          # d uv / d P_v
        dP = point_pose_jacobian(Pv)                              # [P_v]x | -I
        # residual = uv_obs - h: its Jacobian is -J dP
        return -np.einsum("nij,njk->nik", W, J @ dP)


def _retract(T, xi):
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ exp_so3(xi[:3])
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ xi[3:]
    return out


def _gauss_newton(prob: _PnP, T, idx, W, cfg):
    k = float(cfg["huber_k"])

    def cost(T_):
        _, c, _ = prob.residuals(T_, idx, W)
        return float(np.sum(np.where(c <= k, 0.5 * c ** 2, k * c - 0.5 * k ** 2)))

    lam, f = 1e-4, cost(T)
    for _ in range(int(cfg["max_iterations"])):
        e, c, _ = prob.residuals(T, idx, W)
        w = _huber_weight(c, k)
        J = prob.jacobian(T, idx, W).reshape(-1, 6)
        ww = np.repeat(w, 2)
        H = J.T @ (J * ww[:, None])
        g = J.T @ (ww * e.reshape(-1))
        while True:  # Levenberg-Marquardt damping
            try:
                step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), g)
            except np.linalg.LinAlgError:
                return T
            T_new = _retract(T, step)
            f_new = cost(T_new)
            if f_new <= f:
                break
            lam *= 10.0
            if lam > 1e8:
                return T
        lam = max(lam / 10.0, 1e-9)
        done = f - f_new < 1e-8 * max(f, 1e-12) or np.linalg.norm(step) < 1e-9
        T, f = T_new, f_new
        if done:
            break
    return T


def solve_relative_pose(uv, landmarks, camera: Camera, T_vehicle_camera, R=None, landmark_cov=None,
                        config: dict | None = None) -> RelativePose:
    """Pose ``T_place_vehicle`` of an image from 2D detections of landmarks known in the place frame.

    Parameters
    ----------
    uv : (n,2) detections (image pixels; NaN rows = not fired).
    landmarks : (n,3) their landmarks in the place frame.
    camera, T_vehicle_camera : the camera and its extrinsic.
    R : (n,2,2) detection covariances (px²); default ``4 I`` (2 px).
    landmark_cov : (n,3,3) landmark covariances (place frame); default 0.
    config : overrides of :data:`default_config` (the PnP and usability keys).

    Returns
    -------
    RelativePose
        ``ok`` only with at least ``min_inliers`` inliers forming ``min_inlier_fraction`` of the
        detections and a position σ below ``max_position_sigma_m``.
    """
    import cv2

    cfg = resolve_config(config)
    uv = np.asarray(uv, float).reshape(-1, 2)
    P = np.asarray(landmarks, float).reshape(-1, 3)
    n = len(uv)
    if len(P) != n:
        raise ValueError(f"{n} detections but {len(P)} landmarks")
    R = np.tile(4.0 * np.eye(2), (n, 1, 1)) if R is None else np.asarray(R, float).reshape(n, 2, 2)
    Pl = np.zeros((n, 3, 3)) if landmark_cov is None else np.asarray(landmark_cov, float).reshape(n, 3, 3)
    cam = ideal_camera(camera)
    uv = ideal_pixels(camera, uv)
    valid = np.isfinite(uv).all(1) & np.isfinite(P).all(1) & np.isfinite(R).all((1, 2)) & np.isfinite(Pl).all((1, 2))
    idx = np.nonzero(valid)[0]
    nd = len(idx)

    def fail(why, T=None, inl=0, rms=float("nan")):
        return RelativePose(False, T, None, nd, inl, rms, why, np.zeros(n, bool))

    if nd < max(int(cfg["min_inliers"]), 4):
        return fail("too_few_detections")
    T_vc = np.asarray(T_vehicle_camera, float)
    cv2.setRNGSeed(int(cfg["seed"]))
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            P[idx].astype(np.float64), uv[idx].astype(np.float64), cam.K, None,
            iterationsCount=int(cfg["ransac_iterations"]), reprojectionError=float(cfg["ransac_reprojection_px"]),
            confidence=float(cfg["ransac_confidence"]), flags=cv2.SOLVEPNP_EPNP)
    except cv2.error:
        ok = False
    if not ok or inl is None or len(inl) < 4:
        return fail("ransac_failed")
    T_cam_place = make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
    T = invert(T_vc @ T_cam_place)                      # T_place_vehicle
    prob = _PnP(uv, R, P, Pl, cam, T_vc)
    cur = idx[np.sort(inl.reshape(-1))]
    # front check: a RANSAC pose with the inliers behind the camera is a mirror solution
    for _ in range(int(cfg["max_rounds"])):
        W = prob.whitening(T, cur)
        T = _gauss_newton(prob, T, cur, W, cfg)
        Wall = prob.whitening(T, idx)
        _, c, front = prob.residuals(T, idx, Wall)
        _, Pc = prob.camera_points(T, idx)
        new = idx[(c ** 2 <= float(cfg["gate_chi2"])) & front & (Pc[:, 2] > float(cfg["min_depth_m"]))]
        if len(new) < 4:
            return fail("too_few_inliers", T, len(new))
        if np.array_equal(new, cur):
            break
        cur = new
    W = prob.whitening(T, cur)
    e, c, _ = prob.residuals(T, cur, W)
    J = prob.jacobian(T, cur, W).reshape(-1, 6)
    w = np.repeat(_huber_weight(c, float(cfg["huber_k"])), 2)
    H = J.T @ (J * w[:, None])
    _, Pc = prob.camera_points(T, cur)
    uvp, _ = prob.cam.project(Pc)
    rms = float(np.sqrt(np.mean(np.sum((uv[cur] - uvp) ** 2, axis=1))))
    mask = np.zeros(n, bool)
    mask[cur] = True
    try:
        cov = np.linalg.inv(H)
        cov = 0.5 * (cov + cov.T)
        if np.linalg.eigvalsh(cov).min() <= 0:
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        return RelativePose(False, T, None, nd, len(cur), rms, "degenerate", mask)
    res = RelativePose(True, T, cov, nd, len(cur), rms, "ok", mask)
    if len(cur) < int(cfg["min_inliers"]):
        res.ok, res.reason = False, "too_few_inliers"
    elif len(cur) < float(cfg["min_inlier_fraction"]) * nd:
        res.ok, res.reason = False, "low_inlier_fraction"
    elif res.position_sigma_m > float(cfg["max_position_sigma_m"]):
        res.ok, res.reason = False, "weak_geometry"
    return res


# ------------------------------------------------------------------------------------------------
# per-place observations (map build worker)
# ------------------------------------------------------------------------------------------------
def _ins_pose(run, frame: int) -> np.ndarray:
    return interpolate_poses(run.groundtruth_times, run.groundtruth_poses, run.frame_times[int(frame)])


def observe_place(place, views: list, images: list, bank, landmarks, covariances, Q=None,
                  config: dict | None = None) -> list[dict]:
    """Each training run's estimate of the place's world pose (JSON records for the place file).

    Parameters
    ----------
    place : mapping.places.Place
    views : list of TrainingView, the reference run's first (its frame defines the place frame).
    images : gray images of the views' training frames (as mined).
    bank : the place's kept :class:`scenesig.signatures.bank.Bank`; ``landmarks`` (n,3) and ``covariances``
        (n,3,3) its landmarks in the place frame.
    Q : base detection covariance of eq. 5 (px², 2x2); default: landmark refinement's ``Q``.
    config : overrides of :data:`default_config`.

    Returns
    -------
    list of dict
        Per view: ``run``, ``frame``, ``T_world_vehicle_ins`` (the run's INS at the image), ``ok``,
        ``reason``, ``T_place_vehicle`` (or None), ``position_sigma_m``, ``detections``, ``inliers``,
        ``rms_px``.  Empty with ``method="reference"``.
    """
    cfg = resolve_config(config)
    if cfg["method"] == "reference":
        return []
    Q = np.asarray(refine_defaults["Q"] if Q is None else Q, float)
    landmarks = np.asarray(landmarks, float).reshape(-1, 3)
    covariances = np.asarray(covariances, float).reshape(-1, 3, 3)
    areas = np.array([c.box[2] * c.box[3] for c in bank.classifiers], float) if len(bank) else np.zeros(0)
    area_ref = reference_area(areas)
    out = []
    for k, (v, img) in enumerate(zip(views, images)):
        rec = {"run": v.run.name, "frame": int(v.frame), "T_world_vehicle_ins": _ins_pose(v.run, v.frame).tolist()}
        if k == 0 and int(v.frame) == int(place.reference_frame):
            # the place frame *is* this image's vehicle frame
            rec.update(ok=True, reason="reference", T_place_vehicle=np.eye(4).tolist(), position_sigma_m=0.0,
                       detections=0, inliers=0, rms_px=0.0)
        elif not len(bank):
            rec.update(ok=False, reason="no_signatures", T_place_vehicle=None, position_sigma_m=None,
                       detections=0, inliers=0, rms_px=None)
        else:
            d = bank.detect(img, top_n=1)
            x, y, prob, s = d.x[:, 0], d.y[:, 0], d.prob[:, 0], d.scale[:, 0]
            good = np.isfinite(x) & np.isfinite(y) & (prob >= float(cfg["min_probability"])) & (s > 0)
            uv = np.where(good[:, None], np.column_stack([x, y]), np.nan)
            kq = np.where(good, detection_covariance_factor(np.nan_to_num(d.width[:, 0] * d.height[:, 0], nan=area_ref),
                                                            np.where(good, prob, 1.0), np.where(good, s, 1.0),
                                                            area_ref), 1.0)
            R = kq[:, None, None] * Q[None]                  # eq. 5
            rp = solve_relative_pose(uv, landmarks, v.run.camera, v.run.T_vehicle_camera, R, covariances, cfg)
            rec.update(ok=bool(rp.ok), reason=rp.reason,
                       T_place_vehicle=None if rp.T_place_vehicle is None else rp.T_place_vehicle.tolist(),
                       position_sigma_m=None if rp.covariance is None else rp.position_sigma_m,
                       detections=int(rp.detections), inliers=int(rp.inliers),
                       rms_px=None if not np.isfinite(rp.rms_px) else float(rp.rms_px))
        out.append(rec)
    return out


# ------------------------------------------------------------------------------------------------
# combination over runs and along the route
# ------------------------------------------------------------------------------------------------
def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _huber_mean(x: np.ndarray, k: float, iterations: int = 50) -> np.ndarray:
    """Huber M-estimate of the location of the rows of ``x`` (n,d) (norm of the row residual), by IRLS."""
    m = np.median(x, axis=0)
    for _ in range(iterations):
        r = np.linalg.norm(x - m, axis=1)
        w = _huber_weight(r, k)
        m_new = (w[:, None] * x).sum(0) / w.sum()
        if np.allclose(m_new, m, atol=1e-9):
            return m_new
        m = m_new
    return m


def combine_estimates(T_reference: np.ndarray, estimates, usable, config: dict | None = None):
    """Combine runs' estimates of one place's world pose into a correction of the reference pose.

    Parameters
    ----------
    T_reference : (4,4) the reference run's INS pose of the place.
    estimates : (K,4,4) ``T_world_place^(k)``.
    usable : (K,) bool, which estimates to use.

    Returns
    -------
    correction : (4,) ``dx, dy, dz`` (world, m) and ``dyaw`` (rad) to add to the reference pose, or
        None when no estimate is usable.
    info : dict
        ``runs_used``, ``spread_m`` (RMS horizontal distance of the used estimates from their combination),
        ``max_deviation_m``.
    """
    cfg = resolve_config(config)
    E = np.asarray(estimates, float).reshape(-1, 4, 4)
    use = np.asarray(usable, bool).reshape(-1)
    if not use.any():
        return None, {"runs_used": 0, "spread_m": None, "max_deviation_m": None}
    E = E[use]
    d = E[:, :3, 3] - T_reference[:3, 3]
    dyaw = _wrap(yaw_of(E) - yaw_of(T_reference))
    dp = _huber_mean(d, float(cfg["huber_m"]))
    dy = float(_huber_mean(dyaw[:, None], np.radians(float(cfg["huber_deg"])))[0])
    dev = np.linalg.norm(d[:, :2] - dp[:2], axis=1)
    info = {"runs_used": int(use.sum()), "spread_m": float(np.sqrt(np.mean(dev ** 2))),
            "max_deviation_m": float(dev.max())}
    return np.concatenate([dp, [dy]]), info


def smooth_corrections(distance_m, corrections, weights, sigma_m: float) -> np.ndarray:
    """Gaussian-kernel smoothing of per-place corrections along the route.

    Parameters
    ----------
    distance_m : (P,) places' distance along the reference run.
    corrections : (P,4) ``dx, dy, dz, dyaw``; rows of places without an estimate are ignored (NaN).
    weights : (P,) weight of each place's correction (e.g. runs used; 0 = none).
    sigma_m : kernel σ; 0 returns the corrections unchanged (NaN rows filled from the nearest place).

    Returns
    -------
    (P,4) smoothed corrections (zeros if no place has one).
    """
    s = np.asarray(distance_m, float).reshape(-1)
    C = np.asarray(corrections, float).reshape(len(s), -1)
    w = np.where(np.isfinite(C).all(1), np.asarray(weights, float).reshape(-1), 0.0)
    if not (w > 0).any():
        return np.zeros_like(C)
    Cz = np.where(np.isfinite(C), C, 0.0)
    if sigma_m <= 0:
        have = np.nonzero(w > 0)[0]
        nearest = have[np.argmin(np.abs(s[:, None] - s[have][None]), axis=1)]
        return np.where((w > 0)[:, None], Cz, Cz[nearest])
    K = np.exp(-0.5 * ((s[:, None] - s[None]) / sigma_m) ** 2) * w[None]
    return (K @ Cz) / K.sum(1, keepdims=True)


def _apply(T_reference: np.ndarray, c: np.ndarray) -> np.ndarray:
    T = np.array(T_reference, float)
    T[:3, :3] = rot_z(float(c[3])) @ T[:3, :3]
    T[:3, 3] = T[:3, 3] + c[:3]
    return T


def _usable(rec: dict, T_reference: np.ndarray, cfg: dict) -> tuple[bool, np.ndarray | None]:
    """Whether a view record gives an estimate, and the estimate ``T_world_place^(k)``."""
    if not rec.get("ok") or rec.get("T_place_vehicle") is None:
        return False, None
    est = np.asarray(rec["T_world_vehicle_ins"], float) @ invert(np.asarray(rec["T_place_vehicle"], float))
    # PnP, this run's INS and the reference INS must agree to within INS errors: else PnP is wrong
    off = np.linalg.norm(est[:3, 3] - T_reference[:3, 3])
    dyaw = abs(float(_wrap(yaw_of(est) - yaw_of(T_reference))))
    ok = off <= float(cfg["max_offset_m"]) and dyaw <= np.radians(float(cfg["max_heading_offset_deg"]))
    return ok, est


def georeference_places(places, observations: dict, config: dict | None = None):
    """World poses of the places from their per-run observations.

    Parameters
    ----------
    places : list of mapping.places.Place (``T_world_place`` = the reference run's INS, ``distance_m``).
    observations : dict place index -> list of :func:`observe_place` records.
    config : overrides of :data:`default_config`.

    Returns
    -------
    poses : dict place index -> (4,4) ``T_world_place``.
    extras : dict place index -> JSON dict for the manifest (``method``, ``runs_used``, ``runs_total``,
        ``spread_m``, ``correction_m``, ``correction_yaw_deg``, ``pnp_failed``, ``T_reference_ins_place``).
    """
    cfg = resolve_config(config)
    places = sorted(places, key=lambda p: p.index)
    if cfg["method"] == "reference":
        return ({p.index: np.asarray(p.T_world_place, float) for p in places},
                {p.index: {"method": "reference"} for p in places})
    raw = np.full((len(places), 4), np.nan)
    infos, failed, totals = [], [], []
    for i, p in enumerate(places):
        recs = observations.get(p.index, [])
        Tref = np.asarray(p.T_world_place, float)
        ests, use = [], []
        for r in recs:
            ok, est = _usable(r, Tref, cfg)
            ests.append(est if est is not None else np.eye(4))
            use.append(ok)
        c, info = combine_estimates(Tref, np.array(ests).reshape(-1, 4, 4), np.array(use, bool), cfg)
        if c is not None:
            raw[i] = c
        infos.append(info)
        failed.append({r["run"]: r.get("reason") for r, u in zip(recs, use) if not u})
        totals.append(len(recs))
    weights = np.array([inf["runs_used"] for inf in infos], float)
    sm = smooth_corrections([p.distance_m for p in places], raw, weights, float(cfg["smooth_m"]))
    poses, extras = {}, {}
    for i, p in enumerate(places):
        Tref = np.asarray(p.T_world_place, float)
        poses[p.index] = _apply(Tref, sm[i])
        extras[p.index] = {
            "method": "runs", "runs_used": infos[i]["runs_used"], "runs_total": totals[i],
            "spread_m": infos[i]["spread_m"], "max_deviation_m": infos[i]["max_deviation_m"],
            "correction_m": [float(v) for v in sm[i, :3]], "correction_yaw_deg": float(np.degrees(sm[i, 3])),
            "correction_unsmoothed_m": None if not np.isfinite(raw[i]).all() else [float(v) for v in raw[i, :3]],
            "pnp_failed": failed[i], "T_reference_ins_place": Tref.tolist(),
        }
    return poses, extras
