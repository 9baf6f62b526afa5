"""Domain matching by region division, KDMM (the domain stage of the point-set-domain seed, §4.3).

1. **Regions (eqs. 10-11).**  The seed's MSER variant replaces the area of an extremal region by the
   half-width of the confidence interval of its mean grey level, ``CI = z S(n) / sqrt(n)`` (eq. 10;
   ``S`` the sample standard deviation of the region's ``n`` pixels), and calls a region stable where
   ``q(i) = (CI_{i+Delta} - CI_{i-Delta}) / CI_i`` (eq. 11) is at a local minimum over the threshold
   ``i``.  Here the extremal regions are the connected components of ``gray <= t`` for ``levels``
   thresholds between the image's extremes (and of ``gray >= t``, the other polarity), ``CI_{i+Delta}``
   is that of the region's parent ``Delta`` levels up and ``CI_{i-Delta}`` that of its largest child
   ``Delta`` levels down.  As printed ``q`` can be negative (CI usually shrinks as a region grows), so
   its magnitude is used: a stable region is one whose CI changes least.  ``z`` scales every CI alike
   and cancels in ``q``; it is kept (95 %, 1.96) only so CI is the seed's quantity.  Stable regions of
   ``min_area``..``max_area`` (fractions of the image) are taken in order of increasing ``|q|``, a
   region overlapping one already taken is skipped -- on one branch of the component tree this keeps
   the branch's minimum -- and at most ``max_regions``; they seed a watershed of the gradient
   magnitude, which divides the whole image into regions (the seed's "watershed MSER").
2. **Colour map and dissimilarity (eq. 12).**  Given an alignment of the map onto the sensed image,
   each region's colours on the map ``C_t`` are mapped by a colour transform ``phi_c`` -- an affine
   map of RGB fitted by least squares on the region's pixel pairs, a diffeomorphism of colour space
   when invertible -- and ``Diss_e = 1/2 mean |C_r - phi_c(C_t)|^2``.  Divided by the region's own
   colour variance (``1/2 mean |C_r - mean C_r|^2``, plus ``variance_floor``) it is the share of
   the region's colour the map cannot explain: near 0 for an aligned, merely recoloured region, near 1
   for an unrelated one.  Ground cover that changed (snow on a field) leaves some regions unexplained
   whatever the alignment, so the image's dissimilarity is the area-weighted mean over the *best*
   regions covering ``keep_fraction`` of the image ("the best dissimilarity decides").
3. **Decision.**  :func:`domain_dissimilarity` scores one alignment; :class:`scenesig.aerial.psd.PSDMatcher`
   scores every alignment hypothesis of the set stage and keeps the lowest (Algorithm 1's last step).
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "ci_regions", "fit_colour_map", "region_dissimilarities", "domain_dissimilarity",
           "warp_reference"]

#: Settings the seed leaves open (chosen on seed-0 development trials, docs/aerial.md).
default_config = {
    "work_scale": 0.5,          # regions and colours on the sensed image scaled by this
    "levels": 32,               # thresholds of the extremal-region sweep
    "delta": 2,                 # Delta of eq. 11, in levels
    "z": 1.96,                  # z_{sigma/2} of eq. 10 (cancels in q; see the module docstring)
    "min_area": 0.004,          # stable regions: area as a fraction of the image
    "max_area": 0.25,
    "max_regions": 24,
    "keep_fraction": 0.5,       # the best regions covering this share of the image decide
    "variance_floor": 25.0,     # added to a region's colour variance (grey levels^2)
    "min_valid": 0.5,           # an alignment must put this share of the image on the map
    "min_region_px": 30,        # regions with fewer valid pixels (at work_scale) are skipped
}


def _merge(config):
    cfg = merge_settings(default_config, config, "KDMM")
    if int(cfg["delta"]) < 1 or int(cfg["levels"]) < 2 * int(cfg["delta"]) + 1:
        raise ValueError(f"KDMM needs delta >= 1 and levels >= 2 delta + 1, got delta {cfg['delta']}, "
                         f"levels {cfg['levels']}")
    if not 0 < float(cfg["keep_fraction"]) <= 1:
        raise ValueError(f"KDMM keep_fraction must be in (0, 1], got {cfg['keep_fraction']}")
    return cfg


def _stable_candidates(g: np.ndarray, cfg: dict) -> list:
    """(|q|, level, mask index) of the extremal regions of ``g <= t`` with their masks (module docstring)."""
    L, D, z = int(cfg["levels"]), int(cfg["delta"]), float(cfg["z"])
    n_pix = g.size
    lo_a, hi_a = float(cfg["min_area"]) * n_pix, float(cfg["max_area"]) * n_pix
    levels = np.linspace(float(g.min()), float(g.max()), L)
    flat = g.ravel().astype(np.float64)
    labs, cis, areas = [], [], []
    for t in levels:
        lab, n = ndimage.label(g <= t)
        lab = lab.ravel()
        cnt = np.bincount(lab, minlength=n + 1).astype(float)
        s1 = np.bincount(lab, weights=flat, minlength=n + 1)
        s2 = np.bincount(lab, weights=flat * flat, minlength=n + 1)
        var = (s2 - s1 * s1 / np.maximum(cnt, 1)) / np.maximum(cnt - 1, 1)
        ci = z * np.sqrt(np.maximum(var, 0)) / np.sqrt(np.maximum(cnt, 1))          # eq. 10
        ci[0] = np.nan                                                                 # background
        labs.append(lab)
        cis.append(ci)
        areas.append(cnt)
    out = []
    for i in range(D, L - D):
        lab, ci, area = labs[i], cis[i], areas[i]
        for c in np.flatnonzero((area >= lo_a) & (area <= hi_a)):
            if c == 0 or not ci[c] > 0:
                continue
            pix = np.flatnonzero(lab == c)
            parent = labs[i + D][pix[0]]
            child = labs[i - D][pix]
            child = child[child > 0]
            if not len(child):
                continue
            big = np.bincount(child).argmax()
            q = abs(cis[i + D][parent] - cis[i - D][big]) / ci[c]                       # eq. 11, |.|
            if np.isfinite(q):
                out.append((float(q), i, pix))
    return out


def ci_regions(image: np.ndarray, config: dict | None = None) -> np.ndarray:
    """Divide an image into regions: watershed seeded by the CI-stable extremal regions (eqs. 10-11).

    Parameters
    ----------
    image : ndarray (H, W, 3) or (H, W), uint8
        At the resolution the regions are wanted (callers pass the ``work_scale`` image).
    config : dict, optional
        Overrides of :data:`default_config`.

    Returns
    -------
    ndarray (H, W) int
        Region labels 1..R covering every pixel (one region when nothing is stable).
    """
    from skimage.filters import sobel
    from skimage.segmentation import watershed

    cfg = _merge(config)
    img = np.asarray(image)
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    if gray.ndim != 2 or gray.size == 0:
        raise ValueError(f"expected a gray or BGR image, got shape {img.shape}")
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    cands = _stable_candidates(g, cfg) + _stable_candidates(255.0 - g, cfg)
    cands.sort(key=lambda c: (c[0], c[1], int(c[2][0])))
    markers = np.zeros(g.size, np.int32)
    k = 0
    for q, _, pix in cands:
        if k >= int(cfg["max_regions"]):
            break
        if markers[pix].any():
            continue
        k += 1
        markers[pix] = k
    if k == 0:
        return np.ones(g.shape, np.int32)
    return watershed(sobel(g), markers.reshape(g.shape)).astype(np.int32)


def fit_colour_map(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares affine colour map ``phi_c`` (3 x 4) with ``dst ~ [src, 1] @ M.T`` (rows = pixels)."""
    X = np.column_stack([np.asarray(src, np.float64), np.ones(len(src))])
    M, *_ = np.linalg.lstsq(X, np.asarray(dst, np.float64), rcond=None)
    return M.T


