"""Pose of the vehicle relative to a place from 2D-3D correspondences and a motion prior (McManus et al. 2015, eq. 10).

The solver minimises

    J(T) = 1/2 q(T, T̂)^T P_x^{-1} q(T, T̂) + 1/2 Σ_i ρ( ||z_i - h(T, p_i)||²_{Σ_i} )

over the vehicle pose ``T = T_place_vehicle`` with Levenberg-Marquardt, where

* ``q(T, T̂) = Log(T̂^{-1} T)`` is the 6-vector between the pose and the motion prior ``T̂``;
* ``h`` projects the landmark ``p_i`` (place frame) through the extrinsic ``T_vehicle_camera`` and the
  pinhole camera (:class:`scenesig.surveys.geometry.Camera`);
* ``Σ_i = R_i + G_i P_l,i G_i^T`` is the detection covariance ``R_i`` (eq. 5, supplied by the caller)
  plus the landmark's map covariance ``P_l,i`` carried into the image by the projection Jacobian
  ``G_i = ∂h/∂p_i`` (a map landmark that is uncertain along the ray hardly matters, one uncertain
  across it does); ``Σ_i`` is evaluated once per solve round at the round's starting pose so the cost
  stays fixed while LM runs;
* ``ρ`` is the Huber cost on each detection's Mahalanobis norm (eqs. 8-9: IRLS weights ``k/c``).

Outliers: after a round, detections whose squared Mahalanobis residual exceeds the χ²(2) gate are
dropped and the pose re-solved, until the inlier set stops changing.  The result is rejected (with a
reason) when too few inliers remain, when they are too small a share of the detections, when the
solution is statistically inconsistent with the motion prior (χ²(6) gate), or when the information
matrix is not positive definite.

**Conventions** (the same as GTSAM's ``Pose3``, so results go straight into the pose graph): tangent
vectors are ``(ω, v)`` (rotation first), and perturbations are on the right, ``T = T̄ · Exp(ξ)``, i.e.
in the vehicle frame.  Because of that a covariance of ``T_place_vehicle`` is also the covariance of
``T_world_vehicle = T_world_place @ T_place_vehicle``; a prior given in the world becomes
``T_place_vehicle_prior = inv(T_world_place) @ T_world_vehicle_prior`` with the same ``P_prior``.

The spec's ``T_k,p`` (place -> vehicle at time k) is ``inv(T_place_vehicle)``.

Two back ends share the gating, the covariance (inverse of the Huber-weighted information at the
solution) and the checks: a compact numpy LM on the 6-dof tangent (default; its per-detection
residual and normal-equation loops compiled, :mod:`scenesig.localiser._solver_kernel`, equal to the numpy
array code to rounding) and a GTSAM factor graph
(``GenericProjectionFactorCal3_S2`` with landmarks as variables held by their map priors, Huber noise
models, ``LevenbergMarquardtOptimizer``; ~11 ms), kept as an independent reference that the tests
compare against, and for the benchmark (``scenesig bench solver``).  The same code serves point features via
:func:`solve_pnp_prior`, which initialises with a robust absolute pose (:mod:`scenesig.localiser.absolute_pose`).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from scenesig.localiser import _solver_kernel
from scenesig.localiser.absolute_pose import default_config as absolute_pose_default, estimate as estimate_absolute_pose
from scenesig.surveys.geometry import Camera, invert, point_pose_jacobian
from scenesig.surveys.settings import merge_settings
from scenesig.surveys.validation import check_array

__all__ = ["default_config", "SolveResult", "LocalisationConstraint", "solve", "solve_pnp_prior",
           "pose_exp", "pose_log", "default_pnp_config"]

default_config = {
    "huber_k": 1.5,             # Huber threshold, in sigmas of a detection's Mahalanobis norm
    "gate_chi2": 9.21,          # χ²(2 dof) 99 %: a detection beyond this after a round is an outlier
    "max_rounds": 4,            # solve / gate rounds (stops earlier once the inlier set is stable)
    "min_inliers": 4,           # fewer inliers: no constraint ("too_few_inliers")
    "min_inlier_fraction": 0.3,  # share of detections that must agree ("low_inlier_fraction")
    "prior_gate_chi2": 22.46,   # χ²(6 dof) 99.9 % on q(T, T̂): "inconsistent_with_prior"
    "max_iterations": 30,       # LM iterations per round
    "lambda_init": 1e-4,        # LM damping (Marquardt: scales diag of the normal matrix)
    "relative_tolerance": 1e-6,  # stop when the cost decreases by less than this fraction
    "step_tolerance": 1e-8,     # or the step's norm is below this
    "min_depth_m": 0.05,        # landmarks closer than this in front of the camera are unusable
    "backend": "numpy",         # "numpy" | "gtsam"
    # numpy back end: the per-detection loops compiled (localiser._solver_kernel; the same results to
    # rounding, about 1e-15 relative) where numba is installed; False: numpy array code.
    "compiled": True,
}

# PnP (point-feature) defaults, used by solve_pnp_prior only: the robust initialisation is
# localiser.absolute_pose (LO-RANSAC, iterations driven by the confidence), these are its options.
default_pnp_config = {
    "pixel_sigma": 1.0,          # std. dev. of a keypoint position (px) when no R is given
    **absolute_pose_default,
}

# Cost assigned to a detection whose landmark falls behind the camera (a Huber cost at this
# Mahalanobis norm): constant, so it neither pulls nor pushes, but a pose that hides landmarks
# behind the camera is not rewarded with a lower cost.
_BEHIND_NORM = 100.0


# --------------------------------------------------------------------------------- SE(3) maps
def pose_exp(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential of ``(ω, v)`` as a 4x4 matrix (GTSAM ``Pose3.Expmap``)."""
    return gtsam.Pose3.Expmap(np.asarray(xi, dtype=float)).matrix()


