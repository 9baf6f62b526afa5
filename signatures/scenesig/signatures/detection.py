"""Detection engine of a classifier bank: every classifier of a :class:`scenesig.signatures.bank.Bank` scored in
one pass over one HOG pyramid, and each one's best windows picked (the scene signatures of a place detected in a
live image, McManus et al. 2015, §3.3.1; the classifiers are those of §3.2).

The data model -- :class:`~scenesig.signatures.bank.Classifier`, :class:`~scenesig.signatures.bank.Bank` and
their storage -- is :mod:`scenesig.signatures.bank`; :meth:`Bank.detect <scenesig.signatures.bank.Bank.detect>`
and :meth:`Bank.pyramid <scenesig.signatures.bank.Bank.pyramid>` call :func:`detect` and :func:`pyramid` here.
This module holds the detection parameters (:data:`default_config`), the result type (:class:`Detections`), the
filter scoring, the peak picking and the thread (and BLAS thread) use.

One-pass detection
------------------
Classifiers that search the same pyramid level and have the same filter width share one matrix
multiply: the level's features are unrolled along x only (each row of the unrolled matrix is
``fw`` consecutive cells, ``fw * 31`` values), multiplied once by the stacked rows of all the
group's filters, and each filter's score map is the sum of its ``fh`` row responses along a
diagonal (a strided view, no copy).  The multiply is most of the scoring cost (BLAS); the
unrolled matrix is ``fw`` times the level size, not ``fw * fh`` times as a full im2col would be.
Search windows restrict the rows and columns that are unrolled, and (:func:`pyramid`) the cells
of each level whose features are computed at all.

Given an image, :func:`detect` describes and scores each level as one task and runs the
levels on ``threads`` threads (:func:`scenesig.signatures.hog.thread_map`): a level's HOG and its filter
responses are computed exactly as one thread would, so the detections do not depend on the count.
"""
from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass

import numpy as np

from scenesig.signatures.classifier import sigmoid
from scenesig.signatures.hog import (
    REGION_MARGIN_CELLS,
    HogPyramid,
    as_hog_input,
    assemble_pyramid,
    build_level,
    build_pyramid,
    default_config as hog_default,
    learned,
    level_plan,
    level_size,
    thread_map,
    window_cell,
)
from scenesig.surveys.settings import merge_settings

__all__ = ["Detections", "default_config", "detect", "pyramid", "score_maps_bruteforce", "limit_blas_threads"]

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


# ---------------------------------------------------------------------------------- the bank's pyramid and detections


def pyramid(bank, image: np.ndarray, scale_search: int = 1, levels=None, windows=None,
            threads: int = 1) -> HogPyramid:
    """:meth:`scenesig.signatures.bank.Bank.pyramid` of ``bank`` (the parameters are documented there)."""
    levels, windows = _check_search(bank, levels, windows, scale_search)
    check_cell_model(bank)
    h, w = np.asarray(image).shape[:2]
    table = None if windows is None else _pairs(bank, (w, h), levels, windows)
    need = sorted(set().union(*levels)) if len(bank) else []
    return build_pyramid(image, bank.hog, **_pyramid_extent(table, need, windows), threads=threads)


def check_cell_model(bank) -> None:
    """Refuse a bank mined on XFeat cells when this process's XFeat model is another file: its
    filters would be scored on descriptors they were never trained on (confident nonsense).

    Raises
    ------
    scenesig.surveys.errors.DataError
        (a ValueError) naming the model file found and both models' sha256.
    """
    want = bank.meta.get("xfeat_sha256")
    if not want or not learned(bank.hog):
        return
    from scenesig.signatures.xfeat import get_xfeat
    from scenesig.surveys.errors import DataError

    model = get_xfeat()
    if model.sha256 != want:
        raise DataError(model.path, f"this bank was mined on XFeat cells of model sha256 {want[:12]}..., but this "
                                    f"model file is {model.sha256[:12]}...: point $SCENESIG_XFEAT_MODEL at the "
                                    f"model the map was built with")


def _check_search(bank, levels, windows, scale_search: int):
    """Per-classifier levels (default nominal +- scale_search) and windows as a float array, checked."""
    n = len(bank)
    if levels is None:
        levels = [range(max(0, c.level - scale_search), c.level + scale_search + 1) for c in bank.classifiers]
    elif len(levels) != n:
        raise ValueError(f"levels must list the levels of each of the {n} classifiers")
    if windows is not None:
        windows = np.asarray(windows, dtype=float)
        if windows.shape != (n, 4):
            raise ValueError(f"windows must have shape ({n}, 4), got {windows.shape}")
    return levels, windows


