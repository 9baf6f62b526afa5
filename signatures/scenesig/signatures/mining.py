"""Iterative discriminative clustering of candidate shapes for one place (McManus et al. 2015, §3.2, Fig. 3).

For every candidate shape of the fixed template (:mod:`scenesig.signatures.shapes`):

1. **Partitions.**  The place's images are split into ``n_partitions`` (3) groups, each spanning as
   much appearance as possible: the images are ordered so that similar ones are adjacent (leaf
   order of an average-linkage clustering of a global appearance descriptor -- a 16x12 colour
   thumbnail, i.e. overall brightness, colour and layout) and dealt round-robin, so similar images
   land in different groups and every group mixes conditions.  Group sizes differ by at most one.
2. **Initial positives** are the shape's windows in the images of partition 1, placed by the
   alignment offsets at the shape's *nominal level* -- the finest pyramid level at or below
   ``min_nominal_level`` where the filter has at most ``max_filter_cells`` cells, so large shapes are
   described at coarse scale and every filter is small.
3. **Negatives** are windows of the same size sampled in the same images away from the shape
   (IoU < ``negative_iou`` with its aligned position, drawn with a preference for nearby windows --
   local hard negatives -- and from levels nominal +- ``scale_search``), plus random windows from
   images of other places when given.
4. **Train / fire / retrain.**  A linear SVM (:mod:`scenesig.signatures.classifier`: scikit-learn's libsvm on the precomputed linear kernel,
   which is exact and, with a few hundred samples of a few thousand dimensions, ~10x faster than
   ``LinearSVC``) is trained on partition p and fired on partition p + 1 within
   ``search_radius_px`` of the aligned position, over levels nominal +- ``scale_search``; each image
   contributes its single best window, and the ``top_k`` (5, capped by the partition size) best
   images become partition p + 1's positives.  Partitions are visited cyclically.
5. **Convergence.**  A shape converges when a full cycle leaves every partition's top-K firings
   (image, level, cell position) unchanged; it is rejected if that does not happen within
   ``max_iterations`` (3) cycles -- the paper's criterion -- so the earliest convergence is after two
   cycles (6 train/fire steps) and the latest after three (9).
6. **Survivors** are retrained on the union of all partitions' top-K firings (so the filter has seen
   every appearance) and calibrated (lambda of eq. 5) by Platt scaling on held-out scores:
   leave-one-partition-out classifiers score the left-out partition's top-K (positives) and
   negatives, and a logistic fit maps score to probability.  ``quality`` is the held-out
   separation (20th percentile of positive scores minus 99th of negatives, in negative standard
   deviations).  Finally the bank is detected once in every training image (sub-cell refined):
   the median of a classifier's detections in its converged images, moved back by their
   offsets, is its ``nominal_xy``, and their RMS deviation its ``spread`` -- small for structure
   that moves with the alignment, large for near structure (parallax) or unstable filters.

The work per shape is vectorised: every candidate window of a shape is unrolled once into a matrix
(so each firing is one matrix-vector product), the negative pool's Gram matrix is computed once,
and each SVM fit only adds the rows of the current positives.  Shapes run in parallel with joblib
(``n_jobs``); the HOG pyramids are computed once per image and shared.

``scenesig bench mining IMAGE...`` mines a place from a folder of images.
"""
from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from scenesig.signatures import hog as hogmod
from scenesig.signatures.bank import Bank, Classifier
from scenesig.signatures.classifier import LinearSVMTrainer as _Trainer, platt as _platt
from scenesig.signatures.shapes import ShapeSet, candidate_shapes
from scenesig.surveys.settings import merge_settings
from scenesig.surveys.validation import check_image

__all__ = ["default_config", "resolve_config", "mine_place", "partition_images", "shape_geometry", "MiningStats"]

log = logging.getLogger(__name__)

#: Mining parameters (paper values where the paper gives one).
default_config = {
    # What describes a cell: "hog" (the paper's FHOG), "xfeat" (XFeat's dense descriptors) or
    # "hog+xfeat" (stacked); sets the HOG configuration's ``features`` (signatures.hog.describe_cells)
    "features": "hog",
    "hog": {},                    # overrides of signatures.hog.default_config
    "shapes": None,               # candidate template config (None: signatures.shapes default, 296)
    "max_filter_cells": 80,       # filter area bound that selects each shape's nominal level
    "min_nominal_level": 1,       # finest nominal level; >= scale_search keeps level k-1 >= 0
    "scale_search": 1,            # levels searched either side of the nominal one
    "search_radius_px": 24.0,     # firing neighbourhood around the aligned position (input px)
    "n_partitions": 3,            # paper: 3
    "top_k": 5,                   # paper: K = 5 (capped by the partition size)
    "max_iterations": 3,          # paper: reject if not converged within 3 iterations (cycles)
    "converge_tol_cells": 0,      # top-K positions must repeat exactly (0) or within this many cells
    "svm_C": 0.1,                 # SVM regularisation (Doersch et al. use 0.1)
    "balanced": True,             # weight classes inversely to their counts
    "negatives_per_fit": 120,     # local negatives per SVM fit (split over the partition's images)
    "negative_iou": 0.2,          # a negative overlaps the shape's aligned window by less than this
    "negative_locality": 1.5,     # sampling weight 1 / (1 + (d / (this * shape size))^2)
    "external_negatives": 60,     # windows from other places' images per shape (if given)
    "min_texture": 0.0,           # reject shapes whose initial positives have less mean HOG texture
    "max_classifiers": None,      # keep only the best N survivors by held-out quality
    "platt_C": 10.0,              # inverse ridge penalty on the calibration slope
    # Whitened HOG (signatures.whiten; Hariharan et al. 2012): mine on decorrelated features and fold
    # each filter back to raw HOG (radius cells wider on every side).  Off on the paper's path.
    "whiten": False,
    "whiten_radius": 1,           # whitening kernel half-width, cells
    "whiten_reg": 0.1,            # ridge on the background covariance, relative to its mean variance
    "lda_init": False,            # with whiten: the first filter is LDA (mean of the whitened positives)
    # Multi-scale mining: every shape is also mined this many octaves coarser (a filter of about a
    # quarter of the cells per octave, at least min_octave_cells); 0 = the paper's single scale.
    "extra_octaves": 0,
    "min_octave_cells": 6,
}