def region_dissimilarities(sensed: np.ndarray, reference: np.ndarray, valid: np.ndarray, labels: np.ndarray,
                           config: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-region normalised dissimilarity (eq. 12 over the region's colour variance) and valid pixel count.

    ``sensed`` and ``reference`` are aligned (H, W, 3) images; ``valid`` marks pixels the alignment puts
    on the map.  Regions with fewer than ``min_region_px`` valid pixels get NaN.
    """
    cfg = _merge(config)
    S = np.asarray(sensed, np.float64).reshape(-1, 3)
    R = np.asarray(reference, np.float64).reshape(-1, 3)
    lab = np.where(np.asarray(valid, bool).ravel(), np.asarray(labels).ravel(), 0)
    n_reg = int(np.asarray(labels).max())
    d = np.full(n_reg, np.nan)
    cnt = np.bincount(lab, minlength=n_reg + 1)[1:]
    order = np.argsort(lab, kind="stable")
    bounds = np.searchsorted(lab[order], np.arange(1, n_reg + 2))
    for e in range(n_reg):
        if cnt[e] < int(cfg["min_region_px"]):
            continue
        idx = order[bounds[e]:bounds[e + 1]]
        cr, ct = S[idx], R[idx]
        M = fit_colour_map(ct, cr)
        res = cr - (ct @ M[:, :3].T + M[:, 3])
        diss = 0.5 * float((res ** 2).sum(axis=1).mean())                                  # eq. 12
        var = 0.5 * float(((cr - cr.mean(axis=0)) ** 2).sum(axis=1).mean())
        d[e] = diss / (var + float(cfg["variance_floor"]))
    return d, cnt


def domain_dissimilarity(sensed: np.ndarray, reference: np.ndarray, valid: np.ndarray, labels: np.ndarray,
                         config: dict | None = None) -> float:
    """The alignment's dissimilarity: area-weighted mean of the best regions' (module docstring, step 2).

    ``inf`` when the alignment puts less than ``min_valid`` of the image on the map or no region is usable.
    """
    cfg = _merge(config)
    valid = np.asarray(valid, bool)
    if valid.mean() < float(cfg["min_valid"]):
        return float("inf")
    d, cnt = region_dissimilarities(sensed, reference, valid, labels, cfg)
    ok = np.isfinite(d)
    if not ok.any():
        return float("inf")
    d, w = d[ok], cnt[ok].astype(float)
    order = np.argsort(d, kind="stable")
    d, w = d[order], w[order]
    need = float(cfg["keep_fraction"]) * valid.size
    k = int(np.searchsorted(np.cumsum(w), need)) + 1
    return float(np.average(d[:k], weights=w[:k]))


def warp_reference(tile: np.ndarray, to_tile, shape, scale: float, step: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The map under the sensed image: for each pixel of the sensed image scaled by ``scale`` (shape
    ``(h, w)``), the tile's colour where ``to_tile`` puts it (bilinear), and whether that is on the tile.

    ``to_tile`` maps full-resolution sensed pixels to tile pixels; it is evaluated on a grid every ``step``
    work pixels and interpolated bilinearly (the maps fitted here are smooth at that scale: kernels of 40 px
    and more; a KDM map is costly to evaluate densely).  ``tile``
    should already be low-passed for ``scale`` (the sensed image was area-averaged).
    """
    h, w = shape
    gy, gx = np.arange(0, h + step, step, dtype=float), np.arange(0, w + step, step, dtype=float)
    X, Y = np.meshgrid(gx, gy)
    off = (1.0 / scale - 1.0) / 2.0                                   # work pixel -> full-resolution pixel
    full = np.column_stack([X.ravel(), Y.ravel()]) / scale + off
    m = np.asarray(to_tile(full), float).reshape(len(gy), len(gx), 2).astype(np.float32)
    px, py = np.meshgrid(np.arange(w, dtype=np.float32) / step, np.arange(h, dtype=np.float32) / step)
    mx = cv2.remap(m[..., 0], px, py, cv2.INTER_LINEAR)
    my = cv2.remap(m[..., 1], px, py, cv2.INTER_LINEAR)
    H, W = tile.shape[:2]
    valid = (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
    ref = cv2.remap(tile, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return ref, valid