def _pairs(bank, image_size, levels, windows):
    """:func:`_range_table` for an image of ``image_size`` (width, height), before its pyramid exists."""
    w, h = image_size
    spo, cell = int(bank.hog["scales_per_octave"]), int(bank.hog["cell"])
    geom = {}
    for k in sorted(set().union(*levels)) if len(bank) else []:
        lw, lh = level_size((w, h), k, spo)
        if lw >= cell and lh >= cell:
            geom[k] = (lh // cell, lw // cell, lw / w, lh / h)
    return _range_table(bank.classifiers, levels, geom, cell, windows)


def detect(bank, image, windows=None, top_n: int = 1, config: dict | None = None,
           levels=None) -> Detections:
    """:meth:`scenesig.signatures.bank.Bank.detect` of ``bank`` (the parameters are documented there)."""
    cfg = merge_settings(default_config, config, "detection")
    if top_n < 1:
        raise ValueError(f"top_n must be >= 1, got {top_n}")
    levels, windows = _check_search(bank, levels, windows, int(cfg["scale_search"]))
    check_cell_model(bank)
    threads = int(cfg["threads"])
    with limit_blas_threads(cfg["blas_threads"]):
        if isinstance(image, HogPyramid):
            pyr = image
            if not pyr.matches(bank.hog):
                raise ValueError("pyramid was built with different HOG parameters than the bank "
                                 f"({pyr.config} vs {bank.hog})")
            maps = _score_all(bank.classifiers, pyr, levels, windows, threads)
        else:
            pyr, maps = _describe_and_score(bank, image, levels, windows, threads)
    return _pick(bank.classifiers, pyr, maps, top_n, bool(cfg["refine"]), float(cfg["nms_iou"]))


def _describe_and_score(bank, image, levels, windows, threads: int):
    """:func:`pyramid` and :func:`_score_all` in one: each level's features and then its filter
    responses are one task, so on several threads one level is scored while another is
    described.  The same pyramid and score maps as the two steps."""
    cfg = merge_settings(hog_default, bank.hog, "HOG")
    img = as_hog_input(image, bool(cfg["color"]))
    size = img.shape[1::-1]
    table = _pairs(bank, size, levels, windows)
    need = sorted(set().union(*levels)) if len(bank) else []
    plan = level_plan(size, cfg, **_pyramid_extent(table, need, windows))
    jobs = _jobs(table)
    at_level = _by_level(jobs)

    def level_task(p):
        k, lsize, box = p
        feat, valid = build_level(img, lsize, box, cfg)
        return (feat, valid), {key: _score_job(feat, key, jobs[key], bank.classifiers)
                               for key in at_level.get(k, ())}

    done = thread_map(level_task, plan, threads, cost=[_level_cost(p, cfg) for p in plan])
    scored = {}
    for _, d in done:
        scored.update(d)
    return assemble_pyramid(size, cfg, plan, [f for f, _ in done]), _collect(len(bank), jobs, scored)


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
    # Unroll along x: row (y, x) holds cells x .. x + fw - 1 of row y (fw * D values).  (A strided
    # view built directly -- sliding_window_view's checks cost more than the copy at these sizes.)
    if not feat.flags.c_contiguous:
        feat = np.ascontiguousarray(feat)
    t0, t1, t2 = feat.strides
    D = feat.shape[2]
    x_unrolled = np.ndarray((nr, ncol, fw, D), feat.dtype, feat, R0 * t0 + C0 * t1, (t0, t1, t1, t2)) \
        .reshape(nr * ncol, fw * D)
    rows, offs = [], []
    o = 0
    for m in members:
        w = classifiers[m[0]].weights
        rows.append(w.reshape(w.shape[0], fw * D))
        offs.append(o)
        o += w.shape[0]
    # (fw*D, sum fh); one member's filter is used in place (the same layout as the stacked copy)
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


def score_maps_bruteforce(classifier, feat: np.ndarray) -> np.ndarray:
    """Reference correlation of one filter (a :class:`~scenesig.signatures.bank.Classifier`) over one feature
    level (slow; for tests).

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
        res["prob"][found, 0] = sigmoid(cal[found, 0] * s + cal[found, 1])
    return Detections(**res)

