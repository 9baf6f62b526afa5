"""Location from matched regions: the affine transform of the best-consistent triple (Jin et al.
2016, §3.4, eqs. 7-18).

Every triple of matched region centres (sensed ``P_i`` -> registered ``P_ir``) defines an affine
transform (eq. 8).  It predicts where each *other* region should have registered (eq. 9); the
distance to where it did is that region's relative estimation error (eq. 10).  The triple whose
*smallest* relative error is lowest (eqs. 14-15) is chosen, and the sensed image's centre mapped by
its transform is the UAV's position on the reference (eq. 16).  Scale (eq. 17) and rotation
(eq. 18) between the images follow from the triple.

Two guards the paper states only in words: a triple must not be (nearly) collinear -- "a solution
exists if these three points are not collinear" -- so triples spanning less than
``min_triangle_area`` px^2 in the sensed image are skipped; and, since the images were
pre-processed for scale and rotation, a transform far from a similarity (singular values outside
``singular_range``, or unequal by more than ``max_anisotropy``) cannot be right and is skipped too.
All C(N, 3) triples are evaluated at once (N is at most a few tens).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from scenesig.surveys.settings import merge_settings

__all__ = ["affine_from_triple", "apply_affine", "TripleFit", "best_consistent_triple",
           "scale_rotation", "default_config", "AffineEstimate", "ransac_affine"]

#: Guards on the triples (see module docstring).
default_config = {
    "min_triangle_area": 400.0,        # px^2 in the sensed image
    "singular_range": (0.6, 1.6),      # allowed singular values of the linear part
    "max_anisotropy": 1.25,            # largest / smallest singular value
}


def affine_from_triple(src, dst) -> np.ndarray:
    """Affine transform(s) mapping three points exactly (eq. 8).

    Parameters
    ----------
    src, dst : array_like, (..., 3, 2)
        Sensed and registered points.

    Returns
    -------
    ndarray, (..., 2, 3)
        ``[[a00, a01, b0], [a10, a11, b1]]``.  NaN where the points are collinear.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    X = np.concatenate([np.swapaxes(src, -1, -2), np.ones(src.shape[:-2] + (1, 3))], axis=-2)
    Y = np.swapaxes(dst, -1, -2)                                            # (..., 2, 3)
    det = np.linalg.det(X)
    ok = np.abs(det) > 1e-9
    Xs = np.where(ok[..., None, None], X, np.eye(3))
    T = Y @ np.linalg.inv(Xs)
    return np.where(ok[..., None, None], T, np.nan)


def apply_affine(T: np.ndarray, xy) -> np.ndarray:
    """Map points ``(..., 2)`` by a 2 x 3 affine transform."""
    xy = np.asarray(xy, dtype=float)
    return xy @ np.asarray(T)[:, :2].T + np.asarray(T)[:, 2]


def scale_rotation(T: np.ndarray) -> tuple[float, float]:
    """Scale and rotation (degrees, counter-clockwise in image axes) of an affine's linear part.

    Scale is the geometric mean of the singular values (the ratio of reference to sensed lengths,
    the inverse of eq. 17's ``b``); rotation is that of the closest rotation matrix (eq. 18 measured
    on the whole transform rather than on one point pair).
    """
    L = np.asarray(T, dtype=float)[:, :2]
    u, s, vt = np.linalg.svd(L)
    R = u @ vt
    return float(np.sqrt(s[0] * s[1])), float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))


@dataclass
class TripleFit:
    """The chosen triple.

    Attributes
    ----------
    transform : ndarray (2, 3)
        Sensed -> reference affine of the triple (eq. 8).
    triple : tuple of int
        Indices of the three regions.
    min_error : float
        Its minimum relative estimation error over the other regions (eq. 14), px.
    errors : ndarray (N,)
        Relative error of every region under the transform (0 for the triple itself).
    """

    transform: np.ndarray
    triple: tuple
    min_error: float
    errors: np.ndarray


