"""The point-set-domain seed's evaluation measures (§6.2, eqs. 13-19, and its ROC), from exact truth.

Point matching (per sensed image against its tile; ``eps`` = 3 px; the truth ``to_tile`` maps every
sensed pixel to the tile exactly):

* ``KN`` -- keypoints detected in the sensed image; ``IPN`` -- its pixels; ``QR = KN / IPN`` (eq. 16);
* ``CKN`` -- sensed keypoints whose true tile position is within ``eps`` of a keypoint detected on the
  tile (corresponding keypoints); ``RPR = CKN / KN`` (eq. 13);
* ``DTMPN`` -- putative matches (after the method's filter, before RANSAC) whose tile keypoint lies
  within ``eps`` of the sensed keypoint's true position; ``AR = DTMPN / CKN`` (eq. 15);
* ``RR = DTMPN / (DTMPN + UDTMPN)`` (eq. 14).  The seed's ``UDTMPN`` counts "corresponding keypoints
  not correctly matched *or not detected*"; so that RR differs from AR, the denominator here is every
  sensed keypoint whose true position lies on the tile (``KN_on_tile``) -- each has a counterpart on the
  map whether or not the tile's detector found it -- and ``UDTMPN = KN_on_tile - DTMPN``;
* ``RT = T_CKD + T_CKDM`` (eq. 17): CPU seconds of detecting the sensed image's keypoints and of
  matching them (the tile's, offline map work, are not counted).

Set and domain matching: ``RMSE`` (eq. 18) between the sensed image and the tile warped onto it by the
method's estimate, on gray levels standardised over the overlap (zero mean, unit variance -- the trials'
photometric change would otherwise dominate; ``RMSE^2 = 2 (1 - NCC)``); ``RRMSE`` the same within each
region of :func:`scenesig.aerial.kdmm.ci_regions`, averaged over the regions.  A method without an
estimate is scored at the tile's centre, unrotated and unscaled.  Their decidability between genuine pairs
(an image against its own tile) and impostor pairs (against another tile) is given twice (eq. 19):

* ``*_DI`` as printed: ``|m_g - m_i| / sqrt((s_g + s_i) / 2)`` with ``s`` the standard deviations;
* ``*_d_prime`` the usual d': ``|m_g - m_i| / sqrt((s_g^2 + s_i^2) / 2)``.

Object matching: ROC AUC of the methods' match scores, genuine vs impostor pairs
(:func:`roc_auc`: the Mann-Whitney probability that a genuine pair outscores an impostor one, ties
counting half; a pair without an estimate scores ``-inf``).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["EPS_PX", "point_measures", "standardised_rmse", "region_rmse", "decidability", "roc_auc",
           "estimate_map", "match_score"]

#: The seed's tolerance for a correct correspondence (px), from exact truth.
EPS_PX = 3.0


def point_measures(sensed_xy, tile_xy, query, train, to_tile, tile_size, image_shape,
                   detect_seconds: float, match_seconds: float, eps: float = EPS_PX) -> dict:
    """RPR, RR, AR, QR, RT and their counts for one sensed image (module docstring).

    Parameters
    ----------
    sensed_xy, tile_xy : array_like (n, 2), (m, 2)
        Keypoints of the sensed image and of the tile.
    query, train : array_like (k,)
        Putative matches: indices into ``sensed_xy`` and ``tile_xy``.
    to_tile : callable
        Exact sensed -> tile map.
    tile_size : (width, height)
    image_shape : (height, width, ...)
        Of the sensed image.
    """
    s = np.asarray(sensed_xy, float).reshape(-1, 2)
    t = np.asarray(tile_xy, float).reshape(-1, 2)
    q, tr = np.asarray(query, np.int64), np.asarray(train, np.int64)
    kn = len(s)
    truth = np.asarray(to_tile(s), float).reshape(-1, 2) if kn else np.zeros((0, 2))
    W, H = tile_size
    on = (truth[:, 0] >= 0) & (truth[:, 0] <= W - 1) & (truth[:, 1] >= 0) & (truth[:, 1] <= H - 1)
    if kn and len(t):
        dist, _ = cKDTree(t).query(truth, k=1)
        ckn = int((dist <= eps).sum())
    else:
        ckn = 0
    dtmpn = int((np.linalg.norm(t[tr] - truth[q], axis=1) <= eps).sum()) if len(q) else 0
    kn_on = int(on.sum())
    ipn = int(image_shape[0]) * int(image_shape[1])
    return {"KN": kn, "CKN": ckn, "DTMPN": dtmpn, "UDTMPN": kn_on - dtmpn, "KN_on_tile": kn_on, "IPN": ipn,
            "RPR": ckn / kn if kn else float("nan"),
            "RR": dtmpn / kn_on if kn_on else float("nan"),
            "AR": dtmpn / ckn if ckn else float("nan"),
            "QR": kn / ipn,
            "RT": float(detect_seconds) + float(match_seconds)}


def estimate_map(result, tile_shape):
    """The sensed -> tile map of a method's estimate: its own ``map`` (point-set-domain), else its affine
    ``transform``; without an estimate the placement at the tile's centre (module docstring)."""
    f = getattr(result, "map", None)
    T = getattr(result, "transform", None)
    if callable(f) and getattr(result, "to_tile", None) is not None:
        return f
    if T is not None and np.all(np.isfinite(T)):
        T = np.asarray(T, float)
        return lambda xy: np.asarray(xy, float) @ T[:, :2].T + T[:, 2]
    H, W = tile_shape[:2]
    return None, ((W - 1) / 2.0, (H - 1) / 2.0)


