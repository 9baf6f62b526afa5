"""Point-feature baselines: OpenCV ORB / SIFT extraction, descriptor matching, displacement voting.

The heading benchmark (GRIEF protocol, Krajník et al. RAS 2017) and the point-feature localiser
both use these pieces, so each stage is its own function:

1. :func:`extract` -- detect, keep the ``n_features`` strongest keypoints by detector response,
   optionally make them *upright* (orientation forced to 0 before the descriptor is computed, as
   the GRIEF protocol does: a ground robot's camera does not roll, so rotation invariance only
   costs distinctiveness).  :class:`FeatureCache` keeps extractions by image content, so jobs that
   see the same images with the same settings (the ``sift`` and ``sift-all`` baselines replaying one
   run) extract each image once; :func:`feature_cache` opens such a cache for a block of code.
2. :func:`match` -- brute-force 2-NN matching with one of four filters: Lowe's ratio test,
   the DAPC adaptive-distance test (Zhang et al., "Multi-Modal Scene Matching Location Algorithm
   Based on M2Det", CMC 2023, eq. 6-7: keep a match when ``d1 < d2 - mean(d2 - d1)``), grid-based
   motion statistics (:func:`gms_filter`; Bian et al. CVPR 2017), or none; optionally mutual
   (cross-checked) nearest neighbours, and optionally guided (a mask of the pairs allowed).
3. :func:`histogram_displacement` -- histogram voting of the matches' horizontal offsets: the most
   populated 20-px bin wins and the estimate is the mean offset inside it (as the GRIEF evaluation
   code does).  ``voting="fixed"`` uses a grid of bins aligned at 0 (the plain reading of
   "20-px bins"); ``voting="sliding"`` slides the bin over all positions, which is what GRIEF's
   ``match_all`` does (it tries the 20 one-pixel shifts of the grid) and avoids splitting a peak
   that straddles a bin edge.
"""
from __future__ import annotations

import hashlib
import json
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field

import cv2
import numpy as np

from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "PointFeatures", "Matches", "Vote", "extract", "match", "gms_filter",
           "gms_default_config",
           "histogram_displacement", "estimate_displacement", "FEATURE_KINDS", "MATCH_FILTERS", "FeatureCache",
           "feature_cache", "active_feature_cache"]

FEATURE_KINDS = ("orb", "sift", "rootsift", "xfeat")
MATCH_FILTERS = ("ratio", "dapc", "gms", "none", "cossim")

#: Grid-based motion statistics (Bian et al., "GMS: Grid-based Motion Statistics for Fast,
#: Ultra-robust Feature Correspondence", CVPR 2017), the settings of the authors' code.
gms_default_config = {
    # cells per image side; "auto": sqrt(matches / 20) within [4, 20] -- the authors' 20 x 20 holds
    # ~25 matches a cell with their 10000 features; a few hundred matches need coarser cells
    "grid": "auto",
    "alpha": 6.0,          # threshold tau = alpha * sqrt(mean matches per cell of the 3x3 block)
}

#: Defaults = the published GRIEF protocol (1600 upright features, ratio 0.9, 20-px bins).
default_config = {
    "n_features": 1600,
    "upright": True,
    # ORB(1600, 1.2, 8, 31, 0, 2, HARRIS, 31) as in GRIEF's match_all; fastThreshold is OpenCV's.
    "orb": {"scaleFactor": 1.2, "nlevels": 8, "edgeThreshold": 31, "firstLevel": 0, "WTA_K": 2,
            "patchSize": 31, "fastThreshold": 20},
    # SIFT(0, 3, contrastThreshold, 10, 1.6).  GRIEF used contrast 0 and then kept the strongest
    # 1600; OpenCV's default 0.04 leaves fewer than 1600 on low-contrast (snow) images.
    "sift": {"nOctaveLayers": 3, "contrastThreshold": 0.04, "edgeThreshold": 10, "sigma": 1.6},
    "match": {"filter": "ratio", "ratio": 0.9, "mutual": False, "min_cossim": 0.82},
    "vote": {"bin_px": 20.0, "voting": "sliding", "estimate": "mean", "origin": 0.0,
             "max_dy": None},
    # SIFT emits one keypoint per orientation peak; once upright they are identical, so their
    # descriptors are each other's nearest neighbours and fail every ratio test.  Dropping the
    # copies before choosing the N strongest keeps N distinct features.
    "dedupe": True,
    # XFeat (learned, :mod:`scenesig.signatures.xfeat`): overrides of signatures.xfeat.default_config (model file,
    # tiling); its keypoint count is ``n_features`` (upstream's top-k)
    "xfeat": {},
}