def pose_log(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm ``(ω, v)`` of a 4x4 matrix (GTSAM ``Pose3.Logmap``)."""
    return gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(T, dtype=float)))


def _log_derivative(q: np.ndarray) -> np.ndarray:
    """d Log(A·Exp(δ)) / dδ at δ = 0 where Log(A) = q (inverse right Jacobian)."""
    return gtsam.Pose3.LogmapDerivative(q)


# ------------------------------------------------------------------------------------ results
@dataclass
class LocalisationConstraint:
    """A localisation of the vehicle in the world, ready for the pose graph.

    Attributes
    ----------
    T_world_vehicle : (4,4) the solver's posterior pose.
    covariance : (6,6) posterior covariance (includes the motion prior).
    T_world_vehicle_detections : (4,4) the pose the detections alone point to (the prior removed to
        first order; in directions the detections do not constrain it equals the posterior).
    information_detections : (6,6) information (PSD, possibly singular) from the detections alone.

    The posterior already contains the motion prior, which in the pose graph is odometry again:
    feeding ``(T_world_vehicle_detections, information_detections)`` to
    :meth:`scenesig.localiser.posegraph.PoseGraph.add_localisation` avoids counting it twice.
    """

    T_world_vehicle: np.ndarray
    covariance: np.ndarray
    T_world_vehicle_detections: np.ndarray
    information_detections: np.ndarray


@dataclass
class SolveResult:
    """Outcome of one solve.  ``ok`` is False when no constraint should be used; ``reason`` says why.

    Poses are ``T_place_vehicle``; covariances follow GTSAM's Pose3 convention (module docstring).
    """

    ok: bool
    reason: str | None
    T_place_vehicle: np.ndarray
    covariance: np.ndarray | None
    information_detections: np.ndarray | None
    T_place_vehicle_detections: np.ndarray | None
    inliers: np.ndarray                 # (N,) bool
    mahalanobis_sq: np.ndarray          # (N,) squared Mahalanobis residual at the solution
    n_detections: int
    iterations: int
    rounds: int
    prior_chi2: float | None            # q^T P_x^{-1} q at the solution (None without a prior)
    cost: float
    ms: float
    backend: str = "numpy"
    extra: dict = field(default_factory=dict)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def constraint(self, T_world_place: np.ndarray) -> LocalisationConstraint | None:
        """The localisation in the world frame, or None when the solve was rejected."""
        if not self.ok:
            return None
        Twp = np.asarray(T_world_place, dtype=float)
        return LocalisationConstraint(Twp @ self.T_place_vehicle, self.covariance.copy(),
                                      Twp @ self.T_place_vehicle_detections,
                                      self.information_detections.copy())


# ---------------------------------------------------------------------------------- the model
class _Problem:
    """Correspondences, camera and prior for one solve, in the numpy back end's layout."""

    def __init__(self, uv, R, landmarks, landmark_cov, camera, T_vehicle_camera, T_prior, P_prior, cfg):
        self.cfg = cfg
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        n = len(uv)
        self.landmarks = check_array(landmarks, (n, 3), "landmarks")
        self.R = check_array(R, (n, 2, 2), "R")
        self.landmark_cov = None if landmark_cov is None else check_array(landmark_cov, (n, 3, 3), "landmark_cov")
        if not np.all(np.isfinite(uv)):
            raise ValueError("detections uv contain non-finite values")
        if any(camera.distortion):
            # Work with ideal (undistorted) pixels so the model and its Jacobian agree exactly; R is
            # kept, which is accurate to first order for the mild distortion of road cameras.
            rays = camera.rays(uv)
            uv = np.stack([camera.fx * rays[:, 0] + camera.cx, camera.fy * rays[:, 1] + camera.cy], axis=1)
            camera = dataclasses.replace(camera, distortion=())
        self.uv = uv
        self.camera = camera
        self.T_vehicle_camera = check_array(T_vehicle_camera, (4, 4), "T_vehicle_camera")
        T_cv = invert(self.T_vehicle_camera)
        self.R_cv, self.t_cv = np.ascontiguousarray(T_cv[:3, :3]), np.ascontiguousarray(T_cv[:3, 3])
        self._compiled = bool(cfg.get("compiled", False)) and _solver_kernel.AVAILABLE
        self._gathered: tuple = (None, None, None)        # (idx, landmarks[idx], uv[idx]) of the last call
        self.T_prior = None if T_prior is None else check_array(T_prior, (4, 4), "T_place_vehicle_prior")
        if T_prior is not None:
            P = check_array(P_prior, (6, 6), "P_prior")
            try:
                self.P_inv = np.linalg.inv(P)
                np.linalg.cholesky(self.P_inv)
            except np.linalg.LinAlgError:
                raise ValueError("P_prior must be symmetric positive definite") from None
            self.T_prior_inv = invert(self.T_prior)
        else:
            self.P_inv = None

    # -- geometry -------------------------------------------------------------------------
    def points(self, T: np.ndarray, idx: np.ndarray):
        """Vehicle- and camera-frame landmark coordinates at pose T (T_place_vehicle)."""
        R_pv, t_pv = T[:3, :3], T[:3, 3]
        P_v = (self.landmarks[idx] - t_pv) @ R_pv          # = R_pv^T (p - t)
        P_c = P_v @ self.R_cv.T + self.t_cv
        return P_v, P_c

    def whitening(self, T: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """(n,2,2) W with W^T W = Σ^{-1}, Σ = R + G P_l G^T evaluated at pose T."""
        S = self.R[idx].copy()
        if self.landmark_cov is not None:
            _, P_c = self.points(T, idx)
            Jp = self.camera.project_jacobian(P_c)
            G = Jp @ (self.R_cv @ T[:3, :3].T)               # d uv / d p (place frame)
            S += G @ self.landmark_cov[idx] @ np.swapaxes(G, 1, 2)
        # Inverse of the 2x2 Cholesky factor in closed form (vectorised).
        a = np.sqrt(S[:, 0, 0])
        b = S[:, 1, 0] / a
        c = np.sqrt(np.maximum(S[:, 1, 1] - b * b, 0.0))
        if not (np.all(a > 0) and np.all(c > 0) and np.all(np.isfinite(c))):
            raise ValueError("a detection covariance R (+ landmark term) is not positive definite")
        W = np.zeros_like(S)
        W[:, 0, 0] = 1.0 / a
        W[:, 1, 0] = -b / (a * c)
        W[:, 1, 1] = 1.0 / c
        return W

    def _gather(self, idx):
        """``landmarks[idx], uv[idx]`` (one LM round asks for the same rows twenty times)."""
        last, L, uv = self._gathered
        if last is not idx:
            L, uv = np.ascontiguousarray(self.landmarks[idx], float), np.ascontiguousarray(self.uv[idx], float)
            self._gathered = (idx, L, uv)
        return L, uv

    def _compiled_residuals(self, T, idx, W):
        L, uv = self._gather(idx)
        cam = self.camera
        return _solver_kernel.residuals(L, uv, np.ascontiguousarray(W, float), np.ascontiguousarray(T[:3, :3]),
                                        np.ascontiguousarray(T[:3, 3]), self.R_cv, self.t_cv, cam.fx, cam.fy,
                                        cam.cx, cam.cy, self.cfg["min_depth_m"], _BEHIND_NORM, self.cfg["huber_k"])

    def residuals(self, T, idx, W):
        """Whitened residuals e (n,2) of z - h, norms c (n,), front mask, vehicle-frame points."""
        if self._compiled:
            return self._compiled_residuals(T, idx, W)[:5]
        P_v, P_c = self.points(T, idx)
        z = P_c[:, 2]
        front = z > self.cfg["min_depth_m"]
        zs = np.where(front, z, 1.0)
        cam = self.camera
        r = self.uv[idx] - np.stack([cam.fx * P_c[:, 0] / zs + cam.cx, cam.fy * P_c[:, 1] / zs + cam.cy], axis=1)
        e = np.einsum("nij,nj->ni", W, r)
        e[~front] = 0.0
        c = np.sqrt(np.einsum("ni,ni->n", e, e))
        c[~front] = _BEHIND_NORM
        return e, c, front, P_v, P_c

    def prior_residual(self, T):
        return pose_log(self.T_prior_inv @ T)

    def evaluate(self, T, idx, W) -> tuple[float, tuple]:
        """Cost J(T) (eq. 10 with Huber) and the quantities ``linearise`` reuses."""
        if self._compiled:
            *ev, total = self._compiled_residuals(T, idx, W)
            ev = tuple(ev)
        else:
            ev = self.residuals(T, idx, W)
            c = ev[1]
            k = self.cfg["huber_k"]
            total = 0.5 * np.where(c < k, c * c, 2 * k * c - k * k).sum()
        q = None
        if self.P_inv is not None:
            q = self.prior_residual(T)
            total += 0.5 * q @ self.P_inv @ q
        return float(total), ev + (q,)

    def cost(self, T, idx, W) -> float:
        return self.evaluate(T, idx, W)[0]

    def linearise(self, T, idx, W, ev=None):
        """Huber-weighted normal equations at T: (Λ_total, Λ_detections, rhs_total, rhs_detections).

        ``rhs`` is the negative gradient, so the Gauss-Newton step is ``Λ^{-1} rhs``.
        """
        if ev is None:
            ev = self.evaluate(T, idx, W)[1]
        e, c, front, P_v, P_c, q = ev
        k = self.cfg["huber_k"]
        if self._compiled:
            L_det, b_det = _solver_kernel.normal_equations(e, c, front, P_v, P_c, np.ascontiguousarray(W, float),
                                                           self.R_cv, self.camera.fx, self.camera.fy, k)
        else:
            D = point_pose_jacobian(P_v)         # d P_v / d ξ for T <- T·Exp(ξ)
            Jp = self.camera.project_jacobian(np.where(front[:, None], P_c, [0, 0, 1.0]))
            A = W @ (Jp @ (self.R_cv @ D))            # whitened d h / d ξ; e = W(z - h) so de/dξ = -A
            w = np.where(c < k, 1.0, k / np.maximum(c, 1e-300))   # IRLS weights of eq. 9
            w[~front] = 0.0
            Aw = A * w[:, None, None]
            L_det = np.einsum("nki,nkj->ij", Aw, A)
            b_det = np.einsum("nki,nk->i", Aw, e)
        L, b = L_det.copy(), b_det.copy()
        if q is not None:
            Dq = _log_derivative(q)
            DqP = Dq.T @ self.P_inv
            L += DqP @ Dq
            b -= DqP @ q
        return L, L_det, b, b_det


# ---------------------------------------------------------------------------- numpy back end
def _lm_numpy(prob: _Problem, T0: np.ndarray, idx: np.ndarray, W: np.ndarray):
    cfg = prob.cfg
    T = T0.copy()
    lam = cfg["lambda_init"]
    cost, ev = prob.evaluate(T, idx, W)
    it = 0
    for it in range(1, cfg["max_iterations"] + 1):
        L, _, b, _ = prob.linearise(T, idx, W, ev)
        dL = np.diag(np.maximum(np.diag(L), 1e-9))
        improved = False
        while lam < 1e10:
            try:
                xi = np.linalg.solve(L + lam * dL, b)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            T_new = T @ pose_exp(xi)
            new_cost, new_ev = prob.evaluate(T_new, idx, W)
            if new_cost <= cost:
                improved = True
                break
            lam *= 10
        if not improved:
            break
        decrease = cost - new_cost
        T, cost, ev = T_new, new_cost, new_ev
        lam = max(lam / 10, 1e-12)
        if decrease <= cfg["relative_tolerance"] * max(cost, 1e-300) or np.linalg.norm(xi) < cfg["step_tolerance"]:
            break
    return T, it


# ---------------------------------------------------------------------------- GTSAM back end
def _lm_gtsam(prob: _Problem, T0: np.ndarray, idx: np.ndarray, W: np.ndarray):
    """The same problem as a GTSAM factor graph; landmarks are variables held by their map priors.

    Equivalent to the numpy model to first order (the landmark marginalisation is exact here);
    Huber acts on the projection residual whitened by R alone.
    """
    cfg = prob.cfg
    X = gtsam.symbol("x", 0)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(X, gtsam.Pose3(T0))
    cam = prob.camera
    K = gtsam.Cal3_S2(cam.fx, cam.fy, 0.0, cam.cx, cam.cy)
    body_P_sensor = gtsam.Pose3(prob.T_vehicle_camera)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg["huber_k"])
    for j, i in enumerate(idx):
        L = gtsam.symbol("l", j)
        values.insert(L, prob.landmarks[i])
        noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(prob.R[i]))
        graph.add(gtsam.GenericProjectionFactorCal3_S2(prob.uv[i], noise, X, L, K, False, False, body_P_sensor))
        if prob.landmark_cov is not None and np.any(prob.landmark_cov[i]):
            lnoise = gtsam.noiseModel.Gaussian.Covariance(prob.landmark_cov[i])
            graph.add(gtsam.PriorFactorPoint3(L, prob.landmarks[i], lnoise))
        else:
            graph.add(gtsam.NonlinearEqualityPoint3(L, prob.landmarks[i]))
    if prob.P_inv is not None:
        graph.add(gtsam.PriorFactorPose3(X, gtsam.Pose3(prob.T_prior),
                                         gtsam.noiseModel.Gaussian.Information(prob.P_inv)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg["max_iterations"])
    params.setRelativeErrorTol(cfg["relative_tolerance"])
    params.setlambdaInitial(cfg["lambda_init"])
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    return result.atPose3(X).matrix(), int(opt.iterations())


# ------------------------------------------------------------------------------------ driver


def _solve(prob: _Problem, T_init: np.ndarray, idx0: np.ndarray, t_start: float, extra=None) -> SolveResult:
    cfg = prob.cfg
    n = len(prob.uv)
    lm = {"numpy": _lm_numpy, "gtsam": _lm_gtsam}.get(cfg["backend"])
    if lm is None:
        raise ValueError(f"unknown backend {cfg['backend']!r}; use 'numpy' or 'gtsam'")
    all_idx = np.arange(n)
    T = T_init.copy()
    active = np.zeros(n, bool)
    active[idx0] = True
    iterations = rounds = 0
    reason = None
    c2 = np.full(n, np.inf)

    def fail(why, T_out=T):
        return SolveResult(False, why, T_out, None, None, None, active.copy(), c2, n, iterations, rounds,
                           None, float("nan"), (time.perf_counter() - t_start) * 1e3, cfg["backend"],
                           extra or {})

    if active.sum() < cfg["min_inliers"]:
        return fail("too_few_detections" if n < cfg["min_inliers"] else "too_few_inliers")
    W_all = None            # whitening of every detection at the current T (per detection: rows reusable)
    while rounds < cfg["max_rounds"]:
        rounds += 1
        idx = np.flatnonzero(active)
        W = prob.whitening(T, idx) if W_all is None else W_all[idx]
        T, it = lm(prob, T, idx, W)
        iterations += it
        if not np.all(np.isfinite(T)):
            return fail("diverged")
        # Gate every detection (previous outliers may come back) at the new pose.
        W_all = prob.whitening(T, all_idx)
        _, c, front, _, _ = prob.residuals(T, all_idx, W_all)
        c2 = np.where(front, c * c, np.inf)
        new_active = c2 <= cfg["gate_chi2"]
        if new_active.sum() < cfg["min_inliers"]:
            active = new_active
            return fail("too_few_inliers", T)
        if np.array_equal(new_active, active):
            break
        active = new_active
    else:
        # Rounds exhausted with a changed inlier set: solve once more on the final set so the
        # pose and covariance belong to the reported inliers.
        idx = np.flatnonzero(active)
        T, it = lm(prob, T, idx, W_all[idx])
        iterations += it
        W_all = prob.whitening(T, all_idx)
        _, c, front, _, _ = prob.residuals(T, all_idx, W_all)
        c2 = np.where(front, c * c, np.inf)

    idx = np.flatnonzero(active)
    W = W_all[idx]
    cost, ev = prob.evaluate(T, idx, W)
    L, L_det, _, b_det = prob.linearise(T, idx, W, ev)
    prior_chi2 = None
    if prob.P_inv is not None:
        q = prob.prior_residual(T)
        prior_chi2 = float(q @ prob.P_inv @ q)
    if active.sum() < cfg["min_inlier_fraction"] * n:
        reason = "low_inlier_fraction"
    elif prior_chi2 is not None and prior_chi2 > cfg["prior_gate_chi2"]:
        reason = "inconsistent_with_prior"
    cov = None
    try:
        np.linalg.cholesky(L)
        cov = np.linalg.inv(L)
        cov = 0.5 * (cov + cov.T)
    except np.linalg.LinAlgError:
        reason = reason or "degenerate"
    # The pose the detections alone point to: at the optimum the detections' gradient balances
    # the prior's, so shifting by Λ_det^+ b_det (b_det = the detections' pull) removes the prior to
    # first order; directions the detections do not see get no shift.
    T_det = None
    if cov is not None:
        evals, evecs = np.linalg.eigh(0.5 * (L_det + L_det.T))
        keep = evals > 1e-9 * max(evals.max(), 1e-300)
        pinv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
        T_det = T @ pose_exp(pinv @ b_det)
    ok = reason is None
    return SolveResult(ok, reason, T, cov, 0.5 * (L_det + L_det.T), T_det, active.copy(), c2, n,
                       iterations, rounds, prior_chi2, cost, (time.perf_counter() - t_start) * 1e3,
                       cfg["backend"], extra or {})


def solve(uv, R, landmarks, T_place_vehicle_prior, P_prior, camera: Camera, T_vehicle_camera,
          landmark_cov=None, config: dict | None = None) -> SolveResult:
    """Solve eq. 10: vehicle pose in a place's frame from detections and a motion prior.

    Parameters
    ----------
    uv : (N,2) detections z_k^i, pixels (distorted, as observed).
    R : (N,2,2) detection covariances (eq. 5, pixels²).
    landmarks : (N,3) landmark positions p_p^i in the place frame, one per detection.
    T_place_vehicle_prior : (4,4) motion prior T̂ (McManus et al. 2015's T̂_k,p, eq. 10, inverted); also the LM start.
    P_prior : (6,6) its covariance, GTSAM Pose3 convention (rotation first, right perturbation).
    camera : :class:`scenesig.surveys.geometry.Camera`.
    T_vehicle_camera : (4,4) extrinsic.
    landmark_cov : (N,3,3) map covariances of the landmarks (place frame), or None.
    config : overrides of :data:`default_config`.

    Returns
    -------
    SolveResult
        ``ok`` with pose and covariance, or not ``ok`` with ``reason`` in {"too_few_detections",
        "too_few_inliers", "low_inlier_fraction", "inconsistent_with_prior", "degenerate", "diverged"}.
    """
    t0 = time.perf_counter()
    cfg = merge_settings(default_config, config, "solver")
    prob = _Problem(uv, R, landmarks, landmark_cov, camera, T_vehicle_camera, T_place_vehicle_prior, P_prior, cfg)
    return _solve(prob, prob.T_prior, np.arange(len(prob.uv)), t0)


def solve_pnp_prior(uv, points, camera: Camera, T_vehicle_camera, T_place_vehicle_prior=None, P_prior=None,
                    R=None, points_cov=None, config: dict | None = None,
                    pnp_config: dict | None = None) -> SolveResult:
    """Point-feature variant: PnP + RANSAC initialisation, then the same robust LM (with the prior if given).

    Parameters
    ----------
    uv : (N,2) matched keypoints in the live image (pixels).
    points : (N,3) their 3D points in the place frame (from the map keyframe).
    camera, T_vehicle_camera : as in :func:`solve`.
    T_place_vehicle_prior, P_prior : optional motion prior; without it the pose comes from the
        correspondences alone and the consistency-with-prior check is skipped.
    R : (N,2,2) keypoint covariances; default ``pixel_sigma² I``.
    points_cov : (N,3,3) 3D point covariances, or None.
    config, pnp_config : overrides of :data:`default_config` / :data:`default_pnp_config`.

    Returns
    -------
    SolveResult
        As :func:`solve`; ``extra["ransac_inliers"]`` counts RANSAC's inliers, reason
        ``"pnp_failed"`` when RANSAC finds no pose.
    """
    t0 = time.perf_counter()
    cfg = merge_settings(default_config, config, "solver")
    pcfg = merge_settings(default_pnp_config, pnp_config, "PnP")
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    n = len(uv)
    if R is None:
        R = np.tile(np.eye(2) * pcfg["pixel_sigma"] ** 2, (n, 1, 1))
    T_prior = T_place_vehicle_prior
    prob = _Problem(uv, R, points, points_cov, camera, T_vehicle_camera, T_prior,
                    P_prior if T_prior is not None else None, cfg)
    extra = {"ransac_inliers": 0, "ransac_iterations": 0}
    start = T_prior if T_prior is not None else np.eye(4)
    if n < max(cfg["min_inliers"], 4):
        return _solve(prob, start, np.arange(0), t0, extra)
    ap = estimate_absolute_pose(uv, prob.landmarks, camera,
                                {k: v for k, v in pcfg.items() if k in absolute_pose_default})
    extra["ransac_iterations"] = ap.iterations
    if not ap.ok:
        res = _solve(prob, start, np.arange(0), t0, extra)
        res.reason = "pnp_failed"
        return res
    extra["ransac_inliers"] = ap.n_inliers
    T_init = invert(prob.T_vehicle_camera @ ap.T_cam_place)
    return _solve(prob, T_init, np.flatnonzero(ap.inliers), t0, extra)