def _warp_gray(tile, to_tile, image_shape, sensed_centre):
    import cv2

    from scenesig.aerial.kdmm import warp_reference

    if isinstance(to_tile, tuple):            # no estimate: the tile's centre, unrotated, unscaled
        cx, cy = to_tile[1]
        off = np.array([cx, cy]) - np.asarray(sensed_centre)
        to_tile = lambda xy, off=off: np.asarray(xy, float) + off        # noqa: E731
    ref, valid = warp_reference(tile, to_tile, image_shape[:2], 1.0, step=16)
    g = cv2.cvtColor(ref, cv2.COLOR_BGR2GRAY) if ref.ndim == 3 else ref
    return g.astype(np.float64), valid


def _z(a, m):
    v = a[m]
    sd = v.std()
    return (a - v.mean()) / (sd if sd > 1e-9 else 1.0)


def standardised_rmse(sensed, tile, to_tile, sensed_centre) -> float:
    """Eq. 18 on standardised gray levels over the overlap (module docstring); NaN without overlap."""
    import cv2

    g = cv2.cvtColor(sensed, cv2.COLOR_BGR2GRAY).astype(np.float64) if sensed.ndim == 3 else sensed.astype(float)
    r, valid = _warp_gray(tile, to_tile, g.shape, sensed_centre)
    if valid.sum() < 16:
        return float("nan")
    return float(np.sqrt(np.mean((_z(g, valid) - _z(r, valid))[valid] ** 2)))


def region_rmse(sensed, tile, to_tile, sensed_centre, labels) -> float:
    """RRMSE: eq. 18 within each region (``labels`` at the sensed image's resolution), averaged."""
    import cv2

    g = cv2.cvtColor(sensed, cv2.COLOR_BGR2GRAY).astype(np.float64) if sensed.ndim == 3 else sensed.astype(float)
    r, valid = _warp_gray(tile, to_tile, g.shape, sensed_centre)
    vals = []
    for e in np.unique(labels):
        m = (labels == e) & valid
        if m.sum() < 16:
            continue
        vals.append(np.sqrt(np.mean((_z(g, m) - _z(r, m))[m] ** 2)))
    return float(np.mean(vals)) if vals else float("nan")


def decidability(genuine, impostor) -> dict:
    """Eq. 19 as printed (``DI``) and the usual d' (``d_prime``) of two samples (NaNs dropped)."""
    g = np.asarray(genuine, float)
    i = np.asarray(impostor, float)
    g, i = g[np.isfinite(g)], i[np.isfinite(i)]
    if len(g) < 2 or len(i) < 2:
        return {"DI": None, "d_prime": None, "genuine_mean": None, "impostor_mean": None}
    mg, mi, sg, si = g.mean(), i.mean(), g.std(ddof=1), i.std(ddof=1)
    di = abs(mg - mi) / np.sqrt((sg + si) / 2) if sg + si > 0 else float("inf")
    dp = abs(mg - mi) / np.sqrt((sg ** 2 + si ** 2) / 2) if sg + si > 0 else float("inf")
    return {"DI": float(di), "d_prime": float(dp), "genuine_mean": float(mg), "impostor_mean": float(mi)}


def roc_auc(genuine, impostor) -> float | None:
    """Area under the ROC of scores (higher = genuine): P(genuine > impostor) + P(tie) / 2."""
    g = np.asarray(genuine, float)
    i = np.asarray(impostor, float)
    if not len(g) or not len(i):
        return None
    g = np.where(np.isnan(g), -np.inf, g)
    i = np.where(np.isnan(i), -np.inf, i)
    gt = (g[:, None] > i[None, :]).sum()
    eq = (g[:, None] == i[None, :]).sum()
    return float((gt + 0.5 * eq) / (len(g) * len(i)))


def match_score(result) -> float:
    """A method's match score (higher = more likely the right tile): ``score`` (point-set-domain), else the
    whole-image ``ncc`` (MRSM-CC), else its ``score`` (SISM's peak NCC), else RANSAC ``inliers``;
    ``-inf`` without an estimate."""
    c = np.asarray(getattr(result, "centre", [np.nan]), float)
    if not np.all(np.isfinite(c)):
        return float("-inf")
    names = ("score",) if hasattr(result, "dissimilarity") else ("ncc", "score", "inliers")
    for name in names:
        v = getattr(result, name, None)
        if v is not None and np.isfinite(v):
            return float(v)
    return float("-inf")