@dataclass
class PointFeatures:
    """Keypoints and descriptors of one image.

    Attributes
    ----------
    kind : str
        ``"orb"``, ``"sift"``, ``"rootsift"`` or ``"xfeat"``.
    xy : ndarray, shape (N, 2), float32
        Keypoint positions, pixels (x right, y down).
    response, size, angle : ndarray, shape (N,)
        Detector response (strongest first), diameter in px, orientation in degrees (0 if upright).
    octave : ndarray, shape (N,), int
        OpenCV's packed octave field (needed to recompute descriptors).
    descriptors : ndarray, shape (N, D)
        uint8 (ORB, compared with Hamming distance) or float32 (SIFT, L2; XFeat, unit length).
    image_shape : tuple
        (height, width) of the source image.
    """

    kind: str
    xy: np.ndarray
    response: np.ndarray
    size: np.ndarray
    angle: np.ndarray
    octave: np.ndarray
    descriptors: np.ndarray
    image_shape: tuple = field(default=(0, 0))

    def __len__(self) -> int:
        return len(self.xy)

    @property
    def norm(self) -> int:
        """OpenCV norm for this descriptor type."""
        return cv2.NORM_HAMMING if self.kind == "orb" else cv2.NORM_L2

    def keypoints(self) -> list[cv2.KeyPoint]:
        """The keypoints as ``cv2.KeyPoint`` objects (for drawing or recomputing)."""
        return [cv2.KeyPoint(float(x), float(y), float(s), float(a), float(r), int(o))
                for (x, y), s, a, r, o in zip(self.xy, self.size, self.angle, self.response,
                                              self.octave)]

    def subset(self, index) -> "PointFeatures":
        """Features selected by a boolean mask or index array."""
        return PointFeatures(self.kind, self.xy[index], self.response[index], self.size[index],
                             self.angle[index], self.octave[index], self.descriptors[index],
                             self.image_shape)


@dataclass
class Matches:
    """Putative correspondences from features ``a`` (query) to ``b`` (train).

    Attributes
    ----------
    query, train : ndarray, shape (M,), int
        Indices into a and b.
    distance : ndarray, shape (M,)
        Descriptor distance to the nearest neighbour.
    second : ndarray, shape (M,)
        Distance to the second-nearest neighbour (inf when b had a single feature).
    """

    query: np.ndarray
    train: np.ndarray
    distance: np.ndarray
    second: np.ndarray

    def __len__(self) -> int:
        return len(self.query)

    def subset(self, index) -> "Matches":
        return Matches(self.query[index], self.train[index], self.distance[index],
                       self.second[index])


@dataclass
class Vote:
    """Outcome of histogram voting.

    Attributes
    ----------
    displacement : float
        Estimated horizontal displacement b - a, pixels (NaN when nothing voted).
    support : int
        Votes in the winning bin.
    n_votes : int
        Matches that voted (after the optional vertical gate).
    inliers : ndarray of bool, shape (M,)
        Matches in the winning bin.
    bin : tuple of float
        [low, high) offset range of the winning bin.
    """

    displacement: float
    support: int
    n_votes: int
    inliers: np.ndarray
    bin: tuple = (np.nan, np.nan)


def _as_gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {image.dtype}")
    return image


def _make(kind: str, config: dict):
    if kind == "orb":
        # nfeatures bounds what the detector keeps per pyramid level; we re-sort by response below.
        return cv2.ORB_create(nfeatures=config["n_features"], **config["orb"])
    if kind in ("sift", "rootsift"):
        # nfeatures=0: keep all, so that the N strongest are chosen *after* removing the
        # duplicate keypoints SIFT makes for secondary orientations (identical once upright).
        return cv2.SIFT_create(nfeatures=0, **config["sift"])
    raise ValueError(f"unknown feature kind {kind!r}; choose from {FEATURE_KINDS}")