@dataclass
class MiningStats:
    """What happened to the candidate shapes of one place.

    Attributes
    ----------
    n_shapes : int
    kept : int
        Converged classifiers in the bank (after ``max_classifiers``).
    converged : int
        Shapes that converged (kept + dropped by ``max_classifiers``).
    rejected_not_converged : int
    rejected_no_data : int
        Shapes that fell outside too many images to form partitions.
    rejected_textureless : int
    steps : ndarray
        Train/fire steps run per shape.
    seconds : float
        Wall time of :func:`mine_place` (pyramids included).
    pyramid_seconds : float
    partitions : list of list of int
        Image indices of each partition.
    firings : dict
        shape index -> list of (image, x, y, scale) of the converged positives.
    """

    n_shapes: int
    kept: int
    converged: int
    rejected_not_converged: int
    rejected_no_data: int
    rejected_textureless: int
    steps: np.ndarray
    seconds: float
    pyramid_seconds: float
    partitions: list
    firings: dict

    def as_dict(self) -> dict:
        return {"n_shapes": self.n_shapes, "kept": self.kept, "converged": self.converged,
                "rejected_not_converged": self.rejected_not_converged,
                "rejected_no_data": self.rejected_no_data,
                "rejected_textureless": self.rejected_textureless,
                "mean_steps": float(np.mean(self.steps)) if len(self.steps) else 0.0,
                "seconds": self.seconds, "pyramid_seconds": self.pyramid_seconds,
                "partitions": self.partitions}


def resolve_config(config: dict | None = None) -> dict:
    """Every mining setting, its HOG's included: ``config`` (overrides of :data:`default_config`) resolved."""
    cfg = merge_settings(default_config, config, "mining", open=("hog",))
    hog_given = dict(cfg["hog"] or {})
    if "features" in hog_given and hog_given["features"] != cfg["features"]:
        raise ValueError(f"mining features {cfg['features']!r} and hog features {hog_given['features']!r} "
                         f"disagree: set the cell descriptor once, as mining's 'features'")
    hog_given["features"] = cfg["features"]
    cfg["hog"] = merge_settings(hogmod.default_config, hog_given, "HOG")
    hogmod.feature_dim(cfg["hog"])       # an unknown descriptor fails here, before any work
    if cfg["min_texture"] > 0 and cfg["features"] == "xfeat":
        raise ValueError("min_texture reads FHOG's texture columns, which XFeat cells alone do not have: "
                         "use features 'hog' or 'hog+xfeat'")
    if cfg["whiten"] and cfg["features"] != "hog":
        raise ValueError("whitening uses the packaged HOG background statistics: it needs features 'hog'")
    if cfg["n_partitions"] < 2:
        raise ValueError("n_partitions must be >= 2")
    if cfg["min_nominal_level"] < cfg["scale_search"]:
        raise ValueError("min_nominal_level must be >= scale_search (level k - scale_search >= 0)")
    return cfg


# ---------------------------------------------------------------------------------- partitions


