"""Scene-signature heading estimation on GRIEF data sets (the *signatures* method of the heading
benchmark).

For a protocol pair (map image i, live image j) of one place the horizontal displacement of the
scene is estimated from a bank of scene signatures of that place that never saw image j:

* ``sessions`` layout (e.g. stromovka, 12 sessions per place) -- **leave one session out**: the
  bank used for live session j is mined from the place's other sessions, aligned by *their* ground
  truth displacements relative to the first of them (never the live image's), with random windows
  from the other places' images of the same training sessions as external negatives.  One bank per
  (place, live session), shared by the 11 pairs with that live session.
* ``sequence`` layout (e.g. season: one summer map image and one winter live image per place) --
  there is one appearance of the place only, and neighbouring frames of the sequence show other
  scenes (the frames are tens of metres apart), so the bank is mined from **augmented copies of the
  map image**: gamma, contrast, colour casts, blur, noise, desaturation, a synthetic "snow" that
  whitens smooth and bright regions and lifts the shadows, and small left/right shifts (the
  alignment offsets of the shifted copies are known exactly).  Summer frames of other places are
  external negatives.  Live images are never used in training.  ``SignatureHeading(single=True)``
  (``scenesig bench heading --single``) applies this protocol to a sessions layout too: each
  session becomes a one-image map of its places, a development set for single-experience
  settings.  Such banks take the settings :mod:`scenesig.signatures.experience` keeps for one appearance.

Detection: every classifier is searched in the map image near its trained position (the map image's
alignment is known) and in the live image over the whole width and within ``live_search_y_px`` of
its row; classifiers whose detection probability (lambda) reaches ``min_prob`` in both images vote
with ``x_live - x_map``.  The estimate is the weighted mode of the votes (densest window of
``vote_window_px``), refined by the weighted median of the votes in that window.

Vote weights: ``(lambda_map * lambda_live) ** prob_weight`` times ``1 / (1 + (s_x / 6 px)^2)^2``,
where ``s_x`` is the classifier's training spread (:attr:`scenesig.signatures.bank.Classifier.spread`): how
far its firings in the training sessions strayed from the ground-truth alignment.  Signatures on
near structure move with the robot's position (parallax), not only with its heading, and are the
main source of error on stromovka.

**One configuration for every folder.**  The settings above are the same for every data set; the
only thing that depends on the data is a rule that reads the *training* images alone: a bank mined
from fewer than ``calibrated_min_appearances`` real appearances of its place (one summer image and
its augmented copies on the sequence layout) has a detection probability lambda calibrated on
synthetic changes only, which says little about a real change of season; such a bank's classifiers
all vote, with equal probability weight (``min_prob`` and ``prob_weight`` become 0 for it).  The
live images and their truth are never read to choose a setting.

Images are processed at ``scale`` (default 0.5: 1024x384 -> 512x192) and results reported in
full-resolution pixels.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from scenesig.signatures import experience, hog as hogmod, mining
from scenesig.signatures.augment import augment, synthesise
from scenesig.signatures.colour import local_exact_histogram_match
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "bank_config", "SignatureHeading", "estimate_heading_signatures", "densest_window_displacement",
           "augment"]

log = logging.getLogger(__name__)

#: Heading-estimation parameters (pixels are full-resolution unless noted).
default_config = {
    "scale": 0.5,                   # image scale for mining and detection
    "mining": {},                   # overrides of signatures.mining.default_config
    "max_classifiers": None,        # keep only the N best classifiers of a bank
    "external_negative_images": 4,  # other places' images per bank as external negatives
    "map_search_px": 48.0,          # map image: search radius around the trained position
    "live_search_y_px": 96.0,       # live image: vertical search radius (whole width always); a
                                    # quarter of GRIEF's 384-px height: pitch and the path's offset
                                    # between visits move the scene vertically too
    "min_prob": 0.5,                # a classifier "fires" when lambda >= this
    "prob_weight": 1.0,             # votes weighted by (lambda_map * lambda_live) ** this
    # Rule on the training data only: a bank mined from fewer real appearances of its place than
    # this has an uncalibrated lambda, so all its classifiers vote equally (min_prob = prob_weight = 0)
    "calibrated_min_appearances": 2,
    "live_top_n": 1,                # live detections per classifier that vote (NMS-separated)
    "rank_decay": 0.5,              # vote weight of the r-th live detection: rank_decay ** r
    "min_votes": 3,                 # fewer firing classifiers: vote with all classifiers
    "vote_window_px": 20.0,         # mode window (the protocol's 20-px bins)
    "spread_sigma_px": 6.0,         # vote weight 1 / (1 + (spread_x / this)^2)^2
    "augment_copies": 11,           # sequence layout: augmented copies of the map image
    "augment_shift_px": 24.0,       # sequence layout: max left/right shift of a copy
    "single_experience": {},        # overrides of signatures.experience.default_config: what a bank
                                    # from one real appearance is mined and detected with
    "seed": 0,
    # XFeat model file for banks on learned cells (mining's ``features``); None: the library's lookup
    # ($SCENESIG_XFEAT_MODEL, else the user path).  A benchmark names its model here, so it reaches the
    # worker processes that mine (signatures.xfeat reads the model's place from the environment).
    "xfeat_model": None,
}

# ---------------------------------------------------------------------------------- voting


def densest_window_displacement(votes: np.ndarray, weights: np.ndarray | None = None,
                      window: float = 20.0) -> tuple[float, np.ndarray]:
    """Robust displacement from per-classifier votes.

    The densest interval of width ``window`` (sum of weights) is found over the sorted votes; the
    estimate is the weighted median of the votes inside it.

    Parameters
    ----------
    votes : ndarray, shape (n,)
    weights : ndarray, shape (n,), optional
    window : float

    Returns
    -------
    estimate : float
        NaN if there are no votes.
    inliers : ndarray of bool, shape (n,)
    """
    v = np.asarray(votes, dtype=float)
    ok = np.isfinite(v)
    w = np.ones_like(v) if weights is None else np.asarray(weights, dtype=float)
    ok &= np.isfinite(w) & (w > 0)
    inl = np.zeros(len(v), bool)
    if not ok.any():
        return float("nan"), inl
    idx = np.flatnonzero(ok)
    order = idx[np.argsort(v[idx], kind="stable")]
    vs, ws = v[order], w[order]
    cw = np.concatenate([[0.0], np.cumsum(ws)])
    end = np.searchsorted(vs, vs + window, side="right")
    mass = cw[end] - cw[:-1] if len(vs) else np.zeros(0)
    # Ties: prefer the window whose votes are most concentrated (smallest spread).
    best = np.flatnonzero(mass >= mass.max() - 1e-9)
    spreads = [vs[end[b] - 1] - vs[b] for b in best]
    b = int(best[int(np.argmin(spreads))])
    sel = order[b:end[b]]
    inl[sel] = True
    sv, sw = v[sel], w[sel]
    o = np.argsort(sv)
    c = np.cumsum(sw[o])
    est = float(sv[o][np.searchsorted(c, 0.5 * c[-1])])
    return est, inl


# ---------------------------------------------------------------------------------- estimator


@dataclass
class PairRecord:
    """What the estimate of one pair rests on (for figures and diagnosis).

    Boxes are ``x0, y0, x1, y1`` in full-resolution pixels of the map / live image; ``fired``
    marks classifiers that fired in both images, ``inlier`` those whose vote agreed with the
    estimate.  ``spread`` is each classifier's training spread (full-res px, x and y);
    ``live_top`` its top live detections (x in processing px, probability), ``map_x`` /
    ``map_prob`` its map detection.
    """

    estimate: float
    map_boxes: np.ndarray
    live_boxes: np.ndarray
    votes: np.ndarray
    fired: np.ndarray
    inlier: np.ndarray
    bank_size: int
    spread: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    live_top: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 2)))
    map_x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    map_prob: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class _Group:
    place: int
    live: int
    train: list            # session indices used for mining (sessions layout)
    maps: list             # map sessions to estimate against
    pairs: list = field(default_factory=list)


def _load(place, session, scale):
    img = place.image(session)
    if scale != 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return img


class SignatureHeading:
    """Scene-signature heading estimator for a GRIEF data set.

    Parameters
    ----------
    dataset : surveys.grief.GriefDataset or path
    config : dict, optional
        Overrides of :data:`default_config`.
    n_jobs : int
        Banks mined/detected in parallel (processes).
    progress : bool
        tqdm progress over banks.
    single : bool
        Mine every bank from the pair's map image alone (and its synthesised copies) -- the
        sequence layout's protocol -- also on a sessions layout, where it turns each session into a
        one-image map of its places (a development set for single-experience settings that shares
        no image with the season data set).

    Attributes
    ----------
    records : dict
        ``(place, map, live) -> PairRecord`` after :meth:`estimate`.
    bank_stats : list of dict
        Mining statistics of every bank.
    """

    def __init__(self, dataset, config: dict | None = None, n_jobs: int = 1, progress: bool = True,
                 single: bool = False):
        if isinstance(dataset, (str, Path)):
            from scenesig.surveys.grief import load
            dataset = load(dataset)
        self.dataset = dataset
        self.config = merge_settings(default_config, config, "heading",
                                     open=("mining", "single_experience"))
        self.n_jobs = int(n_jobs)
        self.progress = progress
        self.single = bool(single)
        self.records: dict = {}
        self.bank_stats: list = []

    # -------------------------------------------------------------- grouping
    def _groups(self, pairs) -> list[_Group]:
        ds = self.dataset
        by_map = self.single or ds.kind == "sequence"
        groups: dict[tuple[int, int], _Group] = {}
        for pr in pairs:
            place, i, j = int(pr[0]), int(pr[1]), int(pr[2])
            key = (place, i) if by_map else (place, j)
            g = groups.get(key)
            if g is None:
                pl = ds.places[place]
                train = [i] if by_map else [s for s in pl.sessions if s != j]
                g = groups[key] = _Group(place, j, train, [])
            g.pairs.append((place, i, j))
            if i not in g.maps:
                g.maps.append(i)
        return list(groups.values())

    # -------------------------------------------------------------- main
    def estimate(self, pairs) -> list[float]:
        """Estimated displacement (full-resolution px, map -> live) of each pair, in order."""
        pairs = [tuple(int(v) for v in p) for p in pairs]
        groups = self._groups(pairs)
        t0 = time.perf_counter()
        if self.n_jobs == 1:
            it = groups
            if self.progress:
                from tqdm import tqdm
                it = tqdm(groups, desc="signature banks", unit="bank")
            results = [_run_group(self.dataset, g, self.config) for g in it]
        else:
            from joblib import Parallel, delayed
            par = Parallel(n_jobs=self.n_jobs, return_as="generator")
            gen = par(delayed(_run_group)(self.dataset, g, self.config) for g in groups)
            if self.progress:
                from tqdm import tqdm
                gen = tqdm(gen, total=len(groups), desc="signature banks", unit="bank")
            results = list(gen)
        est = {}
        for recs, stats in results:
            self.bank_stats.append(stats)
            for key, rec in recs.items():
                self.records[key] = rec
                est[key] = rec.estimate
        self.seconds = time.perf_counter() - t0
        return [float(est[p]) for p in pairs]


def train_bank(ds, place_index: int, train: list, live: int, cfg: dict):
    """Mine the bank of one place from its training sessions, never from ``live``: the sessions
    aligned by their ground truth relative to the first, joined -- when they are too few to fill
    mining's partitions (one map image: the sequence layout or ``single``) -- by augmented copies.

    Returns ``(bank, images, map_offset, stats)``: the bank, its training images (at ``cfg["scale"]``),
    the horizontal offset of each training session's image relative to the first (scaled px) and
    the mining statistics.
    """
    g = _Group(place_index, live, list(train), [])
    scale = float(cfg["scale"])
    place = ds.places[g.place]
    rng = np.random.default_rng([int(cfg["seed"]), g.place, g.live + 1])
    mcfg = dict(cfg["mining"])
    if cfg["max_classifiers"] is not None:
        mcfg["max_classifiers"] = int(cfg["max_classifiers"])
    # the training-data rule: settings by the number of real appearances (signatures.experience)
    exp = experience.settings_for(len(g.train), mcfg, cfg["single_experience"])
    mcfg = exp["mining"]
    ref = g.train[0]
    images = [_load(place, s, scale) for s in g.train]
    offsets = [[place.displacement(ref, s) * scale if s != ref else 0.0, 0.0] for s in g.train]
    map_offset = {s: o[0] for s, o in zip(g.train, offsets)}
    if len(images) < 2 * int(mining.resolve_config(mcfg)["n_partitions"]):
        # Too few appearances to partition: synthesised copies of the real images stand in.  The
        # clustering starts from two images of the first partition (signatures.mining), so every
        # partition needs two: with fewer real appearances (a map of 1-5 traverses) no shape would mine.
        images, offsets = synthesise(images, offsets, int(cfg["augment_copies"]), rng,
                                     float(cfg["augment_shift_px"]) * scale, exp["conditions"])
    offsets = np.asarray(offsets, dtype=float)
    # Other places seen in the training sessions (never the live session).
    others = [(p, s) for p in range(len(ds.places)) if p != g.place
              for s in ds.places[p].sessions if s in g.train and s != g.live]
    n_neg = min(int(cfg["external_negative_images"]), len(others))
    pick = rng.choice(len(others), size=n_neg, replace=False) if n_neg else []
    negatives = [_load(ds.places[others[k][0]], others[k][1], scale) for k in pick]

    bank, stats = mining.mine_place(images, offsets, config=mcfg, negatives=negatives, n_jobs=1,
                                    rng=int(cfg["seed"]))
    st = {"place": g.place, "live": g.live, **stats.as_dict(), "bank_size": len(bank),
          "appearances": len(g.train), "single_experience": exp["single"],
          "colour_constancy": exp["colour_constancy"]}
    return bank, images, map_offset, st


def _run_group(ds, g: _Group, cfg: dict):
    """Mine one bank and estimate all pairs that use it."""
    from scenesig.signatures.xfeat import using_model

    with using_model(cfg["xfeat_model"]):
        return _estimate_group(ds, g, cfg)


def _estimate_group(ds, g: _Group, cfg: dict):
    scale = float(cfg["scale"])
    place = ds.places[g.place]
    bank, images, map_offset, st = train_bank(ds, g.place, g.train, g.live, cfg)
    # the one data-dependent rule: it counts the real (not augmented) training appearances
    cfg = bank_config(cfg, len(g.train))
    st["calibrated"] = cfg["calibrated"]
    recs = {}
    if len(bank) == 0:
        for key in g.pairs:
            recs[key] = PairRecord(float("nan"), np.zeros((0, 4)), np.zeros((0, 4)), np.zeros(0),
                                   np.zeros(0, bool), np.zeros(0, bool), 0)
        return recs, st

    nom = np.array([c.nominal_xy for c in bank])
    spread = np.array([c.spread for c in bank]) / scale     # full-resolution px
    # Live detection: whole width, rows near the trained row; once per live image of the group.
    ry = float(cfg["live_search_y_px"]) * scale
    live_win = np.stack([np.full(len(bank), -1e6), nom[:, 1] - ry,
                         np.full(len(bank), 1e6), nom[:, 1] + ry], axis=1)
    live_top = max(3, int(cfg["live_top_n"]))
    det_live = {}
    rm = float(cfg["map_search_px"]) * scale
    t_live, t_map = 0.0, 0.0
    for key in g.pairs:
        _, i, j = key
        if j not in det_live:
            live = _load(place, j, scale)
            if st["colour_constancy"]:
                live = local_exact_histogram_match(live, images[0], (5, 5))
            t0 = time.perf_counter()
            live_pyr = hogmod.build_pyramid(live, bank.hog, levels=bank.levels())
            det_live[j] = bank.detect(live_pyr, windows=live_win, top_n=live_top)
            t_live += time.perf_counter() - t0
        img = images[g.train.index(i)] if i in g.train else _load(place, i, scale)
        cx = nom[:, 0] + map_offset[i]
        win = np.stack([cx - rm, nom[:, 1] - rm, cx + rm, nom[:, 1] + rm], axis=1)
        t0 = time.perf_counter()
        det_map = bank.detect(hogmod.build_pyramid(img, bank.hog, levels=bank.levels()),
                              windows=win)
        t_map += time.perf_counter() - t0
        recs[key] = _vote_pair(det_map, det_live[j], cfg, scale, spread)
    # detection cost: a live image is searched over its whole width, the map image near the trained
    # positions (features plus scoring, per image)
    st["live_detect_seconds"], st["live_images"] = t_live, len(det_live)
    st["map_detect_seconds"], st["map_images"] = t_map, len(g.pairs)
    return recs, st


def bank_config(cfg: dict, appearances: int) -> dict:
    """The settings one bank votes with: ``cfg`` after the training-data rule (module docstring).

    ``appearances`` is the number of real training images of the place the bank was mined from
    (augmented copies do not count).  Adds ``calibrated`` (bool).
    """
    out = dict(cfg)
    out["calibrated"] = int(appearances) >= int(cfg["calibrated_min_appearances"])
    if not out["calibrated"]:
        out["min_prob"], out["prob_weight"] = 0.0, 0.0
    return out


def _vote_pair(det_map, det_live, cfg, scale, spread) -> PairRecord:
    """Weighted mode of x_live - x_map over the classifiers that fire in both images.

    Weights: the two detection probabilities times ``1 / (1 + (spread_x / sigma)^2)^2``.  A
    signature whose training firings strayed from the alignment (near structure whose image
    position depends on where the robot stood, or an unstable filter) votes little: its
    displacement mixes heading with parallax.  With ``live_top_n > 1`` the r-th best live
    detection of a classifier votes too, weighted by ``rank_decay ** r``.
    """
    pm = det_map.prob[:, 0]
    n_top = int(cfg["live_top_n"])
    pl = det_live.prob[:, :n_top]
    votes = (det_live.x[:, :n_top] - det_map.x[:, :1]) / scale          # (n, n_top)
    fired = (pm[:, None] >= cfg["min_prob"]) & (pl >= cfg["min_prob"]) & np.isfinite(votes)
    use = fired if fired[:, 0].sum() >= int(cfg["min_votes"]) else np.isfinite(votes)
    sx = np.nan_to_num(spread[:, 0], nan=1e3)
    w = np.where(use, (np.nan_to_num(pm)[:, None] * np.nan_to_num(pl))
                 ** float(cfg["prob_weight"]), 0.0)
    w = w / ((1.0 + (sx / float(cfg["spread_sigma_px"])) ** 2) ** 2)[:, None]
    w = w * float(cfg["rank_decay"]) ** np.arange(n_top)[None, :]
    est, inl = densest_window_displacement(votes.ravel(), w.ravel(), float(cfg["vote_window_px"]))
    return PairRecord(est, det_map.boxes(0) / scale, det_live.boxes(0) / scale, votes[:, 0],
                      fired[:, 0], inl.reshape(votes.shape).any(axis=1), len(votes), spread,
                      live_top=np.stack([det_live.x, det_live.prob], axis=2),
                      map_x=det_map.x[:, 0], map_prob=pm)


def estimate_heading_signatures(dataset, pairs, progress: bool = True, config: dict | None = None,
                                n_jobs: int = 1) -> list[float]:
    """Signature-method displacement estimates (full-resolution px) for GRIEF protocol pairs.

    Parameters
    ----------
    dataset : surveys.grief.GriefDataset or path
    pairs : iterable of (place, map, live)
        ``GriefPair`` tuples from ``dataset.pairs()``.
    progress : bool
    config : dict, optional
        Overrides of :data:`default_config`.
    n_jobs : int
        Banks processed in parallel.

    Returns
    -------
    list of float
        One estimate per pair (NaN where no classifier survived mining).
    """
    return SignatureHeading(dataset, config, n_jobs, progress).estimate(list(pairs))