def _merge(config: dict | None) -> dict:
    return merge_settings(default_config, config, "point-feature", open=("xfeat",))


def _extract_xfeat(image: np.ndarray, n: int, config: dict) -> PointFeatures:
    """XFeat keypoints (:mod:`scenesig.signatures.xfeat`): the ``n`` best by score (upstream's top-k)."""
    from scenesig.signatures.xfeat import get_xfeat

    xy, score, desc = get_xfeat(config["xfeat"]).detect_and_compute(image, top_k=n if n > 0 else 1 << 30)
    k = len(xy)
    return PointFeatures("xfeat", xy, score, np.full(k, 8.0, np.float32), np.zeros(k, np.float32),
                         np.zeros(k, np.int64), np.ascontiguousarray(desc), tuple(np.shape(image)[:2]))


def extract(image: np.ndarray, kind: str = "orb", n_features: int | None = None,
            upright: bool | None = None, config: dict | None = None) -> PointFeatures:
    """Detect keypoints, keep the strongest, compute (upright) descriptors.

    Parameters
    ----------
    image : ndarray
        uint8 gray or BGR image.
    kind : {"orb", "sift", "rootsift", "xfeat"}
        Detector + descriptor.  ``rootsift`` = SIFT with the Hellinger (L1-normalised square
        root) mapping of Arandjelović & Zisserman; ``xfeat`` = the learned XFeat features
        (:mod:`scenesig.signatures.xfeat`; ``upright`` does not apply).
    n_features : int, optional
        Keep this many strongest keypoints (by detector response); default 1600.
    upright : bool, optional
        Force every orientation to 0 before describing (default True).
    config : dict, optional
        Overrides of :data:`default_config` (e.g. ``{"sift": {"contrastThreshold": 0.0}}``).

    Returns
    -------
    PointFeatures
        Sorted by decreasing response.
    """
    cfg = _merge(config)
    if n_features is not None:
        cfg["n_features"] = int(n_features)
    if upright is not None:
        cfg["upright"] = bool(upright)
    n = cfg["n_features"]
    if kind == "xfeat":
        return _extract_xfeat(image, n, cfg)
    gray = _as_gray(image)
    algo = _make(kind, cfg)
    kps = algo.detect(gray, None)
    if cfg["upright"] and cfg["dedupe"]:
        kps = _dedupe(kps)
    kps = sorted(kps, key=lambda k: -k.response)[:n] if n > 0 else list(kps)
    if cfg["upright"]:
        for k in kps:
            k.angle = 0.0
    kps, desc = algo.compute(gray, kps)
    if desc is None or len(kps) == 0:
        dim, dtype = (32, np.uint8) if kind == "orb" else (128, np.float32)
        desc, kps = np.zeros((0, dim), dtype), []
    if len(kps):
        # ORB's compute() regroups keypoints by pyramid level and drops those near the border:
        # restore strongest-first order so callers may take prefixes.
        order = np.argsort([-k.response for k in kps], kind="stable")
        kps = [kps[i] for i in order]
        desc = desc[order]
    if kind == "rootsift" and len(desc):
        desc = np.sqrt(desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)
    return PointFeatures(
        kind=kind,
        xy=np.array([k.pt for k in kps], np.float32).reshape(-1, 2),
        response=np.array([k.response for k in kps], np.float32),
        size=np.array([k.size for k in kps], np.float32),
        angle=np.array([k.angle for k in kps], np.float32),
        octave=np.array([k.octave for k in kps], np.int64),
        descriptors=np.ascontiguousarray(desc),
        image_shape=gray.shape[:2])


