"""A bank of scene-signature classifiers for one place, and one-pass detection of the whole bank.

A :class:`Classifier` is a linear filter over a window of FHOG cells (McManus et al. 2015, §3.2: one SVM per
scene signature) with the shape it was mined from, its nominal position and scale, and the
score-to-probability calibration lambda of eq. (5).  A :class:`Bank` holds the classifiers of a
place, stores to and from plain arrays (the map store writes that dict), and detects all of them in
one pass over one HOG pyramid.

One-pass detection
------------------
Classifiers that search the same pyramid level and have the same filter width share one matrix
multiply: the level's features are unrolled along x only (each row of the unrolled matrix is
``fw`` consecutive cells, ``fw * 31`` values), multiplied once by the stacked rows of all the
group's filters, and each filter's score map is the sum of its ``fh`` row responses along a
diagonal (a strided view, no copy).  The multiply is most of the scoring cost (BLAS); the
unrolled matrix is ``fw`` times the level size, not ``fw * fh`` times as a full im2col would be.
Search windows restrict the rows and columns that are unrolled, and (:meth:`Bank.pyramid`) the cells
of each level whose features are computed at all.

Given an image, :meth:`Bank.detect` describes and scores each level as one task and runs the
levels on ``threads`` threads (:func:`scenesig.signatures.hog.thread_map`): a level's HOG and its filter
responses are computed exactly as one thread would, so the detections do not depend on the count.
"""
from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass, field

import numpy as np

from scenesig.surveys.settings import merge_settings

from scenesig.signatures.hog import FEATURE_DIM, HogPyramid, build_pyramid, default_config as hog_default
from scenesig.signatures.hog import (REGION_MARGIN_CELLS, assemble_pyramid, build_level, level_plan, level_scale,
                            level_size, thread_map, as_hog_input, window_cell)

__all__ = ["Classifier", "Bank", "Detections", "default_config", "score_maps_bruteforce", "limit_blas_threads"]

#: Detection parameters.
default_config = {
    "scale_search": 1,    # search nominal level +- this many pyramid levels
    "refine": True,       # sub-cell peak refinement (parabola through the 3x3 neighbourhood)
    "nms_iou": 0.3,       # top-N: suppress detections overlapping a better one by more than this
    # BLAS threads for the filter multiplies (None: leave numpy's setting).  They are small: a second
    # thread mostly spins -- on two busy cores five times the CPU and the wall time of one thread --
    # and a fixed count gives the same sums, the same detections, on every machine.
    "blas_threads": 1,
    # Pyramid levels described and scored at once (each level's features and filter responses are
    # one task; the levels are independent, so the detections are the same for any count).  One by
    # default: mining and map building already run one process per core; the localiser's detector
    # asks for two (localiser.detector.default_config).
    "threads": 1,
}

_BLAS = None
_BLAS_LIMIT = threading.local()      # the limit this thread's enclosing limit_blas_threads set


def limit_blas_threads(n: int | None):
    """Context limiting numpy's BLAS to ``n`` threads (no-op for None or without threadpoolctl).

    Inside an enclosing context of the same thread with the same ``n`` it is a no-op too (setting
    and restoring a limit costs ~0.1 ms; the localiser's detector and the bank both ask for one).
    """
    global _BLAS
    if n is None or getattr(_BLAS_LIMIT, "n", None) == int(n):
        return contextlib.nullcontext()
    if _BLAS is None:
        try:
            from threadpoolctl import ThreadpoolController
            _BLAS = ThreadpoolController()      # inspecting the loaded libraries costs ~2 ms: once
        except ImportError:
            _BLAS = False
    if _BLAS is False:
        return contextlib.nullcontext()
    return _limited(int(n))


@contextlib.contextmanager
def _limited(n: int):
    outer = getattr(_BLAS_LIMIT, "n", None)
    with _BLAS.limit(limits=n, user_api="blas"):
        _BLAS_LIMIT.n = n
        try:
            yield
        finally:
            _BLAS_LIMIT.n = outer


def _sigmoid(z):
    return 1.0 / (1.0 + np.exp(-np.clip(z, -50, 50)))