def appearance_descriptor(image: np.ndarray) -> np.ndarray:
    """Global appearance descriptor: a 16x12 thumbnail (colour if available) scaled to [0, 1]."""
    img = np.asarray(image)
    small = cv2.resize(img, (16, 12), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    return small.ravel()


def partition_images(descriptors: np.ndarray, n_partitions: int = 3) -> list[np.ndarray]:
    """Split images into groups that each span as much appearance as possible.

    The images are put in a similarity order -- the leaf order of an average-linkage clustering
    of their descriptors, optimally ordered so that neighbours are similar -- and dealt
    round-robin: each run of ``n_partitions`` similar images is split across the groups, so every
    group receives one image of each appearance cluster (and group sizes differ by at most one).

    Parameters
    ----------
    descriptors : ndarray, shape (n, d)
    n_partitions : int

    Returns
    -------
    list of ndarray
        Sorted image indices per partition.
    """
    from scipy.cluster.hierarchy import leaves_list, linkage, optimal_leaf_ordering
    from scipy.spatial.distance import pdist

    d = np.asarray(descriptors, dtype=float)
    n = len(d)
    if n < n_partitions:
        raise ValueError(f"need at least {n_partitions} images to form {n_partitions} partitions, "
                         f"got {n}")
    if n <= 2:
        order = np.arange(n)
    else:
        dist = pdist(d)
        if not np.any(dist > 0):
            order = np.arange(n)
        else:
            order = leaves_list(optimal_leaf_ordering(linkage(dist, "average"), dist))
    return [np.sort(order[p::n_partitions]).astype(int) for p in range(n_partitions)]


# ---------------------------------------------------------------------------------- geometry


def shape_geometry(box, cfg: dict) -> tuple[int, int, int] | None:
    """Nominal level and filter size (k, fh, fw) of a shape ``(x, y, w, h)``.

    The nominal level is the finest level ``k >= min_nominal_level`` at which the window has at
    most ``max_filter_cells`` cells; None if no level gives a window of at least 1 x 1 cells.
    """
    hc = cfg["hog"]
    cell, spo = int(hc["cell"]), int(hc["scales_per_octave"])
    w, h = float(box[2]), float(box[3])
    for k in range(int(cfg["min_nominal_level"]), int(cfg["min_nominal_level"]) + 8 * spo):
        s = float(hogmod.level_scale(k, spo))
        fw, fh = max(1, round(w * s / cell)), max(1, round(h * s / cell))
        if fw * fh <= cfg["max_filter_cells"]:
            if w * s / cell < 0.75 or h * s / cell < 0.75:
                return None
            return k, fh, fw
    return None


def _window_axes(pyr: hogmod.HogPyramid, k: int, rows, cols, fh: int, fw: int):
    """Centres and box edges in input pixels of cell windows, per column and per row (a window's
    box is separable): ``x, y, x0, x1, y0, y1`` -- x and its edges per column, y per row."""
    sx, sy = pyr.scale_xy(k)
    cell = pyr.cell
    x = (cell * (np.asarray(cols, float) + 0.5 * fw)) / sx - 0.5
    y = (cell * (np.asarray(rows, float) + 0.5 * fh)) / sy - 0.5
    bw, bh = fw * cell / sx, fh * cell / sy
    return x, y, x + 0.5 - bw / 2, x + 0.5 + bw / 2, y + 0.5 - bh / 2, y + 0.5 + bh / 2


def _window_view(feat: np.ndarray, fh: int, fw: int) -> np.ndarray:
    """All fh x fw windows of a (Hc, Wc, 31) level as a strided view of shape (Hc - fh + 1, Wc - fw + 1,
    fh, fw * 31): window (r, c) row by row, each row ``fw`` cells of contiguous memory, so a window
    flattens to the (fh, fw, 31) layout of a filter and copying windows moves whole rows."""
    feat = np.ascontiguousarray(feat)
    t0, t1, t2 = feat.strides
    shape = (feat.shape[0] - fh + 1, feat.shape[1] - fw + 1, fh, fw * feat.shape[2])
    return np.ndarray(shape, feat.dtype, feat, 0, (t0, t1, t0, t2))


def _windows_at(feat: np.ndarray, rows, cols, fh: int, fw: int) -> np.ndarray:
    """Feature vectors (n, fh * fw * D) of the windows with top-left cells (rows, cols)."""
    return _window_view(feat, fh, fw)[np.asarray(rows), np.asarray(cols)].reshape(
        len(rows), fh * fw * feat.shape[2])


# ---------------------------------------------------------------------------------- per shape


@dataclass
class _Place:
    pyramids: list
    offsets: np.ndarray           # (n, 2)
    partitions: list              # list of int arrays
    neg_pyramids: list
    cfg: dict
    seed: int

    @property
    def dim(self) -> int:
        """Length of a cell's descriptor (31 for HOG)."""
        return hogmod.feature_dim(self.cfg["hog"])


def _candidates(pd: _Place, box, k_n: int, fh: int, fw: int):
    """All windows a shape may fire on: per image, levels k_n +- S, cells within the radius.

    Returns ``(xc, meta, centres, nominal, slices)``: the windows' feature vectors (one row each),
    their (image, level, row, col), centres in input pixels, the row of each image's nominal
    window, and each image's row range (an image's windows are contiguous).
    """
    cfg = pd.cfg
    cell = int(cfg["hog"]["cell"])
    S = int(cfg["scale_search"])
    cx, cy = box[0] + 0.5 * box[2] - 0.5, box[1] + 0.5 * box[3] - 0.5
    ranges, nominal, slices = [], {}, {}
    start = img_start = 0
    for i, pyr in enumerate(pd.pyramids):
        ex, ey = cx + pd.offsets[i, 0], cy + pd.offsets[i, 1]
        for k in range(k_n - S, k_n + S + 1):
            feat = pyr.levels.get(k)
            if feat is None:
                continue
            hc, wc = feat.shape[:2]
            rf, cf = pyr.cell_at(k, ex, ey, fh, fw)
            rc, cc = int(round(rf)), int(round(cf))
            # Shapes touching the image border can land up to one cell outside the feature map
            # (the map drops the partial last cell): pull them back in.
            if -1 <= rc < 0 or hc - fh < rc <= hc - fh + 1:
                rc = min(max(rc, 0), hc - fh)
            if -1 <= cc < 0 or wc - fw < cc <= wc - fw + 1:
                cc = min(max(cc, 0), wc - fw)
            rad = max(1, int(math.ceil(cfg["search_radius_px"] * pyr.scale(k) / cell)))
            r0, r1 = max(0, rc - rad), min(hc - fh, rc + rad)
            c0, c1 = max(0, cc - rad), min(wc - fw, cc + rad)
            if r1 < r0 or c1 < c0:
                continue
            if k == k_n and r0 <= rc <= r1 and c0 <= cc <= c1:
                nominal[i] = start + (rc - r0) * (c1 - c0 + 1) + (cc - c0)
            ranges.append((i, k, r0, r1, c0, c1))
            start += (r1 - r0 + 1) * (c1 - c0 + 1)
        if start > img_start:
            slices[i] = (img_start, start)
        img_start = start
    if not ranges:
        return None
    # One allocation, filled window row by window row (the windows overlap: unrolling is a copy).
    xc = np.empty((start, fh * fw * pd.dim), np.float32)
    meta = np.empty((start, 4), np.int64)
    centres = np.empty((start, 2))
    o = 0
    for i, k, r0, r1, c0, c1 in ranges:
        pyr = pd.pyramids[i]
        nr, nc = r1 - r0 + 1, c1 - c0 + 1
        m = nr * nc
        xc[o:o + m].reshape(nr, nc, fh, -1)[...] = _window_view(pyr.levels[k], fh, fw)[r0:r1 + 1, c0:c1 + 1]
        rows, cols = np.arange(r0, r1 + 1), np.arange(c0, c1 + 1)
        meta[o:o + m, 0], meta[o:o + m, 1] = i, k
        meta[o:o + m, 2] = np.repeat(rows, nc)
        meta[o:o + m, 3] = np.tile(cols, nr)
        x, y = _window_axes(pyr, k, rows, cols, fh, fw)[:2]
        centres[o:o + m, 0] = np.tile(x, nr)
        centres[o:o + m, 1] = np.repeat(y, nc)
        o += m
    return xc, meta, centres, nominal, slices


def _negatives(pd: _Place, box, k_n, fh, fw, n_per_image, rng):
    """Local negatives (rows, owning image) and external negatives of one shape."""
    cfg = pd.cfg
    S = int(cfg["scale_search"])
    size = cfg["negative_locality"] * max(box[2], box[3])
    thr = float(cfg["negative_iou"])
    size2 = size ** 2
    feats, owner = [], []
    grids = {}   # (level, level shape, level size) -> per-column and per-row window geometry
    for i, pyr in enumerate(pd.pyramids):
        ex = box[0] + pd.offsets[i, 0]
        ey = box[1] + pd.offsets[i, 1]
        ref = (ex, ey, ex + box[2], ey + box[3])
        ref_area = (ref[2] - ref[0]) * (ref[3] - ref[1])
        gx, gy = ex + 0.5 * box[2], ey + 0.5 * box[3]
        parts = []
        for k in range(k_n - S, k_n + S + 1):
            feat = pyr.levels.get(k)
            if feat is None or feat.shape[0] < fh or feat.shape[1] < fw:
                continue
            key = (k, feat.shape[:2], pyr.sizes[k])
            g = grids.get(key)
            if g is None:
                g = grids[key] = _window_axes(pyr, k, np.arange(feat.shape[0] - fh + 1),
                                              np.arange(feat.shape[1] - fw + 1), fh, fw)
            x, y, bx0, bx1, by0, by1 = g
            # A window's box, centre and overlap with the shape's aligned box are separable in
            # its row and column: IoU and squared distance are built on the grid from per-row and
            # per-column terms (the same floating-point operations per window as the per-window
            # formulas), and the IoU only where the overlap is not zero.
            ok = np.ones((len(y), len(x)), bool)
            ix = np.maximum(np.minimum(bx1, ref[2]) - np.maximum(bx0, ref[0]), 0.0)
            iy = np.maximum(np.minimum(by1, ref[3]) - np.maximum(by0, ref[1]), 0.0)
            cs, rs = np.flatnonzero(ix > 0), np.flatnonzero(iy > 0)
            if len(cs) and len(rs):
                # Windows are ordered along each axis, so those overlapping the box form a block.
                cs, rs = slice(cs[0], cs[-1] + 1), slice(rs[0], rs[-1] + 1)
                inter = ix[cs][None, :] * iy[rs][:, None]
                union = (bx1[cs] - bx0[cs])[None, :] * (by1[rs] - by0[rs])[:, None] + ref_area - inter
                ok[rs, cs] = inter / np.maximum(union, 1e-12) < thr
            flat = np.flatnonzero(ok)
            d2 = ((x - gx) ** 2)[None, :] + ((y - gy) ** 2)[:, None]
            parts.append((k, len(x), flat, 1.0 / (1.0 + d2.ravel()[flat] / size2)))
        tot = sum(len(c[2]) for c in parts)
        if tot == 0:
            continue
        wall = np.concatenate([c[3] for c in parts])
        pick = _weighted_sample(rng, wall / wall.sum(), min(n_per_image, tot))
        # The picked windows, level by level (in the order of the levels, each in pick order).
        ends = np.cumsum([len(c[2]) for c in parts])
        lv = np.searchsorted(ends, pick, side="right")
        for j in np.unique(lv):
            k, nc, flat, _ = parts[j]
            sel = flat[pick[lv == j] - (ends[j] - len(flat))]
            feats.append(_windows_at(pyr.levels[k], sel // nc, sel % nc, fh, fw))
            owner.append(np.full(len(sel), i))
    ext = []
    if pd.neg_pyramids and cfg["external_negatives"] > 0:
        n_ext = int(cfg["external_negatives"])
        per = np.bincount(rng.integers(0, len(pd.neg_pyramids), n_ext),
                          minlength=len(pd.neg_pyramids))
        for pyr, m in zip(pd.neg_pyramids, per):
            ks = [k for k in range(k_n - S, k_n + S + 1) if k in pyr.levels
                  and pyr.levels[k].shape[0] >= fh and pyr.levels[k].shape[1] >= fw]
            if m == 0 or not ks:
                continue
            kk = rng.choice(ks, size=m)
            for k in np.unique(kk):
                feat = pyr.levels[int(k)]
                cnt = int(np.sum(kk == k))
                rr = rng.integers(0, feat.shape[0] - fh + 1, cnt)
                cc = rng.integers(0, feat.shape[1] - fw + 1, cnt)
                ext.append(_windows_at(feat, rr, cc, fh, fw))
    D = fh * fw * pd.dim
    local = np.concatenate(feats) if feats else np.zeros((0, D), np.float32)
    owner = np.concatenate(owner) if owner else np.zeros(0, int)
    extx = np.concatenate(ext) if ext else np.zeros((0, D), np.float32)
    return local, owner, extx


def _weighted_sample(rng: np.random.Generator, p: np.ndarray, size: int) -> np.ndarray:
    """``rng.choice(len(p), size, replace=False, p=p)`` for positive weights summing to 1.

    The sampler of numpy's ``Generator.choice`` (numpy 2.x: draw uniforms, invert the cumulative
    weights, keep first occurrences, zero the drawn weights and repeat for the rest), without its
    argument checks -- a Kahan sum and three passes over ``p`` that cost more than the sampling for
    the ~10^4 windows per image of a negative draw; the same draws from the same generator state.
    ``p`` is overwritten.
    """
    found = np.zeros(size, dtype=np.int64)
    n_uniq = 0
    while n_uniq < size:
        x = rng.random((size - n_uniq,))
        if n_uniq > 0:
            p[found[:n_uniq]] = 0
        cdf = np.cumsum(p)
        cdf /= cdf[-1]
        new = cdf.searchsorted(x, side="right")
        _, first = np.unique(new, return_index=True)
        first.sort()
        new = new.take(first)
        found[n_uniq:n_uniq + new.size] = new
        n_uniq += new.size
    return found


def _fire(xc: np.ndarray, slices: dict, images, w: np.ndarray, b: float, top_k: int):
    """Best window per image of a partition, then the ``top_k`` best images: (rows of xc, scores)."""
    best = []
    for i in images:
        a, e = slices[i]
        sc = xc[a:e] @ w + b
        j = int(np.argmax(sc))
        best.append((float(sc[j]), a + j))
    best.sort(key=lambda t: -t[0])
    keep = best[:min(top_k, len(best))]
    return np.array([t[1] for t in keep], dtype=int), np.array([t[0] for t in keep])


def _same(a: np.ndarray, b: np.ndarray, tol: int) -> bool:
    """Do two top-K firing sets (rows image, level, row, col) agree?"""
    if a is None or b is None or len(a) != len(b):
        return False
    a = a[np.lexsort(a.T[::-1])]
    b = b[np.lexsort(b.T[::-1])]
    if tol <= 0:
        return bool(np.array_equal(a, b))
    return bool(np.array_equal(a[:, :2], b[:, :2])
                and np.all(np.abs(a[:, 2:] - b[:, 2:]) <= tol))


def _octave_geometry(box, cfg: dict, octave: int):
    """(k, fh, fw) of a shape ``octave`` octaves coarser than its nominal level, or None when the
    filter would have fewer than ``min_octave_cells`` cells."""
    geo = shape_geometry(box, cfg)
    if geo is None or octave == 0:
        return geo
    hc = cfg["hog"]
    spo, cell = int(hc["scales_per_octave"]), int(hc["cell"])
    k = geo[0] + octave * spo
    s = float(hogmod.level_scale(k, spo))
    fw, fh = round(float(box[2]) * s / cell), round(float(box[3]) * s / cell)
    if fw < 1 or fh < 1 or fw * fh < int(cfg["min_octave_cells"]):
        return None
    return k, fh, fw


def _mine_shape(pd: _Place, s_idx: int, box, kind: str, octave: int = 0):
    """Run the iterative clustering for one shape; returns (status, classifier | None, info)."""
    cfg = pd.cfg
    geo = _octave_geometry(box, cfg, octave)
    if geo is None:
        return "no_data", None, {"steps": 0}
    k_n, fh, fw = geo
    cands = _candidates(pd, box, k_n, fh, fw)
    if cands is None:
        return "no_data", None, {"steps": 0}
    xc, meta, centres, nominal, slices = cands
    P = len(pd.partitions)
    part_imgs = [[int(i) for i in p if int(i) in slices] for p in pd.partitions]
    init = [nominal[i] for i in part_imgs[0] if i in nominal]
    if len(init) < 2 or any(len(p) < 1 for p in part_imgs):
        return "no_data", None, {"steps": 0}
    if cfg["min_texture"] > 0:
        # FHOG's texture columns (27-30; first in a stacked cell)
        tex = xc[init].reshape(len(init), fh * fw, -1)[:, :, 27:hogmod.FEATURE_DIM].mean()
        if tex < cfg["min_texture"]:
            return "textureless", None, {"steps": 0}
    rng = np.random.default_rng([pd.seed, s_idx])
    min_part = min(len(p) for p in part_imgs)
    n_per_image = int(math.ceil(cfg["negatives_per_fit"] / max(1, min_part)))
    xneg, owner, xext = _negatives(pd, box, k_n, fh, fw, n_per_image, rng)
    xall_neg = np.concatenate([xneg, xext]) if len(xext) else xneg
    if len(xall_neg) < 2:
        return "no_data", None, {"steps": 0}
    ext_idx = np.arange(len(xneg), len(xall_neg))
    neg_of = [np.concatenate([np.flatnonzero(np.isin(owner, p)), ext_idx]) for p in part_imgs]
    if any(len(n) == 0 for n in neg_of):
        return "no_data", None, {"steps": 0}
    trainer = _Trainer(xc, xall_neg, float(cfg["svm_C"]), bool(cfg["balanced"]))
    K = int(cfg["top_k"])
    tol = int(cfg["converge_tol_cells"])

    pos = [None] * P
    prev = [None] * P
    pos[0] = np.array(init, dtype=int)
    streak, steps, converged = 0, 0, False
    max_steps = int(cfg["max_iterations"]) * P
    for t in range(max_steps):
        p, q = t % P, (t + 1) % P
        if t == 0 and cfg["whiten"] and cfg["lda_init"]:
            # LDA in whitened space (Hariharan et al. 2012): the positives' mean against the
            # background's, which whitening has moved to zero; only its firing ranking is used.
            w, b = xc[pos[p]].mean(axis=0).astype(np.float64), 0.0
        else:
            w, b = trainer.fit(pos[p], neg_of[p])
        idx, _ = _fire(xc, slices, part_imgs[q], w, b, K)
        steps += 1
        top = meta[idx]
        # streak = consecutive steps whose partition kept its previous top-K; a full cycle of
        # them (P) is convergence.
        streak = streak + 1 if _same(prev[q], top, tol) else 0
        prev[q], pos[q] = top, idx
        if streak >= P:
            converged = True
            break
        if streak + (max_steps - steps) < P:
            break          # cannot complete an unchanged cycle in the steps left: reject now
    if not converged:
        return "not_converged", None, {"steps": steps}

    # Final classifier: all partitions' top-K firings; calibration from leave-one-partition-out.
    all_pos = np.unique(np.concatenate(pos))
    all_neg = np.arange(len(xall_neg))
    w, b = trainer.fit(all_pos, all_neg)
    h_scores, h_labels = [], []
    for q in range(P):
        others = [r for r in range(P) if r != q]
        pq = np.unique(np.concatenate([pos[r] for r in others]))
        nq = np.unique(np.concatenate([neg_of[r] for r in others]))
        wq, bq = trainer.fit(pq, nq)
        held_neg = np.flatnonzero(np.isin(owner, part_imgs[q]))
        h_scores += [xc[pos[q]] @ wq + bq, xneg[held_neg] @ wq + bq]
        h_labels += [np.ones(len(pos[q])), np.zeros(len(held_neg))]
    hs, hl = np.concatenate(h_scores), np.concatenate(h_labels)
    calib = _platt(hs, hl, float(cfg["platt_C"]))
    pos_s, neg_s = hs[hl == 1], hs[hl == 0]
    quality = float((np.percentile(pos_s, 20) - np.percentile(neg_s, 99))
                    / (np.std(neg_s) + 1e-6)) if len(neg_s) else float("nan")
    # Nominal position (refined later by _refine_nominal): firings moved back into the reference
    # image by their offsets.
    pm = meta[all_pos]
    ref_xy = centres[all_pos] - pd.offsets[pm[:, 0]]
    scales = np.array([pd.pyramids[int(i)].scale(int(k)) for i, k in pm[:, :2]])
    nominal = np.median(ref_xy, axis=0)
    clf = Classifier(
        weights=w.reshape(fh, fw, pd.dim), bias=b, level=k_n,
        box=tuple(float(v) for v in box),
        nominal_xy=(float(nominal[0]), float(nominal[1])),
        nominal_scale=float(np.median(scales)), calibration=calib, hog=dict(cfg["hog"]),
        shape_index=int(s_idx), kind=kind, quality=quality)
    firings = [(int(i), float(x), float(y), float(s)) for (i, _, _, _), (x, y), s
               in zip(pm, centres[all_pos], scales)]
    return "converged", clf, {"steps": steps, "firings": firings,
                              "images": sorted({int(i) for i in pm[:, 0]})}


def _refine_nominal(classifiers, pyramids, offsets, cfg, images_of) -> None:
    """Sub-cell nominal position and spread of each classifier from its final filter.

    The final (all-partition) filter is detected in every training image within the search radius
    of its aligned position (one bank pass per image, parabolic sub-cell refinement); over the
    images of its converged firings, ``nominal_xy`` becomes the median of the detections moved
    back by the image offsets and ``spread`` their RMS deviation per axis.
    """
    bank = Bank(classifiers)
    nom = np.array([c.nominal_xy for c in classifiers])
    pad = float(cfg["search_radius_px"]) + 2.0 * int(cfg["hog"]["cell"])
    xy = np.full((len(pyramids), len(classifiers), 2), np.nan)
    for i, pyr in enumerate(pyramids):
        ctr = nom + offsets[i]
        win = np.concatenate([ctr - pad, ctr + pad], axis=1)
        det = bank.detect(pyr, windows=win,
                          config={"scale_search": int(cfg["scale_search"])})
        xy[i, :, 0] = det.x[:, 0] - offsets[i, 0]
        xy[i, :, 1] = det.y[:, 0] - offsets[i, 1]
    for j, c in enumerate(classifiers):
        imgs = images_of[c.shape_index]
        pts = xy[imgs, j]
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) == 0:
            c.spread = (float("nan"), float("nan"))
            continue
        med = np.median(pts, axis=0)
        rms = np.sqrt(np.mean((pts - med) ** 2, axis=0))
        c.nominal_xy = (float(med[0]), float(med[1]))
        c.spread = (float(rms[0]), float(rms[1]))


def _fold_whitening(classifiers, cfg) -> None:
    """Turn filters trained on whitened HOG into equivalent raw-HOG filters (in place): the bank,
    the detector and map files then need nothing new (:func:`scenesig.signatures.whiten.fold_filter`)."""
    from scenesig.signatures.whiten import fold_filter

    for c in classifiers:
        c.weights, c.bias = fold_filter(c.weights, c.bias, int(cfg["whiten_radius"]),
                                        float(cfg["whiten_reg"]))


def _mine_chunk(pd: _Place, items):
    import sklearn
    from threadpoolctl import threadpool_limits
    # Thousands of tiny fits: scikit-learn's per-call input validation would cost more than the
    # solver itself; inputs are built here and known to be finite and well-formed.
    # The matrices of one shape are small: BLAS threads would only spin against each other
    # (10x slower under load); parallelism comes from running shapes in separate processes.
    with warnings.catch_warnings(), threadpool_limits(limits=1, user_api="blas"), \
            sklearn.config_context(skip_parameter_validation=True, assume_finite=True):
        warnings.simplefilter("ignore")   # libsvm iteration-limit warnings on degenerate shapes
        return [(s, *_mine_shape(pd, s, box, kind, o)) for s, box, kind, o in items]


# ---------------------------------------------------------------------------------- API


def _as_image(img, what: str, i: int) -> np.ndarray:
    return check_image(img, f"{what} {i}")


def mine_place(images, offsets=None, config: dict | None = None, negatives=None, n_jobs: int = 1,
               rng: int = 0, pyramids=None, negative_pyramids=None, shapes: ShapeSet | None = None,
               progress: bool = False) -> tuple[Bank, MiningStats]:
    """Mine the scene-signature classifiers of one place.

    Parameters
    ----------
    images : sequence of ndarray
        Training images of the place under different appearance (gray or BGR uint8), all the same
        size; image 0 is the reference frame of the shapes and of ``offsets``.
    offsets : array_like, shape (n, 2), optional
        Approximate alignment: a scene point at (x, y) in image 0 appears near
        (x + dx_i, y + dy_i) in image i (from the INS on surveys; from the training sessions'
        ground truth on GRIEF).  Default zeros.
    config : dict, optional
        Overrides of :data:`default_config`.
    negatives : sequence of ndarray, optional
        Images of other places (negatives only).
    n_jobs : int
        joblib workers over shapes (1: in process).
    rng : int
        Seed; results repeat for equal inputs and seed.
    pyramids, negative_pyramids : list of HogPyramid, optional
        Precomputed pyramids of ``images`` / ``negatives`` (must hold the needed levels); images
        are then only used for the partition descriptor.
    shapes : ShapeSet, optional
        Candidate shapes (default: :func:`scenesig.signatures.shapes.candidate_shapes` of the image size).
    progress : bool
        Show a progress bar over shapes.

    Returns
    -------
    bank : Bank
        The converged classifiers (best first by quality if ``max_classifiers`` is set).
    stats : MiningStats
    """
    t0 = time.perf_counter()
    cfg = resolve_config(config)
    images = [_as_image(im, "image", i) for i, im in enumerate(images)]
    n = len(images)
    P = int(cfg["n_partitions"])
    if n < P:
        raise ValueError(f"mining needs at least {P} images of the place (one per partition), "
                         f"got {n}")
    size = images[0].shape[1], images[0].shape[0]
    for i, im in enumerate(images):
        if (im.shape[1], im.shape[0]) != size:
            raise ValueError(f"image {i} is {im.shape[1]}x{im.shape[0]}, image 0 is "
                             f"{size[0]}x{size[1]}; all training images must have one size")
    offs = np.zeros((n, 2)) if offsets is None else np.asarray(offsets, dtype=float)
    if offs.shape != (n, 2) or not np.all(np.isfinite(offs)):
        raise ValueError(f"offsets must be a finite ({n}, 2) array, got shape {offs.shape}")
    shapes = shapes if shapes is not None else candidate_shapes(*size, cfg["shapes"])
    octaves = range(int(cfg["extra_octaves"]) + 1)
    geos = [_octave_geometry(b, cfg, o) for o in octaves for b in shapes.boxes]
    S = int(cfg["scale_search"])
    need = sorted({k for g in geos if g is not None for k in range(g[0] - S, g[0] + S + 1)})
    tp = time.perf_counter()
    if pyramids is None:
        pyramids = [hogmod.build_pyramid(im, cfg["hog"], levels=need) for im in images]
    negatives = list(negatives or [])
    if negative_pyramids is None:
        negative_pyramids = [hogmod.build_pyramid(_as_image(im, "negative", i), cfg["hog"],
                                                  levels=need) for i, im in enumerate(negatives)]
    for what, pyrs in (("image", pyramids), ("negative", negative_pyramids)):
        for i, pyr in enumerate(pyrs):
            if not pyr.matches(cfg["hog"]):
                raise ValueError(f"{what} pyramid {i} was built with other HOG parameters")
    if len(pyramids) != n:
        raise ValueError(f"got {len(pyramids)} pyramids for {n} images")
    if cfg["whiten"]:
        from scenesig.signatures.whiten import whiten_pyramid
        wr, wg = int(cfg["whiten_radius"]), float(cfg["whiten_reg"])
        pyramids = [whiten_pyramid(p, wr, wg) for p in pyramids]
        negative_pyramids = [whiten_pyramid(p, wr, wg) for p in negative_pyramids]
    t_pyr = time.perf_counter() - tp
    parts = partition_images(np.stack([appearance_descriptor(im) for im in images]), P)
    pd = _Place(pyramids, offs, parts, list(negative_pyramids), cfg, int(rng))
    # item o * n + i: shape i at octave o (octave 0 alone: the paper's items, indices and seeds)
    n_s = len(shapes)
    items = [(o * n_s + i, tuple(shapes.boxes[i]), shapes.kind_name(i), o)
             for o in octaves for i in range(n_s)]
    if n_jobs == 1:
        it = items
        if progress:
            from tqdm import tqdm
            it = tqdm(items, desc="mining shapes", unit="shape")
        results = _mine_chunk(pd, it)
    else:
        from joblib import Parallel, delayed, effective_n_jobs
        nj = effective_n_jobs(n_jobs)
        chunks = [items[j::nj * 4] for j in range(nj * 4)]
        out = Parallel(n_jobs=nj)(delayed(_mine_chunk)(pd, ch) for ch in chunks if ch)
        results = sorted((r for o in out for r in o), key=lambda r: r[0])
    classifiers = [r[2] for r in results if r[1] == "converged"]
    converged = len(classifiers)
    if cfg["max_classifiers"] is not None and len(classifiers) > cfg["max_classifiers"]:
        order = np.argsort([-c.quality for c in classifiers], kind="stable")
        classifiers = [classifiers[i] for i in sorted(order[:int(cfg["max_classifiers"])])]
    if classifiers:
        from threadpoolctl import threadpool_limits
        with threadpool_limits(limits=1, user_api="blas"):   # many small multiplies
            _refine_nominal(classifiers, pyramids, offs, cfg,
                            {r[0]: r[3]["images"] for r in results if r[1] == "converged"})
        if cfg["whiten"]:
            _fold_whitening(classifiers, cfg)
    status = [r[1] for r in results]
    stats = MiningStats(
        n_shapes=len(items), kept=len(classifiers), converged=converged,
        rejected_not_converged=status.count("not_converged"),
        rejected_no_data=status.count("no_data"), rejected_textureless=status.count("textureless"),
        steps=np.array([r[3]["steps"] for r in results]), seconds=time.perf_counter() - t0,
        pyramid_seconds=t_pyr, partitions=[p.tolist() for p in parts],
        firings={r[0]: r[3]["firings"] for r in results if r[1] == "converged"})
    bank = Bank(classifiers, image_size=size)
    if hogmod.learned(cfg["hog"]):
        # which network described the cells: detection refuses another (detection.check_cell_model)
        from scenesig.signatures.xfeat import get_xfeat
        bank.meta["xfeat_sha256"] = get_xfeat().sha256
    return bank, stats