class FeatureCache:
    """Extractions (:func:`extract`) kept by image content and settings, for jobs that see the same images.

    The key is a digest of the image's bytes, shape and dtype and the extraction arguments, so a hit
    is exactly what :func:`extract` would return for that image (it is deterministic).  Descriptors
    are stored as uint8 where that is lossless (ORB always; OpenCV's SIFT descriptors are integers
    in 0..255) and handed back in their original dtype; the other arrays are shared read-only.
    Thread-safe: two threads missing the same image both extract it, and one result is kept.

    Parameters
    ----------
    max_items : keep at most this many extractions (least recently used dropped); None: no bound
        (a SIFT extraction of a VGA frame takes about 0.25 MB).
    """

    def __init__(self, max_items: int | None = None):
        from collections import OrderedDict

        self.max_items = None if max_items is None else int(max_items)
        self._items: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._items)

    @staticmethod
    def key(image: np.ndarray, kind: str, n_features, upright, config) -> tuple:
        img = np.ascontiguousarray(image)
        digest = hashlib.blake2b(img.data, digest_size=20)
        digest.update(repr((img.shape, img.dtype.str)).encode())
        settings = json.dumps([kind, n_features, upright, config], sort_keys=True, default=repr)
        return digest.digest(), settings

    def extract(self, image: np.ndarray, kind: str = "orb", n_features: int | None = None,
                upright: bool | None = None, config: dict | None = None) -> PointFeatures:
        """:func:`extract`, or its earlier result for the same image and arguments."""
        key = self.key(image, kind, n_features, upright, config)
        with self._lock:
            packed = self._items.get(key)
            if packed is not None:
                self._items.move_to_end(key)
                self.hits += 1
        if packed is not None:
            return _unpack(packed)
        feats = extract(image, kind, n_features=n_features, upright=upright, config=config)
        packed = _pack(feats)
        with self._lock:
            self.misses += 1
            self._items[key] = packed
            while self.max_items is not None and len(self._items) > self.max_items:
                self._items.popitem(last=False)
        return _unpack(packed)


def _pack(f: PointFeatures) -> tuple:
    """Read-only copies of the arrays; descriptors as uint8 when that loses nothing."""
    arrays = [np.array(a) for a in (f.xy, f.response, f.size, f.angle, f.octave)]
    desc = np.array(f.descriptors)
    dtype = desc.dtype
    if not desc.size or (np.array_equal(desc, np.round(desc)) and desc.min() >= 0 and desc.max() <= 255):
        desc = desc.astype(np.uint8)
    for a in (*arrays, desc):
        a.setflags(write=False)
    return f.kind, arrays, desc, dtype, tuple(f.image_shape)


def _unpack(packed: tuple) -> PointFeatures:
    kind, (xy, response, size, angle, octave), desc, dtype, shape = packed
    desc = desc if desc.dtype == dtype else np.ascontiguousarray(desc, dtype=dtype)
    return PointFeatures(kind, xy, response, size, angle, octave, desc, shape)


_ACTIVE_CACHE: FeatureCache | None = None


@contextmanager
def feature_cache(cache: FeatureCache | None = None):
    """Within the block, :func:`active_feature_cache` is ``cache`` (a new :class:`FeatureCache` by
    default) in every thread of this process; yields it.

    Code that extracts features of images other code in the block may extract again (the
    point-feature localisers' live features) asks :func:`active_feature_cache` first.  Blocks nest;
    the outer cache is active again after the inner block.
    """
    global _ACTIVE_CACHE
    cache = FeatureCache() if cache is None else cache
    outer, _ACTIVE_CACHE = _ACTIVE_CACHE, cache
    try:
        yield cache
    finally:
        _ACTIVE_CACHE = outer


def active_feature_cache() -> FeatureCache | None:
    """The cache of the innermost :func:`feature_cache` block, or None outside one."""
    return _ACTIVE_CACHE


def _dedupe(kps) -> list:
    """Drop keypoints that differ only in orientation (SIFT emits one per histogram peak)."""
    seen, out = set(), []
    for k in kps:
        key = (round(k.pt[0], 2), round(k.pt[1], 2), round(k.size, 2), k.octave)
        if key not in seen:
            seen.add(key)
            out.append(k)
    return out