def best_consistent_triple(src, dst, config: dict | None = None,
                           groups=None) -> TripleFit | None:
    """The triple with the lowest minimum relative estimation error (eqs. 9-15).

    Parameters
    ----------
    src : array_like (N, 2)
        Region centres in the sensed image (N >= 4).
    dst : array_like (N, 2)
        Their registered positions in the reference.
    config : dict, optional
        Overrides of :data:`default_config`.
    groups : array_like (N,) of int, optional
        When a region contributes several candidate registrations (the top NCC peaks), the
        region each candidate belongs to: a triple takes three different regions, and a triple's
        relative errors are measured on the candidates of the *other* regions only.

    Returns
    -------
    TripleFit or None
        None when N < 4 or no triple passes the guards.
    """
    cfg = merge_settings(default_config, config, "affine")
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    n = len(src)
    g = np.arange(n) if groups is None else np.asarray(groups)
    if len(np.unique(g)) < 4:
        return None
    tri = np.array(list(combinations(range(n), 3)))                     # (M, 3)
    gt = g[tri]
    tri = tri[(gt[:, 0] != gt[:, 1]) & (gt[:, 0] != gt[:, 2]) & (gt[:, 1] != gt[:, 2])]
    s3, d3 = src[tri], dst[tri]
    e1, e2 = s3[:, 1] - s3[:, 0], s3[:, 2] - s3[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    T = affine_from_triple(s3, d3)                                       # (M, 2, 3)
    sv = np.linalg.svd(np.nan_to_num(T[:, :, :2]), compute_uv=False)      # (M, 2)
    lo, hi = cfg["singular_range"]
    ok = (area >= float(cfg["min_triangle_area"])) & np.all(np.isfinite(T), axis=(1, 2))
    ok &= (sv[:, 1] >= lo) & (sv[:, 0] <= hi)
    ok &= sv[:, 0] <= float(cfg["max_anisotropy"]) * np.maximum(sv[:, 1], 1e-12)
    if not ok.any():
        return None
    pred = np.einsum("mij,nj->mni", T[:, :, :2], src) + T[:, None, :, 2]   # (M, N, 2)
    err = np.linalg.norm(pred - dst[None], axis=2)
    own = (g[None, None, :] == g[tri][:, :, None]).any(axis=1)            # (M, N)
    emin = np.where(own, np.inf, err).min(axis=1)
    emin[~ok] = np.inf
    best = int(np.argmin(emin))
    errors = np.where(own[best], 0.0, err[best])
    return TripleFit(T[best], tuple(int(i) for i in tri[best]), float(emin[best]), errors)


@dataclass
class AffineEstimate:
    """A sensed image placed on the reference by an affine fitted to correspondences.

    Attributes
    ----------
    centre : ndarray (2,)
        The sensed centre on the reference (NaN when there is no estimate).
    transform : ndarray (2, 3) or None
    inliers : int
    candidates : int
        Correspondences offered to RANSAC (matches, detections).
    scale, rotation_deg : float
    seconds : float
    matched_pairs, keypoints : int
        Point matchers: putative matches and sensed keypoints (what the seeds' measures read; 0 otherwise).
    point_data : dict
        Point matchers: sensed and tile keypoints, the match index pairs, detection / matching seconds.
    """

    centre: np.ndarray
    transform: np.ndarray | None
    inliers: int
    candidates: int
    scale: float = float("nan")
    rotation_deg: float = float("nan")
    seconds: float = 0.0
    matched_pairs: int = 0
    keypoints: int = 0
    point_data: dict = field(default_factory=dict, repr=False)


def ransac_affine(src, dst, centre, threshold_px: float, min_inliers: int,
                  iterations: int = 2000) -> AffineEstimate:
    """``cv2.estimateAffine2D`` (RANSAC, then refinement on the inliers) of sensed -> reference
    correspondences, and the sensed ``centre`` mapped by it; no estimate below ``min_inliers``."""
    import cv2

    src = np.asarray(src, np.float32).reshape(-1, 2)
    dst = np.asarray(dst, np.float32).reshape(-1, 2)
    nan = np.full(2, np.nan)
    if len(src) < max(3, int(min_inliers)):
        return AffineEstimate(nan, None, 0, len(src))
    T, inl = cv2.estimateAffine2D(src, dst, method=cv2.RANSAC,
                                  ransacReprojThreshold=float(threshold_px),
                                  maxIters=int(iterations), confidence=0.999, refineIters=10)
    n_in = int(inl.sum()) if inl is not None else 0
    if T is None or n_in < int(min_inliers):
        return AffineEstimate(nan, None, n_in, len(src))
    sc, rot = scale_rotation(T)
    return AffineEstimate(apply_affine(T, centre), T, n_in, len(src), sc, rot)