@dataclass
class Classifier:
    """One scene-signature classifier (a linear SVM over a window of HOG cells).

    Attributes
    ----------
    weights : ndarray, shape (fh, fw, 31), float32
        Filter; the score of a window is ``sum(weights * window) + bias``.
    bias : float
    level : int
        Nominal pyramid level ``k`` (scale ``2 ** (-k / scales_per_octave)``) the filter was trained at.
    box : tuple of float
        The candidate shape ``(x, y, w, h)`` in pixels of the reference image.
    nominal_xy : tuple of float
        Where the signature lies in the reference image (centre, pixels): the median over its
        training firings of the firing position shifted back by the image's alignment offset.
    nominal_scale : float
        Median scale (level scale) of the training firings.
    calibration : tuple of float
        ``(a, b)``: detection probability ``lambda = 1 / (1 + exp(-(a * score + b)))`` (Platt scaling
        fitted on held-out partitions during mining).
    hog : dict
        HOG parameters the filter expects (see :data:`scenesig.signatures.hog.default_config`).
    shape_index : int
        Index of the shape in the candidate template (-1 if unknown).
    kind : str
        Shape kind name.
    quality : float
        Held-out separability from mining (higher is better; NaN if unknown).
    spread : tuple of float
        ``(sx, sy)``: RMS deviation (pixels, per axis) of the training firings, moved into the
        reference image by their alignment offsets, from ``nominal_xy``.  Small for signatures that
        move with the alignment (distant structure), large for near ones (parallax) or unstable
        ones.  NaN if unknown.
    """

    weights: np.ndarray
    bias: float
    level: int
    box: tuple
    nominal_xy: tuple
    nominal_scale: float
    calibration: tuple = (1.0, 0.0)
    hog: dict = field(default_factory=lambda: dict(hog_default))
    shape_index: int = -1
    kind: str = ""
    quality: float = float("nan")
    spread: tuple = (float("nan"), float("nan"))

    def __post_init__(self):
        w = np.asarray(self.weights, dtype=np.float32)
        if w.ndim != 3 or w.shape[2] != FEATURE_DIM or w.shape[0] < 1 or w.shape[1] < 1:
            raise ValueError(f"classifier weights must have shape (fh, fw, {FEATURE_DIM}), "
                             f"got {w.shape}")
        self.weights = w

    @property
    def filter_shape(self) -> tuple[int, int]:
        """(fh, fw) in cells."""
        return self.weights.shape[0], self.weights.shape[1]

    @property
    def scale(self) -> float:
        """Scale of the nominal level."""
        return float(level_scale(self.level, int(self.hog["scales_per_octave"])))

    def probability(self, score):
        """Calibrated detection probability (lambda) of raw SVM scores."""
        a, b = self.calibration
        return _sigmoid(a * np.asarray(score, dtype=float) + b)


@dataclass
class Detections:
    """Detections of a bank in one image: arrays of shape (n_classifiers, top_n).

    Missing detections (classifier has no valid window in the search region, or fewer than top_n
    after NMS) are NaN (``level`` -1).  Coordinates are window centres in input-image pixels.
    """

    x: np.ndarray
    y: np.ndarray
    scale: np.ndarray
    score: np.ndarray
    prob: np.ndarray
    level: np.ndarray
    width: np.ndarray
    height: np.ndarray

    def __len__(self) -> int:
        return self.x.shape[0]

    @property
    def best(self) -> "Detections":
        """Only the best detection per classifier (arrays of shape (n, 1))."""
        return Detections(*(getattr(self, f)[:, :1] for f in self._fields()))

    @staticmethod
    def _fields():
        return ("x", "y", "scale", "score", "prob", "level", "width", "height")

    def boxes(self, rank: int = 0) -> np.ndarray:
        """(n, 4) boxes ``x0, y0, x1, y1`` of the rank-th detection of each classifier."""
        hw, hh = 0.5 * self.width[:, rank], 0.5 * self.height[:, rank]
        cx, cy = self.x[:, rank] + 0.5, self.y[:, rank] + 0.5
        return np.stack([cx - hw, cy - hh, cx + hw, cy + hh], axis=1)