def _knn(da: np.ndarray, db: np.ndarray, norm: int, mask: np.ndarray | None = None):
    """2-NN of each row of da among rows of db (only pairs ``mask`` allows): (index1, dist1, dist2)."""
    m = cv2.BFMatcher(norm, crossCheck=False)
    k = min(2, len(db))
    if mask is not None:
        res = m.knnMatch(da, db, k=k, mask=np.ascontiguousarray(mask, dtype=np.uint8))
    else:
        res = m.knnMatch(da, db, k=k)
    idx = np.array([r[0].trainIdx if r else -1 for r in res], np.int64)
    d1 = np.array([r[0].distance if r else np.inf for r in res], np.float64)
    d2 = np.array([r[1].distance if len(r) > 1 else np.inf for r in res], np.float64)
    return idx, d1, d2


def match(a: PointFeatures, b: PointFeatures, filter: str = "ratio", ratio: float = 0.9,
          mutual: bool = False, dapc_over: str = "all", mask: np.ndarray | None = None,
          gms: dict | None = None, min_cossim: float = 0.82) -> Matches:
    """Match descriptors of ``a`` to ``b`` (brute force, 2 nearest neighbours).

    Parameters
    ----------
    a, b : PointFeatures
        Same descriptor kind.
    filter : {"ratio", "dapc", "gms", "none", "cossim"}
        ``ratio``: keep when ``d1 < ratio * d2`` (Lowe).  ``cossim``: unit descriptors (XFeat) kept
        when their cosine similarity ``1 - d1² / 2`` exceeds ``min_cossim`` -- with ``mutual``, XFeat's
        own matcher (Potje et al. 2024; :func:`scenesig.signatures.xfeat.match_mnn`).  ``dapc``: keep when
        ``d1 < d2 - mean(d2 - d1)``, the mean over all of a's 2-NN pairs -- a threshold that adapts
        to how separable this image pair's descriptors are (M2Det scene-matching paper, §3.4, eqs. 6-7).  ``none``: keep
        every nearest neighbour.
    ratio : float
        Ratio for ``filter="ratio"``.
    mutual : bool
        Also require a's feature to be b's feature's nearest neighbour (cross-check).
    dapc_over : {"all", "mutual"}
        Which 2-NN pairs the DAPC mean gap is taken over: all of a's (default), or -- with
        ``mutual`` -- only the mutual pairs, the order of the M2Det scene-matching paper's procedure (§3.4) (bidirectional
        matching first, steps c-e, then the dynamic distance test, step f).
    mask : ndarray of bool, shape (len(a), len(b)), optional
        Pairs allowed to match (guided matching: e.g. b's keypoints near a's predicted projection);
        nearest neighbours, ratios and the mutual check are taken among allowed pairs only.
    gms : dict, optional
        With ``filter="gms"``: overrides of :data:`gms_default_config` (``image_size_a`` and
        ``image_size_b`` default to each side's ``image_shape``).

    Returns
    -------
    Matches
    """
    if a.kind != b.kind:
        raise ValueError(f"cannot match {a.kind} descriptors with {b.kind}")
    if filter not in MATCH_FILTERS:
        raise ValueError(f"unknown match filter {filter!r}; choose from {MATCH_FILTERS}")
    empty = Matches(*(np.zeros(0, t) for t in (np.int64, np.int64, float, float)))
    if len(a) == 0 or len(b) == 0:
        return empty
    if dapc_over not in ("all", "mutual"):
        raise ValueError(f"dapc_over must be 'all' or 'mutual', got {dapc_over!r}")
    if dapc_over == "mutual" and filter == "dapc" and not mutual:
        raise ValueError("dapc_over='mutual' needs mutual=True")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (len(a), len(b)):
            raise ValueError(f"mask must have shape {(len(a), len(b))}, got {mask.shape}")
    if filter == "cossim" and mutual and mask is None:
        # XFeat's matcher on the similarity matrix (one matrix product, as upstream does)
        from scenesig.signatures.xfeat import match_mnn

        ia, ib, s = match_mnn(a.descriptors, b.descriptors, min_cossim)
        dist = np.sqrt(np.clip(2.0 - 2.0 * s.astype(float), 0.0, None))
        return Matches(ia.astype(np.int64), ib.astype(np.int64), dist, np.full(len(ia), np.inf))
    idx, d1, d2 = _knn(a.descriptors, b.descriptors, a.norm, mask)
    keep = idx >= 0
    if mutual:
        back, _, _ = _knn(b.descriptors, a.descriptors, a.norm, None if mask is None else mask.T)
        keep &= back[np.clip(idx, 0, None)] == np.arange(len(a))
    if filter == "ratio":
        keep &= d1 < ratio * d2
    elif filter == "dapc":
        pool = (idx >= 0) if dapc_over == "all" else keep
        finite = np.isfinite(d2) & pool
        gap = float(np.mean(d2[finite] - d1[finite])) if finite.any() else 0.0
        keep &= d1 < d2 - gap
    elif filter == "cossim":
        keep &= (1.0 - 0.5 * d1 ** 2) > min_cossim
    elif filter == "gms":
        gms = dict(gms or {})
        size_a = gms.pop("image_size_a", None) or a.image_shape[::-1]     # call arguments, not settings
        size_b = gms.pop("image_size_b", None) or b.image_shape[::-1]
        cfg = merge_settings(gms_default_config, gms, "GMS")
        q = np.flatnonzero(keep)
        ok = gms_filter(a.xy[q], b.xy[idx[q]], size_a, size_b, **cfg)
        keep[q[~ok]] = False
    q = np.flatnonzero(keep)
    return Matches(q, idx[q], d1[q], d2[q])


