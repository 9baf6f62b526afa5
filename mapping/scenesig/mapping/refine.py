"""Landmark refinement for scene signatures (McManus et al. 2015, §3.2.1, eqs. 1-9).

Every classifier that survived mining is fired over a window of frames around its place (about +-10 m).
This module turns those detections into a motion-consistent 3D landmark, or rejects the classifier:

1. **temporal check** -- fit a line to the detections' image track with 2-point RANSAC and reject the
   classifier if fewer than half of its detections are inliers (a stable element moves smoothly);
2. **depth sweep** -- sample depths 1..100 m at 1 m along the ray of the anchor detection (the inlier
   detection nearest the reference frame), reproject into the window with the known odometry and keep the
   depth with the lowest total Huber cost;
3. **Levenberg-Marquardt** on the full 3D point with a Huber cost (eqs. 6-9), measurement covariance
   ``R = a / (lambda s) Q`` (eq. 5), implemented here as vectorised IRLS so a whole place (hundreds of
   classifiers) is one batched 3-parameter problem; then, when the detector's searched scales are known,
   a **scale gate**: firings at a scale the landmark's depth contradicts (the patch grew or shrank out of
   the searched pyramid levels, so the detector matched something else) are dropped and 2-3 repeated --
   not in the paper; without it, near landmarks came out far (their firings lag behind the growing patch);
4. **checks** -- reject landmarks behind the camera, at the depth bound or with a poor fit, and keep the
   point in the place frame with its covariance ``(H^T W R^-1 H)^-1``.

``scenesig bench refine`` runs the synthetic benchmark (accuracy and speed) and prints a JSON report.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from scenesig.mapping.geometry import (
    anchor_rays,
    camera_depth,
    camera_poses,
    derotate_pixels,
    detection_covariance_factor,
    ideal_camera,
    ideal_pixels,
    ray_points,
    reference_area,
    reproject,
    reproject_jacobian,
)
from scenesig.surveys.geometry import Camera, invert
from scenesig.surveys.settings import merge_settings
from scenesig.surveys.validation import check_covariance

__all__ = ["default_config", "REASONS", "WindowDetections", "RefineResult", "refine_landmarks",
           "temporal_check", "depth_sweep", "lm_huber", "huber"]

default_config = {
    # Base covariance Q (px^2) of the detector's search resolution at scale 1 (eqs. 4-5).
    "Q": [[4.0, 0.0], [0.0, 4.0]],
    # The patch area a is divided by this before eq. 5 so that a/(lambda s) is dimensionless and Q keeps its
    # meaning (the covariance of a typical patch at full scale and certainty).  None: the median area of the
    # valid detections passed in, so callers can pass areas in pixels (width * height) directly.
    "area_ref": None,
    # Fewer detections than this cannot give a track and parallax worth trusting (rejected as "temporal").
    "min_detections": 4,
    # Temporal check: RANSAC inlier distance to the track line, as a fraction of the image diagonal.
    "temporal_inlier_frac": 0.03,
    "temporal_min_inlier_ratio": 0.5,
    # Rotate detections into the place camera's orientation first, so turning does not bend the track.
    "temporal_derotate": True,
    # All pairs are tried when there are at most this many; otherwise this many random pairs (seeded).
    "ransac_max_pairs": 256,
    "seed": 0,
    # Depth sweep along the anchor ray (anchor-camera depth, metres); 0 is skipped.
    "sweep_min": 1.0,
    "sweep_max": 100.0,
    "sweep_step": 1.0,
    # Huber threshold alpha (eq. 9) on the Mahalanobis residual c = sqrt(e^T R^-1 e).
    "huber_alpha": 2.0,
    "lm_max_iterations": 50,
    "lm_tolerance": 1e-7,
    # Depth checks (place-camera depth, metres): behind / too close, and the sweep's upper bound.
    "min_depth": 0.5,
    "depth_bound": 99.0,
    # Also reject when depth + k * sigma_depth reaches the bound: the data cannot tell the landmark from
    # one at the bound (a far point seen with little parallax).  None disables.
    "depth_bound_sigmas": 1.0,
    # Fit checks over the detections the final estimate explains (Mahalanobis residual <= fit_outlier_mahal).
    "fit_outlier_mahal": 6.0,
    "fit_max_rms_mahal": 3.0,
    # RMS pixel error as a fraction of the image diagonal (6 px at 640x480); None disables.  A large patch
    # that straddles a depth discontinuity deforms as the vehicle moves -- its parts move with different
    # parallax -- so no single point explains its firings to within a few pixels, and whatever depth it
    # gets is not the depth of anything in it: on the simulator (demo world) such landmarks (RMS 6-16 px)
    # had median depth errors 2-3x those of the rest.
    "fit_max_rms_frac": 0.0075,
    # Multiply the covariance by the a-posteriori variance factor (chi^2 / dof) when R is poorly known.
    "scale_covariance": False,
    # Scale gating (only with WindowDetections.scale_range).  A landmark at depth z_a in the anchor camera appears
    # z_a / z_j times larger in window frame j, so the detector can only have found it at scale
    # s_j = s_a z_j / z_a (s_a: the anchor firing's scale).  Where s_j lies outside the searched scales (by
    # more than ``scale_range_margin`` octaves) the patch could not be matched, and where the firing's own
    # scale differs from s_j by more than ``scale_tolerance`` octaves it matched something else -- in both
    # cases, for large patches, typically a part of the grown patch that lags towards the focus of
    # expansion and drags the depth far.  The depth sweep scores each sampled depth without the firings it
    # rules out, plus a Huber cost on every firing's scale residual (sigma = scale_tolerance / 2; else a
    # depth at which the patch hardly grows would explain the lagging firings for free); LM then runs on
    # the firings the estimate leaves, re-censoring and re-running at most ``scale_iterations`` times.
    # Censored firings are neither used nor counted against the landmark by the fit check.
    "scale_tolerance": 0.25,       # octaves (one pyramid level at 4 scales per octave)
    "scale_range_margin": 0.125,   # octaves (half a level: the detector still matches that far off)
    "scale_iterations": 3,         # 0 disables the gating
    # Landmarks per vectorised batch (bounds memory of the sweep: chunk x depths x frames x 3 floats).
    "chunk": 64,
}

#: Rejection reasons, in the order they are tested.
REASONS = ("temporal", "depth", "fit")

_C_BEHIND = 1e3  # Mahalanobis residual charged for an observation behind its camera (a hard outlier)


def huber(c: np.ndarray, alpha: float) -> np.ndarray:
    """Huber cost of the paper, ``c^2`` for ``|c| < alpha`` and ``2 alpha |c| - alpha^2`` beyond."""
    c = np.abs(c)
    return np.where(c < alpha, c * c, 2.0 * alpha * c - alpha * alpha)


def _huber_weight(c: np.ndarray, alpha: float) -> np.ndarray:
    """IRLS weights of eq. 9: 1 inside the threshold, ``alpha / c`` beyond."""
    with np.errstate(divide="ignore"):
        return np.where(c < alpha, 1.0, alpha / np.maximum(c, 1e-300))


@dataclass
class WindowDetections:
    """Detections of N classifiers over F window frames (the refinement window; a frame's bank detection
    is :class:`scenesig.signatures.detection.Detections`).

    Parameters
    ----------
    uv : (N, F, 2) array
        Detection centres in pixels of the (possibly distorted) camera; NaN where the classifier did not
        fire.  (F, 2) is accepted for a single classifier.
    scale : (N, F) array
        Scale ``s`` at which it fired (1 = full resolution, 0.5 = half-resolution pyramid level).
    prob : (N, F) array
        Detection probability ``lambda`` in (0, 1].
    area : (N,) or (N, F) array
        Patch area ``a`` (see ``default_config["area_ref"]`` for the units).
    scale_range : (N, 2) array, optional
        Smallest and largest scale the detector searched for each classifier (e.g. its nominal pyramid
        level +- ``scale_search``).  Given, ``scale`` is taken to be the real pyramid scale of each firing
        and the refinement gates detections by scale (see ``default_config["scale_tolerance"]``); None
        (default) leaves scales to eq. 5 only.
    """

    uv: np.ndarray
    scale: np.ndarray
    prob: np.ndarray
    area: np.ndarray
    scale_range: np.ndarray | None = None

    def __post_init__(self):
        uv = np.asarray(self.uv, dtype=float)
        if uv.ndim == 2:
            uv = uv[None]
        if uv.ndim != 3 or uv.shape[2] != 2:
            raise ValueError(f"uv must be (N, F, 2), got {np.shape(self.uv)}")
        N, F = uv.shape[:2]
        self.uv = uv

        def as_nf(name, a):
            a = np.asarray(a, dtype=float)
            if a.ndim == 0:
                return np.full((N, F), float(a))
            if a.shape == (F,) and N == 1:
                a = a[None]
            if a.shape == (N,):
                return np.repeat(a[:, None], F, axis=1)
            if a.shape != (N, F):
                raise ValueError(f"{name} must be (N, F) = {(N, F)} (or (N,) for area), got {a.shape}")
            return a

        self.scale = as_nf("scale", self.scale)
        self.prob = as_nf("prob", self.prob)
        self.area = as_nf("area", self.area)
        if self.scale_range is not None:
            r = np.asarray(self.scale_range, dtype=float)
            if r.shape == (2,):
                r = np.tile(r, (N, 1))
            if r.shape != (N, 2) or not np.all(r[:, 1] >= r[:, 0]) or not np.all(r > 0):
                raise ValueError(f"scale_range must be (N, 2) = ({N}, 2) positive [min, max] scales, got "
                                 f"{np.shape(self.scale_range)}")
            self.scale_range = r

    @property
    def shape(self) -> tuple[int, int]:
        """(N classifiers, F frames)."""
        return self.uv.shape[:2]


@dataclass
class RefineResult:
    """Outcome of :func:`refine_landmarks` for N classifiers over F window frames.

    Attributes
    ----------
    points : (N, 3) landmark in the place frame (NaN where it was never estimated).
    covariances : (N, 3, 3) covariance of ``points`` (NaN where never estimated).
    depth : (N,) depth of the landmark in the camera at the place (z, metres).
    sweep_depth : (N,) best anchor-camera depth of the sweep.
    reason : (N,) str, ``""`` for kept landmarks, else one of :data:`REASONS`.
    inliers : (N, F) bool, temporal-check inliers (the detections used by the optimiser).
    fit_inliers : (N, F) bool, detections the final estimate explains.
    inlier_ratio : (N,) temporal inlier ratio.
    rms_px, rms_mahal : (N,) RMS pixel / Mahalanobis residual over ``fit_inliers``.
    iterations : (N,) LM iterations; converged : (N,) bool.
    anchor : (N,) window frame whose detection anchored the depth sweep (-1 if none).
    censored : (N, F) bool, detections dropped by the scale gate (all False without it).
    """

    points: np.ndarray
    covariances: np.ndarray
    depth: np.ndarray
    sweep_depth: np.ndarray
    reason: np.ndarray
    inliers: np.ndarray
    fit_inliers: np.ndarray
    inlier_ratio: np.ndarray
    rms_px: np.ndarray
    rms_mahal: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    anchor: np.ndarray
    config: dict = field(default_factory=dict, repr=False)
    censored: np.ndarray | None = None

    @property
    def kept(self) -> np.ndarray:
        """(N,) bool: landmarks that passed every check."""
        return self.reason == ""

    def counts(self) -> dict:
        """Number of kept landmarks and of rejections per reason."""
        out = {"kept": int(self.kept.sum())}
        out.update({r: int((self.reason == r).sum()) for r in REASONS})
        return out


# --------------------------------------------------------------------------------------------------------
# 1. temporal check
# --------------------------------------------------------------------------------------------------------
def _line_distances(pa, pb, xy):
    """Distances (n, P, F) of points xy (n, F, 2) to the lines through pa, pb (n, P, 2).

    Degenerate pairs (pa == pb, e.g. a detection that never moves) measure the distance to the point.
    """
    d = pb - pa
    L = np.hypot(d[..., 0], d[..., 1])
    deg = L <= 1e-9
    normal = np.stack([-d[..., 1], d[..., 0]], axis=-1) / np.where(deg, 1.0, L)[..., None]
    # |n . (x - pa)| = |n . x - n . pa| as one batched matmul: (n, P, 2) @ (n, 2, F)
    # |n . (x - pa)| = |n . x - n . pa|, written out: far faster than batched 2-vector products
    offset = normal[..., 0] * pa[..., 0] + normal[..., 1] * pa[..., 1]
    dist = np.abs(normal[..., 0, None] * xy[:, None, :, 0] + normal[..., 1, None] * xy[:, None, :, 1]
                  - offset[..., None])
    if deg.any():
        r = xy[:, None, :, :] - pa[:, :, None, :]
        dist = np.where(deg[..., None], np.hypot(r[..., 0], r[..., 1]), dist)
    return dist


def _ransac_segment(xy, valid, thr, max_pairs, rng):
    """2-point RANSAC line per landmark over one track segment; returns the (N, Fs) inlier mask."""
    N, Fs = valid.shape
    inl = np.zeros((N, Fs), bool)
    if Fs < 2:
        return valid.copy()
    all_pairs = Fs * (Fs - 1) // 2
    if all_pairs <= max_pairs:
        ia, ib = np.triu_indices(Fs, 1)
        pa_idx = np.broadcast_to(ia, (N, all_pairs))
        pb_idx = np.broadcast_to(ib, (N, all_pairs))
    else:
        # Random distinct pairs among each landmark's valid detections (valid frames sorted first).
        order = np.argsort(~valid, axis=1, kind="stable")
        nv = valid.sum(axis=1)
        u1 = rng.random((N, max_pairs))
        u2 = rng.random((N, max_pairs))
        a = np.floor(u1 * nv[:, None]).astype(int)
        b = np.floor(u2 * np.maximum(nv[:, None] - 1, 1)).astype(int)
        b = b + (b >= a)
        a = np.minimum(a, Fs - 1)
        b = np.minimum(b, Fs - 1)
        pa_idx = np.take_along_axis(order, a, axis=1)
        pb_idx = np.take_along_axis(order, b, axis=1)
    rows = np.arange(N)[:, None]
    pair_ok = valid[rows, pa_idx] & valid[rows, pb_idx]
    xy0 = np.where(valid[..., None], xy, 0.0)  # finite everywhere; invalid frames are masked below
    dist = _line_distances(xy0[rows, pa_idx], xy0[rows, pb_idx], xy0)  # (N, P, Fs)
    vmask = valid[:, None, :]
    is_in = (dist < thr) & vmask
    count = is_in.sum(axis=2)
    # Most inliers wins; ties go to the tighter line (MSAC cost), so the choice does not depend on order.
    msac = np.where(vmask, np.minimum(dist * dist, thr * thr), 0.0).sum(axis=2)
    score = np.where(pair_ok, count - msac / (thr * thr * (Fs + 1)), -np.inf)
    best = np.argmax(score, axis=1)
    has = np.isfinite(score[np.arange(N), best])
    inl = is_in[np.arange(N), best] & has[:, None]

    # Local optimisation: refit the line to the inliers by total least squares and keep it if it explains
    # at least as many detections (a 2-point line is only as good as its two noisy points).
    w = inl.astype(float)
    n_in = w.sum(axis=1)
    refit = n_in >= 3
    if refit.any():
        xz = np.where(inl[..., None], xy, 0.0)
        m = xz.sum(axis=1) / np.maximum(n_in, 1)[:, None]
        r = np.where(inl[..., None], xy - m[:, None, :], 0.0)
        C = np.einsum("nfi,nfj->nij", r, r)
        _, vecs = np.linalg.eigh(C)
        normal = vecs[:, :, 0]  # smallest eigenvalue: normal of the best-fit line
        d2 = np.abs(np.einsum("nfi,ni->nf", np.nan_to_num(xy - m[:, None, :]), normal))
        inl2 = (d2 < thr) & valid
        better = refit & (inl2.sum(axis=1) >= n_in)
        inl[better] = inl2[better]
    return inl


def temporal_check(xy, valid, threshold, min_ratio=0.5, min_detections=4, max_pairs=256, seed=0,
                   segments=None):
    """2-point RANSAC line fit to each classifier's image track (paper Fig. 4).

    Parameters
    ----------
    xy : (N, F, 2) array
        Detection positions (ideally derotated, see :func:`scenesig.mapping.geometry.derotate_pixels`).
    valid : (N, F) bool array
        Where a detection exists.
    threshold : float
        Inlier distance (pixels) to the line.
    min_ratio : float
        Minimum inlier ratio (paper: one half).
    min_detections : int
        Minimum number of inlier detections.
    max_pairs : int
        All pairs are tried when there are at most this many, else this many random pairs.
    seed : int
        Seed of the pair sampling (results repeat).
    segments : (F,) int array, optional
        Track label of each frame (e.g. one per training run); a line is fitted per segment.

    Returns
    -------
    inliers : (N, F) bool
    ok : (N,) bool
        Passed the check.
    ratio : (N,) float
        Inlier ratio (0 where there are no detections).
    """
    xy = np.asarray(xy, dtype=float)
    valid = np.asarray(valid, bool) & np.isfinite(xy).all(axis=2)
    N, F = valid.shape
    seg = np.zeros(F, int) if segments is None else np.asarray(segments)
    if seg.shape != (F,):
        raise ValueError(f"segments must have one label per frame ({F}), got shape {seg.shape}")
    rng = np.random.default_rng(seed)
    inliers = np.zeros((N, F), bool)
    for s in np.unique(seg):
        cols = np.flatnonzero(seg == s)
        inliers[:, cols] = _ransac_segment(np.where(valid[:, cols, None], xy[:, cols], np.nan),
                                           valid[:, cols], float(threshold), int(max_pairs), rng)
    n_valid = valid.sum(axis=1)
    n_in = inliers.sum(axis=1)
    ratio = np.where(n_valid > 0, n_in / np.maximum(n_valid, 1), 0.0)
    ok = (ratio >= min_ratio) & (n_in >= min_detections)
    return inliers, ok, ratio


# --------------------------------------------------------------------------------------------------------
# 2-3. depth sweep and Levenberg-Marquardt with Huber weights
# --------------------------------------------------------------------------------------------------------
def _mahalanobis(e, k, Qinv):
    """c = sqrt(e^T R^-1 e) with R^-1 = k Q^-1 (eq. 5 gives k = lambda s / a)."""
    e0, e1 = e[..., 0], e[..., 1]
    q = Qinv[0, 0] * e0 * e0 + (Qinv[0, 1] + Qinv[1, 0]) * e0 * e1 + Qinv[1, 1] * e1 * e1
    return np.sqrt(np.maximum(k * q, 0.0))


def _scale_check(expected, log_s, lo, hi, tolerance, margin):
    """Scale gate of firings (all arguments broadcast; log2 scales / octaves).

    Returns ``usable`` -- the firing can be the landmark: the scale its depth predicts (``expected``) lies
    within the searched range ``[lo, hi]`` (+- ``margin``) and the firing's own scale ``log_s`` agrees with
    it within ``tolerance`` -- and ``residual``: ``log_s`` minus the predicted scale clamped to the searched
    range (what the detector reports at best when the patch grew or shrank beyond it).
    """
    with np.errstate(invalid="ignore"):
        inside = (expected >= lo - margin) & (expected <= hi + margin)
        residual = log_s - np.clip(expected, lo, hi)
        return inside & ~(np.abs(residual) > tolerance), residual


def depth_sweep(origin, direction, z_obs, k, mask, T_cam_place, camera, Qinv, alpha, depths, scale=None):
    """Total Huber reprojection cost of points at sampled depths along anchor rays.

    Parameters
    ----------
    origin, direction : (n, 3) arrays
        Anchor rays in the place frame (:func:`scenesig.mapping.geometry.anchor_rays`).
    z_obs : (n, F, 2) array
        Observations (ideal pixels).
    k : (n, F) array
        Information scale ``lambda s / a`` of each observation (``R^-1 = k Q^-1``).
    mask : (n, F) bool
        Observations to use.
    T_cam_place : (F, 4, 4), camera : ideal Camera, Qinv : (2, 2), alpha : Huber threshold.
    depths : (K,) array
        Sampled anchor-camera depths.
    scale : dict, optional
        Scale gate (see ``default_config["scale_tolerance"]``): ``log_s`` (n, F) log2 firing scales,
        ``log_sa`` (n,) log2 scale of the anchor firing, ``lo``, ``hi`` (n,) log2 searched scales,
        ``tolerance``, ``margin``, ``sigma`` (octaves).  At each depth, firings that depth rules out leave
        the reprojection cost, and every firing adds ``huber(residual / sigma)`` of its scale residual
        (:func:`_scale_check`) -- without it a depth at which the patch hardly grows would explain
        firings that lag behind a growing patch for free.

    Returns
    -------
    best : (n,) float
        Depth of minimum cost (the first one on ties).
    cost : (n, K) float
    """
    depths = np.asarray(depths, float)
    P = ray_points(origin, direction, depths)  # (n, K, 3)
    uv, zc = reproject(T_cam_place, P, camera)  # (n, K, F, 2), (n, K, F)
    e = z_obs[:, None] - uv
    c = _mahalanobis(e, k[:, None], Qinv)
    c = np.where((zc > 0) & np.isfinite(c), c, _C_BEHIND)
    use = np.broadcast_to(mask[:, None], c.shape)
    extra = 0.0
    if scale is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            expected = scale["log_sa"][:, None, None] + np.log2(zc / depths[None, :, None])
        usable, res = _scale_check(expected, scale["log_s"][:, None, :], scale["lo"][:, None, None],
                                   scale["hi"][:, None, None], scale["tolerance"], scale["margin"])
        # behind the camera is not censored: the reprojection cost charges it as the hard outlier it is
        use = use & (usable | ~(zc > 0))
        extra = np.where(mask[:, None] & np.isfinite(res), huber(np.nan_to_num(res) / scale["sigma"], alpha),
                         0.0).sum(axis=2)
    cost = np.where(use, huber(c, alpha), 0.0).sum(axis=2) + extra
    return depths[np.argmin(cost, axis=1)], cost


def _robust_system(p, z_obs, k, mask, T_cam_place, camera, Qinv, alpha):
    """Huber cost, IRLS normal matrix A = sum w H^T R^-1 H and gradient g = sum w H^T R^-1 e at p (n,3)."""
    uv, zc, H = reproject_jacobian(T_cam_place, p, camera)
    e = z_obs - uv
    front = (zc > 1e-6) & np.isfinite(uv).all(axis=-1)
    c = np.where(front, _mahalanobis(np.nan_to_num(e), k, Qinv), _C_BEHIND)
    use = mask & front
    cost = np.where(mask, huber(c, alpha), 0.0).sum(axis=1)
    wk = np.where(use, _huber_weight(c, alpha) * k, 0.0)  # (n, F): Huber-reweighted information scale
    H = np.nan_to_num(H)
    WHtQ = (np.swapaxes(H, -1, -2) @ Qinv) * wk[..., None, None]  # w k H^T Q^-1, (n, F, 3, 2)
    A = (WHtQ @ H).sum(axis=1)
    g = (WHtQ @ np.nan_to_num(e)[..., None])[..., 0].sum(axis=1)
    return cost, A, g, c, e, zc, wk


def lm_huber(p0, z_obs, k, mask, T_cam_place, camera, Qinv, alpha, max_iterations=50, tolerance=1e-7):
    """Levenberg-Marquardt with IRLS Huber weights on 3D points (eqs. 6-9), batched over landmarks.

    Each landmark is its own 3-parameter problem; all are stepped together, each with its own damping
    ``lambda`` (eq. 8: ``(H^T R~^-1 H + lambda 1) dp = H^T R~^-1 e``).  A step is kept only if it lowers
    that landmark's Huber cost.

    Parameters
    ----------
    p0 : (n, 3) array
        Initial points (place frame).
    z_obs, k, mask, T_cam_place, camera, Qinv, alpha
        As for :func:`depth_sweep`.
    max_iterations : int
    tolerance : float
        Convergence when the step is below ``tolerance * (|p| + 1)`` or the relative cost decrease below
        ``tolerance``.

    Returns
    -------
    p : (n, 3) array
        Refined points.
    A : (n, 3, 3) array
        Huber-weighted information matrix ``H^T W R^-1 H`` at the solution.
    cost : (n,) array
        Final Huber cost.
    iterations : (n,) int array
    converged : (n,) bool array
    """
    p = np.array(p0, dtype=float)
    n = len(p)
    args = (T_cam_place, camera, Qinv, alpha)
    cost, A, g, *_ = _robust_system(p, z_obs, k, mask, *args)
    scale = np.maximum(np.trace(A, axis1=1, axis2=2) / 3.0, 1e-12)
    lam = 1e-3 * scale
    iterations = np.zeros(n, int)
    converged = np.zeros(n, bool)
    eye = np.eye(3)
    for _ in range(int(max_iterations)):
        act = np.flatnonzero(~converged)
        if act.size == 0:
            break
        iterations[act] += 1
        M = A[act] + lam[act, None, None] * eye
        dp = np.linalg.solve(M, g[act][..., None])[..., 0]
        p_new = p[act] + dp
        c_new, A_new, g_new, *_ = _robust_system(p_new, z_obs[act], k[act], mask[act], *args)
        better = np.isfinite(c_new) & (c_new < cost[act])
        idx = act[better]
        small_step = np.linalg.norm(dp[better], axis=1) <= tolerance * (np.linalg.norm(p[idx], axis=1) + 1.0)
        small_gain = (cost[idx] - c_new[better]) <= tolerance * np.maximum(cost[idx], 1e-300)
        p[idx], cost[idx], A[idx], g[idx] = p_new[better], c_new[better], A_new[better], g_new[better]
        lam[idx] = np.maximum(lam[idx] / 10.0, 1e-12 * scale[idx])
        converged[idx[small_step | small_gain]] = True
        worse = act[~better]
        lam[worse] *= 10.0
        # Damping this large means no step can lower the cost any more: we are at the minimum.
        converged[worse[lam[worse] > 1e10 * scale[worse]]] = True
    return p, A, cost, iterations, converged


def _safe_inverse(A):
    """Batched inverse of 3x3 information matrices; NaN where (numerically) singular."""
    out = np.full_like(A, np.nan)
    cond = np.linalg.cond(A)
    ok = np.isfinite(cond) & (cond < 1e12)
    if ok.any():
        out[ok] = np.linalg.inv(A[ok])
    return out


# --------------------------------------------------------------------------------------------------------
# the whole stage
# --------------------------------------------------------------------------------------------------------
def refine_landmarks(detections: WindowDetections, T_window_place, camera: Camera, T_vehicle_camera,
                     reference: int | None = None, Q=None, segments=None, config: dict | None = None
                     ) -> RefineResult:
    """Refine (or reject) the landmarks of N classifiers from their detections over a window.

    Parameters
    ----------
    detections : WindowDetections
        (N classifiers, F window frames).
    T_window_place : (F, 4, 4) array
        ``T_{j,p}``: the place (vehicle) frame in each window vehicle frame, from the odometry increments
        (:func:`scenesig.mapping.geometry.window_poses_from_increments`).
    camera : Camera
        The survey camera (distortion allowed).
    T_vehicle_camera : (4, 4) array
    reference : int, optional
        Window frame of the place (default: the frame nearest the place frame's origin).  Anchors are the
        inlier detections nearest it.
    Q : (2, 2) array, optional
        Base covariance of the search resolution (px^2); default ``config["Q"]``.
    segments : (F,) int array, optional
        Track label per frame for the temporal check (frames of different runs form different tracks).
    config : dict, optional
        Overrides of :data:`default_config`.

    Returns
    -------
    RefineResult
    """
    cfg = merge_settings(default_config, config, "refinement")
    if not isinstance(detections, WindowDetections):
        raise TypeError("detections must be a mapping.refine.WindowDetections")
    N, F = detections.shape
    T_wp = np.asarray(T_window_place, dtype=float)
    if T_wp.shape != (F, 4, 4):
        raise ValueError(f"T_window_place must be (F, 4, 4) = ({F}, 4, 4), got {T_wp.shape}")
    T_vc = np.asarray(T_vehicle_camera, dtype=float)
    Qm = check_covariance(cfg["Q"] if Q is None else Q, 2, "Q")
    Qinv = np.linalg.inv(Qm)
    if reference is None:
        reference = int(np.argmin(np.linalg.norm(invert(T_wp)[:, :3, 3], axis=1)))
    if not 0 <= reference < F:
        raise ValueError(f"reference frame {reference} outside 0..{F - 1}")

    icam = ideal_camera(camera)
    diag = math.hypot(camera.width, camera.height)
    alpha = float(cfg["huber_alpha"])
    z_obs = ideal_pixels(camera, detections.uv)
    s, lamb, a = detections.scale, detections.prob, detections.area
    valid = np.isfinite(z_obs).all(axis=2) & (s > 0) & (lamb > 0) & (a > 0)
    area_ref = cfg["area_ref"]
    if area_ref is None:
        area_ref = reference_area(a[valid])
    if not area_ref > 0:
        raise ValueError(f"area_ref must be > 0, got {area_ref}")
    with np.errstate(divide="ignore", invalid="ignore"):
        # R^-1 = k Q^-1, eq. 5
        k = np.where(valid, detection_covariance_factor(a, lamb, s, area_ref, inverse=True), 0.0)
    z_obs = np.where(valid[..., None], z_obs, np.nan)
    T_cp = camera_poses(T_wp, T_vc)

    # 1. temporal check
    xy = derotate_pixels(z_obs, T_cp, T_vc, icam) if cfg["temporal_derotate"] else z_obs
    inliers, ok, ratio = temporal_check(
        xy, valid, cfg["temporal_inlier_frac"] * diag, cfg["temporal_min_inlier_ratio"],
        int(cfg["min_detections"]), int(cfg["ransac_max_pairs"]), int(cfg["seed"]), segments)

    points = np.full((N, 3), np.nan)
    covs = np.full((N, 3, 3), np.nan)
    sweep_depth = np.full(N, np.nan)
    iterations = np.zeros(N, int)
    converged = np.zeros(N, bool)
    anchor = np.full(N, -1)
    infos = np.full((N, 3, 3), np.nan)

    # Anchor: the inlier detection nearest (in frames) to the reference frame.
    dist = np.abs(np.arange(F) - reference)[None, :] + np.where(inliers, 0, 10 * F + 10)
    anchor[ok] = np.argmin(dist[ok], axis=1)
    depths = np.arange(cfg["sweep_min"], cfg["sweep_max"] + 0.5 * cfg["sweep_step"], cfg["sweep_step"])
    depths = depths[depths > 0]
    todo = np.flatnonzero(ok)
    chunk = max(1, int(cfg["chunk"]))

    # 3b. scale gate (with the searched scales): firings the landmark's depth rules out are censored
    censored = np.zeros((N, F), bool)
    temporal_inliers = inliers.copy()
    gate = None
    if detections.scale_range is not None and int(cfg["scale_iterations"]) > 0:
        with np.errstate(divide="ignore"):
            log_s = np.where(valid, np.log2(np.where(valid, s, 1.0)), np.nan)
        gate = {"log_s": log_s, "lo": np.log2(detections.scale_range[:, 0]),
                "hi": np.log2(detections.scale_range[:, 1]), "tolerance": float(cfg["scale_tolerance"]),
                "margin": float(cfg["scale_range_margin"]), "sigma": 0.5 * float(cfg["scale_tolerance"])}

    def censor(idx, p):
        """Firings of landmarks idx at points p (n, 3) their depth rules out (never the anchor)."""
        Pc = np.einsum("fij,nj->nfi", T_cp[:, :3, :3], np.nan_to_num(p)) + T_cp[:, :3, 3]
        z = Pc[..., 2]
        rows = np.arange(len(idx))
        za = z[rows, anchor[idx]]
        with np.errstate(divide="ignore", invalid="ignore"):
            expected = gate["log_s"][idx, anchor[idx]][:, None] + np.log2(z / za[:, None])
        usable, _ = _scale_check(expected, gate["log_s"][idx], gate["lo"][idx, None], gate["hi"][idx, None],
                                 gate["tolerance"], gate["margin"])
        out = valid[idx] & ~usable & (z > 0)  # behind the camera: an outlier, not a censored firing
        out[rows, anchor[idx]] = False
        out[~(np.isfinite(p).all(axis=1) & (za > 0))] = False
        return out

    def estimate(which):
        for start in range(0, which.size, chunk):
            idx = which[start:start + chunk]
            an = anchor[idx]
            o, d = anchor_rays(T_cp, z_obs[idx, an], an, icam)
            # 2. depth sweep
            g = None if gate is None else {**gate, "log_s": gate["log_s"][idx], "log_sa": gate["log_s"][idx, an],
                                           "lo": gate["lo"][idx], "hi": gate["hi"][idx]}
            best, _ = depth_sweep(o, d, z_obs[idx], k[idx], temporal_inliers[idx], T_cp, icam, Qinv, alpha, depths,
                                  scale=g)
            sweep_depth[idx] = best
            # 3. LM with Huber weights on the full 3D point (on the firings the gate leaves)
            p = o + best[:, None] * d
            for rep in range(max(1, int(cfg["scale_iterations"]) if gate is not None else 1)):
                if gate is not None:
                    cens = censor(idx, p)
                    if rep and np.array_equal(cens, censored[idx]):
                        break
                    censored[idx] = cens
                    inliers[idx] = temporal_inliers[idx] & ~cens
                p, A, _c, it, conv = lm_huber(p, z_obs[idx], k[idx], inliers[idx], T_cp, icam, Qinv, alpha,
                                              cfg["lm_max_iterations"], cfg["lm_tolerance"])
                points[idx], infos[idx], iterations[idx], converged[idx] = p, A, it, conv

    estimate(todo)

    # 4. checks, on the final estimate
    reason = np.full(N, "", dtype="<U8")
    reason[~ok] = "temporal"
    fit_inliers = np.zeros((N, F), bool)
    rms_px = np.full(N, np.nan)
    rms_mahal = np.full(N, np.nan)
    depth = np.full(N, np.nan)
    if todo.size:
        p = points[todo]
        _, _, _, c, e, zc, wk = _robust_system(np.nan_to_num(p), z_obs[todo], k[todo], inliers[todo],
                                               T_cp, icam, Qinv, alpha)
        fin = inliers[todo] & (zc > 0) & (c <= cfg["fit_outlier_mahal"])
        fit_inliers[todo] = fin
        nf = fin.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms_mahal[todo] = np.sqrt(np.where(fin, c * c, 0.0).sum(axis=1) / nf)
            rms_px[todo] = np.sqrt(np.where(fin, (np.nan_to_num(e) ** 2).sum(axis=2), 0.0).sum(axis=1) / nf)
        A = infos[todo]
        # (H^T W R^-1 H)^-1 with the final Huber weights: a detection many sigmas off counts for little, so
        # it cannot make the landmark look better known than the detections that agree.
        cov = _safe_inverse(A)
        if cfg["scale_covariance"]:
            dof = np.maximum(2 * nf - 3, 1)
            vf = np.where(fin, wk / np.maximum(k[todo], 1e-300) * c * c, 0.0).sum(axis=1) / dof
            cov = cov * np.maximum(vf, 1e-12)[:, None, None]
        covs[todo] = cov
        depth[todo] = camera_depth(p, T_vc)

        # depth: not estimated (singular) / behind or too close to the place camera / at the bound
        T_c_v = invert(T_vc)
        zdir = T_c_v[2, :3]  # d(depth)/d(p)
        var_depth = np.einsum("i,nij,j->n", zdir, cov, zdir)
        bad_depth = ~np.isfinite(p).all(axis=1) | ~np.isfinite(cov).all(axis=(1, 2))
        bad_depth |= depth[todo] <= cfg["min_depth"]
        # ... and in front of the anchor camera (observations behind other cameras are already outliers)
        bad_depth |= zc[np.arange(todo.size), anchor[todo]] <= cfg["min_depth"]
        bad_depth |= depth[todo] >= cfg["depth_bound"]
        if cfg["depth_bound_sigmas"] is not None:
            with np.errstate(invalid="ignore"):
                bad_depth |= (depth[todo] + cfg["depth_bound_sigmas"] * np.sqrt(np.maximum(var_depth, 0))
                              >= cfg["depth_bound"])
        # fit: too few explained detections, or residuals too large
        n_valid = (valid[todo] & ~censored[todo]).sum(axis=1)
        need = np.maximum(int(cfg["min_detections"]), np.ceil(cfg["temporal_min_inlier_ratio"] * n_valid))
        bad_fit = (nf < need) | ~(rms_mahal[todo] <= cfg["fit_max_rms_mahal"])
        if cfg["fit_max_rms_frac"] is not None:
            bad_fit |= ~(rms_px[todo] <= cfg["fit_max_rms_frac"] * diag)
        r = reason[todo]
        r[bad_depth] = "depth"
        r[~bad_depth & bad_fit] = "fit"
        reason[todo] = r

    return RefineResult(points=points, covariances=covs, depth=depth, sweep_depth=sweep_depth, reason=reason,
                        inliers=inliers, fit_inliers=fit_inliers, inlier_ratio=ratio, rms_px=rms_px,
                        rms_mahal=rms_mahal, iterations=iterations, converged=converged, anchor=anchor,
                        config=cfg, censored=censored)