class Bank:
    """The scene-signature classifiers of one place.

    Parameters
    ----------
    classifiers : list of Classifier
        All must share the same HOG parameters.
    image_size : tuple of int, optional
        (width, height) of the images the bank was trained on; detection checks it.
    meta : dict, optional
        Free-form numeric/str metadata kept through :meth:`to_arrays`.
    """

    def __init__(self, classifiers, image_size=None, meta=None):
        self.classifiers = list(classifiers)
        self.image_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
        self.meta = dict(meta or {})
        hogs = {tuple(sorted(c.hog.items())) for c in self.classifiers}
        if len(hogs) > 1:
            raise ValueError("classifiers of one bank must share HOG parameters "
                             f"(found {len(hogs)} different sets)")
        self.hog = dict(self.classifiers[0].hog) if self.classifiers else dict(hog_default)

    # ------------------------------------------------------------------ container
    def __len__(self) -> int:
        return len(self.classifiers)

    def __getitem__(self, i):
        if isinstance(i, (int, np.integer)):
            return self.classifiers[int(i)]
        return self.select(i)

    def __iter__(self):
        return iter(self.classifiers)

    def __repr__(self) -> str:
        return f"Bank({len(self)} classifiers, image_size={self.image_size})"

    def select(self, indices) -> "Bank":
        """A bank with the classifiers at ``indices`` (int array, slice or boolean mask)."""
        idx = np.arange(len(self))[indices]
        sub = Bank.__new__(Bank)      # the classifiers share this bank's HOG parameters: no re-check
        sub.classifiers = [self.classifiers[i] for i in np.atleast_1d(idx)]
        sub.image_size, sub.meta, sub.hog = self.image_size, dict(self.meta), dict(self.hog)
        return sub

    def best(self, n: int) -> "Bank":
        """The ``n`` classifiers of highest mining quality (NaN quality last)."""
        q = np.array([c.quality for c in self.classifiers], dtype=float)
        order = np.argsort(-np.nan_to_num(q, nan=-np.inf), kind="stable")
        return self.select(np.sort(order[:n]))

    # ------------------------------------------------------------------ storage
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for storage (no pickles; float16 only where the round trip is exact)."""
        n = len(self)
        cs = self.classifiers
        flat = (np.concatenate([c.weights.ravel() for c in cs]) if n
                else np.zeros(0, np.float32))
        kinds = sorted({c.kind for c in cs})
        out = {
            "weights": _compact(flat.astype(np.float32)),
            "filter_shape": np.array([c.filter_shape for c in cs], dtype=np.int32).reshape(n, 2),
            "bias": np.array([c.bias for c in cs], dtype=np.float64),
            "level": np.array([c.level for c in cs], dtype=np.int32),
            "box": _compact(np.array([c.box for c in cs], dtype=np.float64).reshape(n, 4)),
            "nominal_xy": np.array([c.nominal_xy for c in cs], dtype=np.float64).reshape(n, 2),
            "nominal_scale": np.array([c.nominal_scale for c in cs], dtype=np.float64),
            "calibration": np.array([c.calibration for c in cs], dtype=np.float64).reshape(n, 2),
            "shape_index": np.array([c.shape_index for c in cs], dtype=np.int32),
            "kind": np.array([kinds.index(c.kind) for c in cs], dtype=np.int32),
            "kind_names": np.array(kinds, dtype=str),
            "quality": np.array([c.quality for c in cs], dtype=np.float64),
            "spread": np.array([c.spread for c in cs], dtype=np.float64).reshape(n, 2),
            "hog_cell": np.array(int(self.hog["cell"])),
            "hog_scales_per_octave": np.array(int(self.hog["scales_per_octave"])),
            "hog_clip": np.array(float(self.hog["clip"])),
            "hog_color": np.array(bool(self.hog["color"])),
            "image_size": np.array(self.image_size if self.image_size else (-1, -1), dtype=np.int32),
        }
        for k, v in self.meta.items():
            out[f"meta_{k}"] = np.asarray(v)
        return out

    @classmethod
    def from_arrays(cls, d: dict) -> "Bank":
        """Inverse of :meth:`to_arrays`.

        Raises
        ------
        ValueError
            If a required array is missing or the sizes disagree.
        """
        need = ("weights", "filter_shape", "bias", "level", "box", "nominal_xy", "nominal_scale",
                "calibration", "hog_cell", "hog_scales_per_octave", "hog_clip", "hog_color")
        missing = [k for k in need if k not in d]
        if missing:
            raise ValueError(f"bank arrays lack {', '.join(missing)}")
        fs = np.asarray(d["filter_shape"], dtype=int).reshape(-1, 2)
        n = len(fs)
        sizes = fs[:, 0] * fs[:, 1] * FEATURE_DIM
        flat = np.asarray(d["weights"], dtype=np.float32)
        if flat.size != sizes.sum():
            raise ValueError(f"bank weights hold {flat.size} values but the filter shapes need "
                             f"{int(sizes.sum())}")
        for key in ("bias", "level", "box", "nominal_xy", "nominal_scale", "calibration"):
            a = np.asarray(d[key])
            if (a.shape[0] if a.ndim else 1) != n:
                raise ValueError(f"bank array {key!r} does not have {n} rows")
        hog = {"cell": int(d["hog_cell"]), "scales_per_octave": int(d["hog_scales_per_octave"]),
               "clip": float(d["hog_clip"]), "color": bool(d["hog_color"])}
        kind_names = [str(s) for s in np.asarray(d.get("kind_names", np.array([], dtype=str)))]
        kind = np.asarray(d.get("kind", np.full(n, -1)), dtype=int)
        sidx = np.asarray(d.get("shape_index", np.full(n, -1)), dtype=int)
        qual = np.asarray(d.get("quality", np.full(n, np.nan)), dtype=float)
        spread = np.asarray(d.get("spread", np.full((n, 2), np.nan)), dtype=float).reshape(n, 2)
        offs = np.concatenate([[0], np.cumsum(sizes)])
        cs = []
        for i in range(n):
            cs.append(Classifier(
                weights=flat[offs[i]:offs[i + 1]].reshape(fs[i, 0], fs[i, 1], FEATURE_DIM),
                bias=float(np.asarray(d["bias"])[i]), level=int(np.asarray(d["level"])[i]),
                box=tuple(float(v) for v in np.asarray(d["box"], dtype=float).reshape(n, 4)[i]),
                nominal_xy=tuple(float(v) for v in np.asarray(d["nominal_xy"]).reshape(n, 2)[i]),
                nominal_scale=float(np.asarray(d["nominal_scale"])[i]),
                calibration=tuple(float(v) for v in np.asarray(d["calibration"]).reshape(n, 2)[i]),
                hog=dict(hog), shape_index=int(sidx[i]),
                kind=kind_names[kind[i]] if 0 <= kind[i] < len(kind_names) else "",
                quality=float(qual[i]), spread=(float(spread[i, 0]), float(spread[i, 1]))))
        size = tuple(int(v) for v in np.asarray(d.get("image_size", (-1, -1))))
        meta = {k[5:]: (v.item() if np.ndim(v) == 0 else v) for k, v in d.items()
                if k.startswith("meta_")}
        bank = cls(cs, None if size[0] < 0 else size, meta)
        bank.hog = hog
        return bank

    # ------------------------------------------------------------------ detection
    def levels(self, scale_search: int = 1) -> list[int]:
        """Pyramid levels detection needs (nominal +- scale_search, never below 0)."""
        ks = set()
        for c in self.classifiers:
            ks.update(range(max(0, c.level - scale_search), c.level + scale_search + 1))
        return sorted(ks)

    def pyramid(self, image: np.ndarray, scale_search: int = 1, levels=None, windows=None,
                threads: int = 1) -> HogPyramid:
        """The HOG pyramid of ``image`` with exactly what this bank searches.

        Parameters
        ----------
        image : gray or BGR image.
        scale_search : levels nominal +- this (when ``levels`` is not given).
        levels : per-classifier levels to search (as in :meth:`detect`).
        windows : per-classifier search windows (as in :meth:`detect`).  With windows only the
            cells the windows' detections can touch are computed at each level (and levels no
            window reaches are skipped); those cells are exactly the whole level's.
        threads : levels computed at once (the features are the same for any count).
        """
        levels, windows = self._check_search(levels, windows, scale_search)
        h, w = np.asarray(image).shape[:2]
        table = None if windows is None else self._pairs((w, h), levels, windows)
        need = sorted(set().union(*levels)) if len(self) else []
        return build_pyramid(image, self.hog, **_pyramid_extent(table, need, windows), threads=threads)

    def _check_search(self, levels, windows, scale_search: int):
        """Per-classifier levels (default nominal +- scale_search) and windows as a float array, checked."""
        n = len(self)
        if levels is None:
            levels = [range(max(0, c.level - scale_search), c.level + scale_search + 1) for c in self.classifiers]
        elif len(levels) != n:
            raise ValueError(f"levels must list the levels of each of the {n} classifiers")
        if windows is not None:
            windows = np.asarray(windows, dtype=float)
            if windows.shape != (n, 4):
                raise ValueError(f"windows must have shape ({n}, 4), got {windows.shape}")
        return levels, windows

    def _pairs(self, image_size, levels, windows):
        """:func:`_range_table` for an image of ``image_size`` (width, height), before its pyramid exists."""
        w, h = image_size
        spo, cell = int(self.hog["scales_per_octave"]), int(self.hog["cell"])
        geom = {}
        for k in sorted(set().union(*levels)) if len(self) else []:
            lw, lh = level_size((w, h), k, spo)
            if lw >= cell and lh >= cell:
                geom[k] = (lh // cell, lw // cell, lw / w, lh / h)
        return _range_table(self.classifiers, levels, geom, cell, windows)

    def detect(self, image, windows=None, top_n: int = 1, config: dict | None = None,
               levels=None) -> Detections:
        """Detect every classifier of the bank in one image.

        Parameters
        ----------
        image : ndarray, ScaledImages or HogPyramid
            The image (gray or BGR), the image with its levels' resizes
            (:class:`scenesig.signatures.hog.ScaledImages`, the same detections), or its pyramid (built with
            this bank's HOG parameters and the needed levels, e.g. by :meth:`pyramid`).
        windows : ndarray, shape (n, 4), optional
            Per-classifier search window ``x_min, y_min, x_max, y_max`` (input pixels) for the
            detection *centre*; a row of NaN means the whole image.
        top_n : int
            Number of detections per classifier (after non-maximum suppression).
        config : dict, optional
            Overrides of :data:`default_config`.
        levels : sequence of sequence of int, optional
            Per-classifier pyramid levels to search (default nominal +- ``scale_search``).

        Returns
        -------
        Detections
        """
        cfg = merge_settings(default_config, config, "detection")
        if top_n < 1:
            raise ValueError(f"top_n must be >= 1, got {top_n}")
        levels, windows = self._check_search(levels, windows, int(cfg["scale_search"]))
        threads = int(cfg["threads"])
        with limit_blas_threads(cfg["blas_threads"]):
            if isinstance(image, HogPyramid):
                pyr = image
                if not pyr.matches(self.hog):
                    raise ValueError("pyramid was built with different HOG parameters than the bank "
                                     f"({pyr.config} vs {self.hog})")
                maps = _score_all(self.classifiers, pyr, levels, windows, threads)
            else:
                pyr, maps = self._describe_and_score(image, levels, windows, threads)
        return _pick(self.classifiers, pyr, maps, top_n, bool(cfg["refine"]), float(cfg["nms_iou"]))

    def _describe_and_score(self, image, levels, windows, threads: int):
        """:meth:`pyramid` and :func:`_score_all` in one: each level's features and then its filter
        responses are one task, so on several threads one level is scored while another is
        described.  The same pyramid and score maps as the two steps."""
        cfg = merge_settings(hog_default, self.hog, "HOG")
        img = as_hog_input(image, bool(cfg["color"]))
        size = img.shape[1::-1]
        table = self._pairs(size, levels, windows)
        need = sorted(set().union(*levels)) if len(self) else []
        plan = level_plan(size, cfg, **_pyramid_extent(table, need, windows))
        jobs = _jobs(table)
        at_level = _by_level(jobs)

        def level_task(p):
            k, lsize, box = p
            feat, valid = build_level(img, lsize, box, cfg)
            return (feat, valid), {key: _score_job(feat, key, jobs[key], self.classifiers)
                                   for key in at_level.get(k, ())}

        done = thread_map(level_task, plan, threads, cost=[_level_cost(p, cfg) for p in plan])
        scored = {}
        for _, d in done:
            scored.update(d)
        return assemble_pyramid(size, cfg, plan, [f for f, _ in done]), _collect(len(self), jobs, scored)


def _pyramid_extent(table, need, windows) -> dict:
    """``levels`` and ``regions`` of :func:`build_pyramid` for a range table: every needed level whole
    without windows; with windows only the levels some window reaches, each the bounding box (cells,
    end exclusive) of its pairs' windows."""
    if windows is None:
        return {"levels": need, "regions": None}
    _, k, fh, fw, r0, r1, c0, c1 = table
    boxes = {}
    for kk in np.unique(k):
        on = k == kk
        boxes[int(kk)] = (int(r0[on].min()), int((r1[on] + fh[on]).max()),
                          int(c0[on].min()), int((c1[on] + fw[on]).max()))
    return {"levels": sorted(boxes), "regions": boxes}


def _level_cost(p, cfg) -> float:
    """Pixels a :func:`scenesig.signatures.hog.build_level` task of :func:`scenesig.signatures.hog.level_plan` describes
    (to start the largest levels first)."""
    _, (lw, lh), box = p
    if box is None:
        return float(lw * lh)
    cell, m = int(cfg["cell"]), 2 * REGION_MARGIN_CELLS
    return float(min(lh, (box[1] - box[0] + m) * cell) * min(lw, (box[3] - box[2] + m) * cell))


def _compact(a: np.ndarray) -> np.ndarray:
    """float16 copy of ``a`` if that round trip is exact, else ``a`` unchanged."""
    a16 = a.astype(np.float16)
    with np.errstate(over="ignore", invalid="ignore"):
        if np.array_equal(a16.astype(a.dtype), a, equal_nan=True):
            return a16
    return a


# ---------------------------------------------------------------------------------- scoring


def _range_table(classifiers, levels, geom: dict, cell: int, windows):
    """Every (classifier, level) pair to score, with its top-left cell ranges (non-empty only).

    ``geom`` maps each available level to ``(hc, wc, sx, sy)`` (cells, scale).  The ranges
    ``[r0, r1] x [c0, c1]`` (inclusive) hold the top-left cells of the windows whose centre lies in
    the classifier's search window (:func:`scenesig.signatures.hog.window_cell` of its corners; the whole
    level for a NaN window).  Returns int arrays ``i, k, fh, fw, r0, r1, c0, c1``, pairs in
    classifier order and each classifier's levels in its order.
    """
    ii, kk = [], []
    for i, ks in enumerate(levels):
        for k in ks:
            if k in geom:
                ii.append(i)
                kk.append(k)
    i = np.array(ii, dtype=np.intp)
    k = np.array(kk, dtype=np.intp)
    shapes = np.array([c.filter_shape for c in classifiers], dtype=np.intp).reshape(-1, 2)
    fh, fw = shapes[i, 0], shapes[i, 1]
    g = np.array([geom[int(v)] for v in kk], dtype=float).reshape(-1, 4)
    r0, r1 = np.zeros(len(i), np.intp), g[:, 0].astype(np.intp) - fh
    c0, c1 = np.zeros(len(i), np.intp), g[:, 1].astype(np.intp) - fw
    if windows is not None and len(i):
        win = np.asarray(windows, dtype=float)[i]
        sx, sy = g[:, 2], g[:, 3]
        ok = ~np.isnan(win).any(axis=1)
        # window_cell() of both corners, on arrays; 1e-9 absorbs round-off.
        ra, ca = window_cell(win[:, 0], win[:, 1], (sx, sy), cell, fh, fw)
        rb, cb = window_cell(win[:, 2], win[:, 3], (sx, sy), cell, fh, fw)
        with np.errstate(invalid="ignore"):
            r0 = np.where(ok, np.maximum(r0, np.ceil(ra - 1e-9)), r0).astype(np.intp)
            r1 = np.where(ok, np.minimum(r1, np.floor(rb + 1e-9)), r1).astype(np.intp)
            c0 = np.where(ok, np.maximum(c0, np.ceil(ca - 1e-9)), c0).astype(np.intp)
            c1 = np.where(ok, np.minimum(c1, np.floor(cb + 1e-9)), c1).astype(np.intp)
    keep = (r1 >= r0) & (c1 >= c0)
    return tuple(a[keep] for a in (i, k, fh, fw, r0, r1, c0, c1))


def _score_all(classifiers, pyr: HogPyramid, levels, windows, threads: int = 1):
    """Score maps: list (per classifier) of list of (k, r0, c0, map) with map[r - r0, c - c0].

    The levels are scored on ``threads`` threads; the maps are the same for any count."""
    geom = {k: (*f.shape[:2], *pyr.scale_xy(k)) for k, f in pyr.levels.items()}
    table = _range_table(classifiers, levels, geom, pyr.cell, windows)
    i, k, fh, fw, r0, r1, c0, c1 = table
    for kk, box in pyr.regions.items():
        on = k == kk
        v0, v1, u0, u1 = box
        bad = on & ((r0 < v0) | (r1 + fh > v1) | (c0 < u0) | (c1 + fw > u1))
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise ValueError(f"pyramid level {kk} holds features only in cells {box}, but classifier {i[j]} needs "
                             f"rows {r0[j]}..{r1[j] + fh[j] - 1}, columns {c0[j]}..{c1[j] + fw[j] - 1} "
                             "(build it with Bank.pyramid and the same windows and levels)")
    jobs = _jobs(table)
    at_level = _by_level(jobs)
    done = thread_map(lambda keys: {key: _score_job(pyr.levels[key[0]], key, jobs[key], classifiers) for key in keys},
                      list(at_level.values()), threads, cost=[pyr.levels[ks[0][0]].size for ks in at_level.values()])
    scored = {}
    for d in done:
        scored.update(d)
    return _collect(len(classifiers), jobs, scored)


def _jobs(table) -> dict:
    """The range table's pairs grouped by (level, filter width) -- one multiply each (or one per member,
    see :func:`_score_job`) -- in the order the groups first appear: ``{(k, fw): [(i, r0, r1, c0, c1)]}``."""
    i, k, fh, fw, r0, r1, c0, c1 = table
    jobs: dict[tuple[int, int], list] = {}
    for row in zip(i.tolist(), k.tolist(), fw.tolist(), r0.tolist(), r1.tolist(), c0.tolist(), c1.tolist()):
        jobs.setdefault((row[1], row[2]), []).append((row[0], row[3], row[4], row[5], row[6]))
    return jobs


def _by_level(jobs: dict) -> dict:
    """``{k: [(k, fw), ...]}``: the groups of :func:`_jobs` per level, in their order."""
    at_level: dict[int, list] = {}
    for key in jobs:
        at_level.setdefault(key[0], []).append(key)
    return at_level


def _collect(n: int, jobs: dict, scored: dict) -> list:
    """Per classifier, its score maps in the order of the groups (as a serial loop appends them)."""
    out = [[] for _ in range(n)]
    for key in jobs:
        for i, entry in scored[key]:
            out[i].append(entry)
    return out


def _score_job(feat, key, members, classifiers) -> list:
    """``[(i, (k, r0, c0, map)), ...]`` of one (level, filter width) group on the level's features."""
    k, fw = key
    # One multiply for the whole group over the union of its windows -- unless the windows
    # are small and scattered (the localiser's case), when the union would mostly be wasted
    # work and each member is scored on its own region.
    area = sum((m[2] - m[1] + 1) * (m[4] - m[3] + 1) for m in members)
    union = ((max(m[2] for m in members) - min(m[1] for m in members) + 1)
             * (max(m[4] for m in members) - min(m[3] for m in members) + 1))
    batches = [members] if len(members) == 1 or 2 * area >= union else [[m] for m in members]
    out = []
    for batch in batches:
        out.extend(_score_group(feat, fw, batch, classifiers, k))
    return out


def _score_group(feat, fw, members, classifiers, k) -> list:
    """Score a group of same-width filters on one level with one matrix multiply:
    ``[(i, (k, r0, c0, map)), ...]`` in the order of ``members``."""
    # Union of the members' ranges: rows and columns of cells that must be unrolled.
    if len(members) == 1:
        i, R0, R1, C0, C1 = members[0]
        R1 += classifiers[i].filter_shape[0]                              # exclusive
    else:
        R0 = min(m[1] for m in members)
        C0 = min(m[3] for m in members)
        R1 = max(m[2] + classifiers[m[0]].filter_shape[0] for m in members)   # exclusive
        C1 = max(m[4] for m in members)
    C1 += fw                                                              # exclusive
    R1, C1 = min(R1, feat.shape[0]), min(C1, feat.shape[1])
    nr, ncol = R1 - R0, C1 - C0 - fw + 1
    # Unroll along x: row (y, x) holds cells x .. x + fw - 1 of row y (fw * 31 values).  (A strided
    # view built directly -- sliding_window_view's checks cost more than the copy at these sizes.)
    if not feat.flags.c_contiguous:
        feat = np.ascontiguousarray(feat)
    t0, t1, t2 = feat.strides
    x_unrolled = np.ndarray((nr, ncol, fw, FEATURE_DIM), feat.dtype, feat, R0 * t0 + C0 * t1, (t0, t1, t1, t2)) \
        .reshape(nr * ncol, fw * FEATURE_DIM)
    rows, offs = [], []
    o = 0
    for m in members:
        w = classifiers[m[0]].weights
        rows.append(w.reshape(w.shape[0], fw * FEATURE_DIM))
        offs.append(o)
        o += w.shape[0]
    # (fw*31, sum fh); one member's filter is used in place (the same layout as the stacked copy)
    wmat = (rows[0] if len(rows) == 1 else np.concatenate(rows, axis=0)).T
    resp = (x_unrolled @ wmat).reshape(nr, ncol, o)             # row responses
    s0, s1, s2 = resp.strides
    out = []
    for m, off in zip(members, offs):
        i, r0, r1, c0, c1 = m
        fh = classifiers[i].filter_shape[0]
        nrow = r1 - r0 + 1
        # score[y, x] = sum_d resp[y + d, x, d]: a diagonal of the row responses (strided view).
        start = (r0 - R0) * s0 + (c0 - C0) * s1 + off * s2
        diag = np.ndarray((nrow, c1 - c0 + 1, fh), resp.dtype, resp, start, (s0, s1, s0 + s2))
        out.append((i, (k, r0, c0, diag.sum(axis=2) + np.float32(classifiers[i].bias))))
    return out


def score_maps_bruteforce(classifier: Classifier, feat: np.ndarray) -> np.ndarray:
    """Reference correlation of one filter over one feature level (slow; for tests).

    Returns the (Hc - fh + 1, Wc - fw + 1) map of ``sum(w * window) + bias``.
    """
    fh, fw = classifier.filter_shape
    hc, wc = feat.shape[:2]
    out = np.empty((hc - fh + 1, wc - fw + 1))
    w = classifier.weights.astype(np.float64)
    for r in range(out.shape[0]):
        for c in range(out.shape[1]):
            out[r, c] = np.sum(w * feat[r:r + fh, c:c + fw]) + classifier.bias
    return out


def _parabola(m: np.ndarray, r: int, c: int) -> tuple[float, float]:
    """Sub-cell offset of a peak from a parabola through it and its 4-neighbours."""
    dr = dc = 0.0
    if 0 < r < m.shape[0] - 1:
        a, b, d = m[r - 1, c], m[r, c], m[r + 1, c]
        den = a - 2 * b + d
        if den < 0:
            dr = float(np.clip(0.5 * (a - d) / den, -0.5, 0.5))
    if 0 < c < m.shape[1] - 1:
        a, b, d = m[r, c - 1], m[r, c], m[r, c + 1]
        den = a - 2 * b + d
        if den < 0:
            dc = float(np.clip(0.5 * (a - d) / den, -0.5, 0.5))
    return dr, dc


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of box a (4,) with boxes b (m, 4), boxes as x0, y0, x1, y1."""
    ix = np.clip(np.minimum(a[2], b[:, 2]) - np.maximum(a[0], b[:, 0]), 0, None)
    iy = np.clip(np.minimum(a[3], b[:, 3]) - np.maximum(a[1], b[:, 1]), 0, None)
    inter = ix * iy
    area = (a[2] - a[0]) * (a[3] - a[1]) + (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) - inter
    return inter / np.maximum(area, 1e-12)


def _pick(classifiers, pyr: HogPyramid, maps, top_n: int, refine: bool, nms_iou: float):
    if top_n == 1:
        return _pick_best(classifiers, pyr, maps, refine)
    n = len(classifiers)
    shape = (n, top_n)
    res = {f: np.full(shape, np.nan) for f in Detections._fields()}
    res["level"] = np.full(shape, -1, dtype=int)
    cell = pyr.cell
    for i, c in enumerate(classifiers):
        fh, fw = c.filter_shape
        entries = maps[i]
        if not entries:
            continue
        cands = []  # (score, k, r, c, map index)
        per_level = max(1, 8 * top_n) if top_n > 1 else 1
        for mi, (k, r0, c0, m) in enumerate(entries):
            flat = m.ravel()
            if per_level >= flat.size:
                idx = np.arange(flat.size)
            elif per_level == 1:
                idx = np.array([int(np.argmax(flat))])
            else:
                idx = np.argpartition(-flat, per_level)[:per_level]
            for j in idx:
                rr, cc = divmod(int(j), m.shape[1])
                cands.append((float(flat[j]), mi, rr, cc))
        cands.sort(key=lambda t: -t[0])
        kept_boxes, t = [], 0
        for score, mi, rr, cc in cands:
            k, r0, c0, m = entries[mi]
            dr, dc = _parabola(m, rr, cc) if refine else (0.0, 0.0)
            x, y = pyr.window_centre(k, r0 + rr + dr, c0 + cc + dc, fh, fw)
            sx, sy = pyr.scale_xy(k)
            bw, bh = fw * cell / sx, fh * cell / sy
            box = np.array([x + 0.5 - bw / 2, y + 0.5 - bh / 2, x + 0.5 + bw / 2, y + 0.5 + bh / 2])
            if kept_boxes and top_n > 1 and np.any(_iou(box, np.array(kept_boxes)) > nms_iou):
                continue
            kept_boxes.append(box)
            res["x"][i, t], res["y"][i, t] = x, y
            res["scale"][i, t] = 0.5 * (sx + sy)
            res["score"][i, t] = score
            res["prob"][i, t] = float(c.probability(score))
            res["level"][i, t] = k
            res["width"][i, t], res["height"][i, t] = bw, bh
            t += 1
            if t == top_n:
                break
    return Detections(**res)


def _pick_best(classifiers, pyr: HogPyramid, maps, refine: bool) -> Detections:
    """:func:`_pick` for ``top_n = 1``: each classifier's best window over its levels (the first
    level's on a tie, as the stable sort of :func:`_pick`), without candidate lists and NMS."""
    n = len(classifiers)
    res = {f: np.full((n, 1), np.nan) for f in Detections._fields()}
    res["level"] = np.full((n, 1), -1, dtype=int)
    cell = pyr.cell
    found = np.zeros(n, bool)
    for i, c in enumerate(classifiers):
        entries = maps[i]
        if not entries:
            continue
        best, bj, bm = -np.inf, 0, None
        for e in entries:
            m = e[3]
            j = int(m.argmax())
            v = float(m.flat[j])
            if bm is None or v > best:
                best, bj, bm = v, j, e
        k, r0, c0, m = bm
        fh, fw = c.filter_shape
        rr, cc = divmod(bj, m.shape[1])
        dr, dc = _parabola(m, rr, cc) if refine else (0.0, 0.0)
        x, y = pyr.window_centre(k, r0 + rr + dr, c0 + cc + dc, fh, fw)
        sx, sy = pyr.scale_xy(k)
        res["x"][i, 0], res["y"][i, 0] = x, y
        res["scale"][i, 0] = 0.5 * (sx + sy)
        res["score"][i, 0] = best
        res["level"][i, 0] = k
        res["width"][i, 0], res["height"][i, 0] = fw * cell / sx, fh * cell / sy
        found[i] = True
    if found.any():
        cal = np.array([c.calibration for c in classifiers], dtype=float).reshape(n, 2)
        s = res["score"][found, 0]
        res["prob"][found, 0] = _sigmoid(cal[found, 0] * s + cal[found, 1])
    return Detections(**res)