def gms_filter(xy_a: np.ndarray, xy_b: np.ndarray, size_a, size_b, grid="auto",
               alpha: float = 6.0) -> np.ndarray:
    """Grid-based motion statistics: which putative matches ``xy_a[i] -> xy_b[i]`` are consistent.

    A true match moves with its neighbours, so the 3x3 block of grid cells around it in image a
    sends many matches to the corresponding block around its cell in image b; a false one has
    little such support (Bian et al. 2017; as Fan et al., "PSiamRML: Target Recognition and Matching
    Integrated Localization Algorithm Based on Pseudo-Siamese Network", §4.2, eqs. 3-7, use it).
    Per cell of a, its matches' most frequent destination cell is the cell pair's motion; a match on that motion is kept when the support
    ``s`` (matches from the 9 neighbouring cells to the 9 cells around the destination, the same
    relative neighbour on each side) exceeds ``tau = alpha * sqrt(n / 9)``, ``n`` the matches
    leaving the 9 cells of a.  As in the authors' code the grid is tried at four half-cell shifts
    and a match kept by any of them is kept.

    Parameters
    ----------
    xy_a, xy_b : (M, 2) matched keypoint positions.
    size_a, size_b : (width, height) of the two images.
    grid : cells per side, or ``"auto"`` (:data:`gms_default_config`).
    alpha : threshold factor.

    Returns
    -------
    ndarray of bool, shape (M,)
    """
    xy_a = np.asarray(xy_a, float).reshape(-1, 2)
    xy_b = np.asarray(xy_b, float).reshape(-1, 2)
    m = len(xy_a)
    keep = np.zeros(m, bool)
    if m == 0:
        return keep
    g = int(np.clip(round(np.sqrt(m / 20.0)), 4, 20)) if grid == "auto" else int(grid)
    off = np.array([[-1, -1], [0, -1], [1, -1], [-1, 0], [0, 0], [1, 0], [-1, 1], [0, 1], [1, 1]])

    def cells(xy, size, shift):
        w, h = float(size[0]), float(size[1])
        c = np.floor((xy / [w, h]) * g + shift).astype(int)
        return np.clip(c, 0, g)            # a shifted grid has g + 1 cells per side

    for shift in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
        gs = g + 1
        ca, cb = cells(xy_a, size_a, shift), cells(xy_b, size_b, shift)
        ia = ca[:, 1] * gs + ca[:, 0]
        ib = cb[:, 1] * gs + cb[:, 0]
        motion = np.zeros((gs * gs, gs * gs), np.int32)
        np.add.at(motion, (ia, ib), 1)
        per_cell = motion.sum(axis=1)
        best = motion.argmax(axis=1)                    # each cell of a's dominant destination
        on_motion = best[ia] == ib
        src = ia[on_motion]
        sa = np.column_stack([src % gs, src // gs])
        da = np.column_stack([best[src] % gs, best[src] // gs])
        support = np.zeros(len(src))
        n = np.zeros(len(src))
        for d in off:
            pa, pb = sa + d, da + d
            ok = (pa >= 0).all(1) & (pa < gs).all(1) & (pb >= 0).all(1) & (pb < gs).all(1)
            fa = np.where(ok, pa[:, 1] * gs + pa[:, 0], 0)
            fb = np.where(ok, pb[:, 1] * gs + pb[:, 0], 0)
            support += np.where(ok, motion[fa, fb], 0)
            n += np.where(ok, per_cell[fa], 0)
        # the match itself is not its own support (eq. 3: s = |x| - 1)
        good = (support - 1) > alpha * np.sqrt(n / 9.0)
        keep[np.flatnonzero(on_motion)[good]] = True
    return keep


def histogram_displacement(dx: np.ndarray, bin_px: float = 20.0, voting: str = "sliding",
                      estimate: str = "mean", origin: float = 0.0,
                      dy: np.ndarray | None = None, max_dy: float | None = None) -> Vote:
    """Histogram voting over horizontal offsets.

    Parameters
    ----------
    dx : ndarray, shape (M,)
        Horizontal offset of each match (x in b minus x in a).
    bin_px : float
        Bin width (20 px in the GRIEF protocol).
    voting : {"fixed", "sliding"}
        ``fixed``: bins ``[origin + k * bin_px, origin + (k + 1) * bin_px)``.  ``sliding``: the
        bin may start anywhere (the best window of width ``bin_px``), the continuous form of
        GRIEF's 20 shifted grids.
    estimate : {"mean", "centre"}
        Mean offset of the winning bin's members (GRIEF) or the bin's centre.
    origin : float
        Bin-grid origin for ``fixed`` (e.g. -1024 for ``np.histogram`` over [-1024, 1024]).
    dy, max_dy : optional
        Vertical offsets and a gate: matches with ``|dy| >= max_dy`` do not vote.

    Returns
    -------
    Vote
        Ties go to the bin with the smaller offset (deterministic).
    """
    dx = np.asarray(dx, float)
    ok = np.isfinite(dx)
    if max_dy is not None and dy is not None:
        ok &= np.abs(np.asarray(dy, float)) < max_dy
    inl = np.zeros(len(dx), bool)
    if not ok.any():
        return Vote(np.nan, 0, 0, inl)
    v = dx[ok]
    if voting == "fixed":
        k = np.floor((v - origin) / bin_px).astype(np.int64)
        ks, counts = np.unique(k, return_counts=True)
        best = ks[np.argmax(counts)]
        lo, hi = origin + best * bin_px, origin + (best + 1) * bin_px
        support = int(counts.max())
    elif voting == "sliding":
        s = np.sort(v)
        # window [s_i, s_i + bin_px): count = first index >= s_i + bin_px minus i
        ends = np.searchsorted(s, s + bin_px, side="left")
        counts = ends - np.arange(len(s))
        i = int(np.argmax(counts))
        lo, hi = s[i], s[i] + bin_px
        support = int(counts[i])
    else:
        raise ValueError(f"unknown voting {voting!r}; choose 'fixed' or 'sliding'")
    if estimate not in ("mean", "centre"):
        raise ValueError(f"unknown estimate {estimate!r}; choose 'mean' or 'centre'")
    member = ok & (dx >= lo) & (dx < hi)
    inl[member] = True
    value = dx[member].mean() if estimate == "mean" else 0.5 * (lo + hi)
    return Vote(float(value), support, int(ok.sum()), inl, (float(lo), float(hi)))


def estimate_displacement(a: PointFeatures, b: PointFeatures,
                          config: dict | None = None) -> tuple[Vote, Matches]:
    """Match ``a`` (map) to ``b`` (live) and vote the horizontal displacement b - a.

    Returns
    -------
    (Vote, Matches)
        ``vote.inliers`` indexes ``matches``.
    """
    cfg = _merge(config)
    m = match(a, b, **cfg["match"])
    dx = b.xy[m.train, 0] - a.xy[m.query, 0]
    dy = b.xy[m.train, 1] - a.xy[m.query, 1]
    vote = histogram_displacement(dx, dy=dy, **cfg["vote"])
    return vote, m
