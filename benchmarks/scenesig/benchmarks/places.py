"""Place recognition on real appearance change: ``scenesig bench places DATASET --methods ... --json OUT``.

The retrieval a localiser without GPS does at start-up (:mod:`scenesig.localiser.relocalise`), on real images
instead of the simulator: given a live image, which place of the map is it?

Protocols (GRIEF data, ``../shared/data/grief``; :mod:`scenesig.surveys.grief`)

``season`` (sequence layout)
    the 101 summer frames (``season_00``) are the map, one place each; the 101 winter frames
    (``season_01``) are the queries, in driving order.  A retrieval is correct when it names a place
    within ``tolerance`` = 1 frame of the query's own.
``stromovka`` (sessions layout)
    for every session j, the 5 images of session j are the queries and the images of the other 11
    sessions the map (a place scores its best image); ``tolerance`` = 0 (the exact place).  The
    numbers are over all 12 x 5 queries.

Methods (one harness; every method sees the same map images and queries)

``signatures``
    what a scenesig map stores, and the localiser's own retrieval: the compact whole-image
    descriptors of :mod:`scenesig.signatures.globaldesc` shortlist ``shortlist`` places, and each
    shortlisted place's bank verifies: it is searched across the whole query image (rows near its
    trained row) and its classifiers vote for a horizontal displacement (the GRIEF analogue of the
    pose solve, :func:`scenesig.signatures.heading.densest_window_displacement`); the place whose votes agree best
    (the share of vote weight in the densest 20-px window) wins; places outside the shortlist keep
    their descriptor order behind the shortlist.  Banks are mined as in ``bench heading`` -- on
    season from augmented copies of the summer image only, on stromovka leave-one-session-out (never
    from the query's session) -- with the reduced candidate template of :data:`SIGNATURE_MINING`
    (96 shapes instead of 296; mining a full bank per place for all 101 season places takes hours on
    two cores).  Single image: no neighbouring queries are used.  ``shortlist`` is a number of
    places or a share of them (``"40%"``).
``signatures-seq``
    the same verifications, reasoned over a sequence as the localiser's global localisation does
    (:mod:`scenesig.localiser.relocalise`: a fix needs agreeing verifications from several frames).  On GRIEF
    there is no odometry; the queries are neighbouring frames in driving order, one per place, so
    place p for query q scores the mean verification of the diagonal (q - k, p - k), k = 0 ..
    ``sequence_length`` - 1 (:func:`sequence_scores`).  Every query is verified once, so its cost
    per query is the single-image method's (the sequence adds a few additions).
``hog``
    whole-image HOG (the same :func:`scenesig.signatures.globaldesc.describe`), nearest neighbour by cosine.
``seqslam``
    SeqSLAM (Milford & Wyeth, ICRA 2012): 64x32 patch-normalised (8x8 patches) gray thumbnails, the
    sum of absolute differences, local contrast enhancement over 10 map places, and a sequence search
    over the query and its **previous** ``sequence_length`` - 1 **queries** (straight lines through
    the difference matrix, speeds 0.8-1.25 places per query) -- the same sequence length as
    ``signatures-seq``.
``vlad``
    SIFT (OpenCV, up to 1000 per image on a 512-px-wide gray image, RootSIFT) aggregated by VLAD
    (Jegou et al. 2010) on a 64-word k-means vocabulary (scikit-learn, fitted on the map images
    only), intra-normalised and power-normalised; nearest neighbour by cosine.

``--protocol single-session`` (sessions layout only) is a development protocol: every ordered pair of
sessions, one session's images the map (one image per place, like season), the other's the queries;
:mod:`scenesig.benchmarks.places_select` chooses the descriptor, shortlist and sequence length on it.

Output JSON: ``{"dataset", "protocol", "queries", "places", "tolerance", "methods": {NAME: {"recall_at_1",
"recall_at_5", "seconds_per_query"}}}`` (plus ``recall_at_n`` for N = 1..20 and ``seconds_map``
per method), a printed table, and ``places_<dataset>.png``: recall@N per method.
``seconds_per_query`` is the query side only (descriptor, shortlist, verification); building the
map (mining, vocabulary) is ``seconds_map`` (0 for banks read from ``--cache``).  The signature
methods add ``shortlist`` (places verified), the sequence methods ``sequence_length``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from scenesig.surveys.grief import GriefDataset, load

__all__ = ["default_config", "METHODS", "PROTOCOLS", "SIGNATURE_MINING", "Protocol", "protocols", "recall_at",
           "shortlist_size", "sequence_scores", "run_benchmark", "main"]

METHODS = ("signatures", "signatures-seq", "hog", "seqslam", "vlad")
PROTOCOLS = ("standard", "single-session")

#: Reduced candidate template for the signatures method's banks (see the module docstring).
SIGNATURE_MINING = {"shapes": {"kinds": [{"name": "square-s", "size": 0.15, "aspect": 1.0, "nx": 8, "ny": 4},
                                         {"name": "wide", "size": 0.20, "aspect": 2.0, "nx": 5, "ny": 4},
                                         {"name": "tall", "size": 0.20, "aspect": 0.5, "nx": 8, "ny": 3}]}}

default_config = {
    "max_n": 20,                      # recall@N reported for N = 1..max_n
    # signatures: places verified per query (an int, or a share: "40%"); 40 % and the sequence length
    # were chosen on stromovka's single-session protocol (benchmarks/places_select.py), never on season
    "shortlist": "40%",
    "sequence_length": 3,             # signatures-seq and seqslam: frames per sequence
    "cache": None,                    # folder caching mined banks (CLI --cache)
    # overrides of signatures.globaldesc.default_config (hog, signatures); chosen on stromovka's
    # single-session protocol (benchmarks/places_select.py, docs/cross_validation.md), never on season
    "descriptor": {"kind": "hog", "width": 128, "cell": 16},
    "heading": {"mining": SIGNATURE_MINING, "augment_copies": 6},  # signatures.heading overrides
    "seqslam": {"size": (64, 32), "patch": 8, "enhance": 10, "v_min": 0.8, "v_max": 1.25,
                "n_v": 10},
    "vlad": {"words": 64, "features": 1000, "width": 512, "seed": 0},
}


# ---------------------------------------------------------------------------------- protocol
@dataclass
class Protocol:
    """One retrieval problem: map images with their place, queries with their true place."""

    name: str
    map_images: list            # (place, session) of every map image
    queries: list               # (place, session) of every query, in driving order
    places: int
    tolerance: int
    live: int                   # the query session (stromovka: leave it out of the banks)


def protocols(ds: GriefDataset, kind: str = "standard") -> list[Protocol]:
    """season: one protocol; stromovka: one per query session.

    ``kind="single-session"`` (sessions layout only; a development protocol) makes every ordered
    pair of sessions (i, j) a protocol: session i's images are the map (one image per place, as on
    season) and session j's the queries, exact place (132 protocols of 5 queries on stromovka).
    """
    n = len(ds.places)
    if kind not in PROTOCOLS:
        raise ValueError(f"unknown protocol {kind!r}; choose from {', '.join(PROTOCOLS)}")
    if kind == "single-session":
        if ds.kind == "sequence":
            raise ValueError(f"{ds.root}: the single-session protocol needs a sessions layout (images/ + ground_truth/)")
        out = []
        for i in range(ds.n_sessions):
            for j in range(ds.n_sessions):
                m = [(p, i) for p in range(n) if i in ds.places[p].sessions]
                q = [(p, j) for p in range(n) if j in ds.places[p].sessions]
                if i != j and m and q:
                    out.append(Protocol(f"{ds.name}/map{i + 1:02d}-live{j + 1:02d}", m, q, n, 0, -1))
        return out
    if ds.kind == "sequence":
        return [Protocol(ds.name, [(p, 0) for p in range(n)], [(p, 1) for p in range(n)], n, 1, 1)]
    out = []
    for j in range(ds.n_sessions):
        q = [(p, j) for p in range(n) if j in ds.places[p].sessions]
        m = [(p, s) for p in range(n) for s in ds.places[p].sessions if s != j]
        if q:
            out.append(Protocol(f"{ds.name}/session{j + 1:02d}", m, q, n, 0, j))
    return out


def _gray(ds, ps, width=None):
    img = ds.places[ps[0]].image(ps[1], gray=True)
    if width is not None and img.shape[1] != width:
        img = cv2.resize(img, (width, round(img.shape[0] * width / img.shape[1])), interpolation=cv2.INTER_AREA)
    return img


def _per_place(sim: np.ndarray, owner: np.ndarray, n_places: int) -> np.ndarray:
    """(Q, M) image similarities -> (Q, P): the best image of each place (higher is better)."""
    out = np.full((sim.shape[0], n_places), -np.inf)
    for p in range(n_places):
        cols = owner == p
        if cols.any():
            out[:, p] = sim[:, cols].max(axis=1)
    return out


def recall_at(scores: np.ndarray, truth: np.ndarray, tolerance: int, max_n: int) -> np.ndarray:
    """recall@N, N = 1..max_n: the share of queries with a place within ``tolerance`` among the N best."""
    order = np.argsort(-scores, axis=1, kind="stable")[:, :max_n]
    hit = np.abs(order - truth[:, None]) <= tolerance
    rec = np.cumsum(hit, axis=1).clip(max=1).mean(axis=0)
    return np.concatenate([rec, np.full(max_n - len(rec), rec[-1] if len(rec) else 0.0)])   # N beyond the places


# ---------------------------------------------------------------------------------- methods
def _cpu(timing: dict | None, c0: float) -> None:
    """Record the CPU seconds since ``c0`` (all threads of the process) in ``timing["cpu"]``."""
    if timing is not None:
        timing["cpu"] = time.process_time() - c0


def _hog(ds, pr: Protocol, cfg: dict, timing: dict | None = None):
    from scenesig.signatures import globaldesc

    dcfg = cfg.get("descriptor") or None
    M = np.stack([globaldesc.describe(_gray(ds, m), dcfg) for m in pr.map_images])
    t0, c0 = time.perf_counter(), time.process_time()
    Q = np.stack([globaldesc.describe(_gray(ds, q), dcfg) for q in pr.queries])
    s = _per_place(Q @ M.T, np.array([m[0] for m in pr.map_images]), pr.places)
    _cpu(timing, c0)
    return s, time.perf_counter() - t0, 0.0


def _thumb(img, size, patch):
    t = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA).astype(np.float32)
    h, w = t.shape
    b = t.reshape(h // patch, patch, w // patch, patch)
    b = (b - b.mean(axis=(1, 3), keepdims=True)) / (b.std(axis=(1, 3), keepdims=True) + 1e-3)
    return b.reshape(h, w)


def _seqslam(ds, pr: Protocol, cfg: dict, timing: dict | None = None):
    c = cfg["seqslam"]
    M = np.stack([_thumb(_gray(ds, m), c["size"], c["patch"]).ravel() for m in pr.map_images])
    t0, c0 = time.perf_counter(), time.process_time()
    Q = np.stack([_thumb(_gray(ds, q), c["size"], c["patch"]).ravel() for q in pr.queries])
    D = np.abs(Q[:, None, :] - M[None, :, :]).mean(axis=2)                  # (Q, M)
    D = -_per_place(-D, np.array([m[0] for m in pr.map_images]), pr.places)  # best image of a place
    # local contrast enhancement along the map (SeqSLAM's Eq. 1)
    P = D.shape[1]
    r = int(c["enhance"]) // 2
    E = np.empty_like(D)
    for p in range(P):
        win = D[:, max(0, p - r):min(P, p + r + 1)]
        E[:, p] = (D[:, p] - win.mean(axis=1)) / (win.std(axis=1) + 1e-6)
    # sequence search over the previous `length` queries, straight lines of speed v (places/query)
    L = int(cfg["sequence_length"])
    speeds = np.linspace(c["v_min"], c["v_max"], int(c["n_v"]))
    n = len(pr.queries)
    S = np.full((n, P), -np.inf)
    for q in range(n):
        k = np.arange(min(L, q + 1))
        for p in range(P):
            best = np.inf
            for v in speeds:
                cols = np.round(p - v * k).astype(int)
                ok = (cols >= 0) & (cols < P)
                if ok.any():
                    best = min(best, float(E[q - k[ok], cols[ok]].mean()))
            S[q, p] = -best
    _cpu(timing, c0)
    return S, time.perf_counter() - t0, 0.0


def _vlad_features(img, sift, width):
    img = cv2.resize(img, (width, round(img.shape[0] * width / img.shape[1])), interpolation=cv2.INTER_AREA)
    _, d = sift.detectAndCompute(img, None)
    if d is None:
        return np.zeros((0, 128), np.float32)
    d = np.sqrt(d / (d.sum(axis=1, keepdims=True) + 1e-7))     # RootSIFT
    return d.astype(np.float32)


def _vlad_encode(d, centres):
    k, dim = centres.shape
    v = np.zeros((k, dim), np.float32)
    if len(d):
        a = np.argmin(((d[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        np.add.at(v, a, d - centres[a])
    v /= np.linalg.norm(v, axis=1, keepdims=True) + 1e-12          # intra-normalisation
    v = np.sign(v) * np.sqrt(np.abs(v))
    v = v.ravel()
    return v / (np.linalg.norm(v) + 1e-12)


def _vlad(ds, pr: Protocol, cfg: dict, timing: dict | None = None):
    from sklearn.cluster import MiniBatchKMeans

    c = cfg["vlad"]
    sift = cv2.SIFT_create(nfeatures=int(c["features"]))
    t_map = time.perf_counter()
    feats = [_vlad_features(_gray(ds, m), sift, int(c["width"])) for m in pr.map_images]
    allf = np.concatenate([f for f in feats if len(f)])
    rng = np.random.default_rng(int(c["seed"]))
    sample = allf[rng.choice(len(allf), size=min(len(allf), 50000), replace=False)]
    km = MiniBatchKMeans(n_clusters=int(c["words"]), random_state=int(c["seed"]), n_init=3, batch_size=2048)
    centres = km.fit(sample).cluster_centers_.astype(np.float32)
    M = np.stack([_vlad_encode(f, centres) for f in feats])
    t_map = time.perf_counter() - t_map
    t0, c0 = time.perf_counter(), time.process_time()
    Q = np.stack([_vlad_encode(_vlad_features(_gray(ds, q), sift, int(c["width"])), centres) for q in pr.queries])
    s = _per_place(Q @ M.T, np.array([m[0] for m in pr.map_images]), pr.places)
    _cpu(timing, c0)
    return s, time.perf_counter() - t0, t_map


def _mine(args):
    ds_root, place, train, live, hcfg = args
    from scenesig.signatures import heading

    # a GRIEF folder is passed by path (each worker reads it); any other data set object as it is
    ds = load(ds_root) if isinstance(ds_root, (str, Path)) else ds_root
    bank, _, _, st = heading.train_bank(ds, place, train, live, hcfg)
    return place, bank, st


def shortlist_size(value, places: int) -> int:
    """Places verified per query: an integer, or a share of the map's places (``"40%"`` or 0.4)."""
    if isinstance(value, str) and value.strip().endswith("%"):
        frac = float(value.strip()[:-1]) / 100.0
    elif isinstance(value, float) and value < 1.0:
        frac = value
    else:
        n = int(value)
        if n < 1:
            raise ValueError(f"shortlist must be >= 1 place or a share such as 40%, got {value!r}")
        return min(n, places)
    if not 0.0 < frac <= 1.0:
        raise ValueError(f"shortlist share must be in (0, 100%], got {value!r}")
    return max(1, min(places, int(round(frac * places))))


def _heading_config(cfg: dict) -> dict:
    """The bank settings: the heading benchmark's one configuration with this benchmark's overrides."""
    from scenesig.signatures import heading
    from scenesig.surveys.settings import merge_settings

    # heading's one configuration for both layouts (a training-data rule, not per-layout overrides)
    return merge_settings(heading.default_config, cfg["heading"] or None, "heading",
                          open=("mining", "single_experience"))


def _verify(ds, pr: Protocol, cfg: dict, jobs: int = 1, progress: bool = True, banks_cache: dict | None = None,
            timing: dict | None = None):
    """Descriptor shortlist + bank verification of every query (module docstring).

    Returns ``(desc, verified, seconds, seconds_map)``: ``desc`` (Q, P) descriptor similarities (a
    place scores its best map image), ``verified`` (Q, P) the verification score of the shortlisted
    places (share of vote weight in the densest window) and NaN elsewhere.  ``timing``, when given,
    receives the query side's CPU seconds (``"cpu"``).
    """
    from joblib import Parallel, delayed

    from scenesig.signatures import globaldesc, heading, hog as hogmod, mining

    hcfg = _heading_config(cfg)
    scale = float(hcfg["scale"])
    banks_cache = {} if banks_cache is None else banks_cache
    t_map = time.perf_counter()
    # the map: per place a bank (never trained on the query session) and its images' descriptors
    train = {p: sorted({s for q, s in pr.map_images if q == p}) for p in range(pr.places)}
    disk = None
    if cfg.get("cache"):
        # mined banks on disk, keyed by everything that decides them (re-runs skip the mining)
        key = json.dumps({"data": str(Path(ds.root).resolve()), "heading": hcfg}, sort_keys=True, default=str)
        disk = Path(cfg["cache"]) / hashlib.sha1(key.encode()).hexdigest()[:16]
    for p in range(pr.places):
        k = (p, tuple(train[p]), pr.live)
        f = disk / f"bank_{p}_{'-'.join(map(str, train[p]))}_{pr.live}.pkl" if disk is not None else None
        if train[p] and k not in banks_cache and f is not None and f.is_file():
            banks_cache[k] = pickle.loads(f.read_bytes())
    todo = [p for p in range(pr.places) if train[p] and (p, tuple(train[p]), pr.live) not in banks_cache]
    tasks = [(str(ds.root) if isinstance(ds, GriefDataset) else ds, p, train[p], pr.live, hcfg) for p in todo]
    if tasks:
        gen = Parallel(n_jobs=jobs, return_as="generator")(delayed(_mine)(t) for t in tasks)
        if progress:
            from tqdm import tqdm
            gen = tqdm(gen, total=len(tasks), desc=f"banks {pr.name}", unit="bank")
        for p, b, _ in gen:
            banks_cache[(p, tuple(train[p]), pr.live)] = b
            if disk is not None:
                disk.mkdir(parents=True, exist_ok=True)
                f = disk / f"bank_{p}_{'-'.join(map(str, train[p]))}_{pr.live}.pkl"
                tmp = f.with_name(f.name + ".tmp")
                tmp.write_bytes(pickle.dumps(b))
                os.replace(tmp, f)
    banks = {p: banks_cache[(p, tuple(train[p]), pr.live)] for p in range(pr.places) if train[p]}
    dcfg = cfg.get("descriptor") or None
    D = np.stack([globaldesc.describe(_gray(ds, m), dcfg) for m in pr.map_images])
    owner = np.array([m[0] for m in pr.map_images])
    t_map = time.perf_counter() - t_map
    hog_cfg = mining.resolve_config(dict(hcfg["mining"]))["hog"]
    ry = float(hcfg["live_search_y_px"]) * scale
    window = float(hcfg["vote_window_px"])
    K = shortlist_size(cfg["shortlist"], pr.places)
    t0, c0 = time.perf_counter(), time.process_time()
    desc = np.full((len(pr.queries), pr.places), -np.inf)
    V = np.full((len(pr.queries), pr.places), np.nan)
    for qi, q in enumerate(pr.queries):
        desc[qi] = _per_place(globaldesc.describe(_gray(ds, q), dcfg)[None] @ D.T, owner, pr.places)[0]
        order = np.argsort(-desc[qi], kind="stable")
        img = heading._load(ds.places[q[0]], q[1], scale)
        pyramids = {}                       # one HOG pyramid per level set, shared by the shortlist
        for p in order[:K]:
            bank = banks.get(int(p))
            if bank is None or not len(bank):
                V[qi, p] = 0.0
                continue
            lv = tuple(bank.levels())
            if lv not in pyramids:
                pyramids[lv] = hogmod.build_pyramid(img, hog_cfg, levels=bank.levels())
            nom = np.array([c.nominal_xy for c in bank])
            win = np.stack([np.full(len(bank), -1e6), nom[:, 1] - ry, np.full(len(bank), 1e6), nom[:, 1] + ry], axis=1)
            det = bank.detect(pyramids[lv], windows=win, top_n=1)
            votes = (det.x[:, 0] - nom[:, 0]) / scale
            spread = np.nan_to_num(np.array([c.spread[0] for c in bank]) / scale, nan=1e3)
            w = 1.0 / (1.0 + (spread / float(hcfg["spread_sigma_px"])) ** 2) ** 2
            w = np.where(np.isfinite(votes), w, 0.0)
            _, inl = heading.densest_window_displacement(votes, w, window)
            V[qi, p] = float(w[inl].sum() / w.sum()) if w.sum() > 0 else 0.0
    _cpu(timing, c0)
    return desc, V, time.perf_counter() - t0, t_map


def single_scores(desc: np.ndarray, verified: np.ndarray) -> np.ndarray:
    """Single-image ranking: the shortlist by verification first, then every other place by descriptor."""
    return np.where(np.isfinite(verified), 2.0 + np.nan_to_num(verified), desc)


def sequence_scores(desc: np.ndarray, verified: np.ndarray, length: int) -> np.ndarray:
    """Sequence ranking (``signatures-seq``): place p for query q scores the mean verification of
    the diagonal (q - k, p - k), k = 0..length-1 -- the query's ``length - 1`` predecessors in
    driving order must have verified at the map's preceding places.  Odometry-free: on GRIEF the
    query and map sequences hold one frame per place, so the vehicle advances one place per query.
    A place outside a frame's shortlist contributes 0 for that frame, and so does a predecessor
    before the map's first place; near the start of the query sequence fewer frames are used.  Ties
    keep the single-image order.
    """
    Q, P = verified.shape
    f = np.nan_to_num(verified, nan=0.0)
    total = np.zeros((Q, P))
    for k in range(int(length)):
        if k >= Q or k >= P:
            break
        total[k:, k:] += f[:Q - k, :P - k]
    # divided by the frames the query has (not the diagonal's length): a place near the map's start
    # cannot win on a shorter, luckier diagonal
    frames = np.minimum(np.arange(Q) + 1, int(length))[:, None]
    seq = total / frames
    single = single_scores(desc, verified)
    rank = np.argsort(np.argsort(-single, axis=1, kind="stable"), axis=1)   # 0 = best single
    return seq + 1e-9 * (P - rank)                   # the single-image order breaks exact ties only


_RUNNERS = {"hog": _hog, "seqslam": _seqslam, "vlad": _vlad}


# ---------------------------------------------------------------------------------- harness
def run_benchmark(dataset_path, methods=METHODS, json_path=None, jobs: int = 1, progress: bool = True,
                  config: dict | None = None, protocol: str = "standard") -> dict:
    """Run the protocol(s) of a GRIEF data set; returns (and writes) the JSON document."""
    cfg = {**default_config, **(config or {})}
    methods = [m.strip() for m in methods if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise ValueError(f"unknown method(s) {', '.join(bad) or '(none given)'}; choose from {', '.join(METHODS)}")
    if int(cfg["sequence_length"]) < 1:
        raise ValueError(f"sequence length must be >= 1, got {cfg['sequence_length']!r}")
    ds = load(dataset_path)
    prs = protocols(ds, protocol)
    shortlist_size(cfg["shortlist"], prs[0].places)           # a bad value fails before any work
    max_n = int(cfg["max_n"])
    doc = {"dataset": ds.name, "protocol": protocol, "queries": sum(len(p.queries) for p in prs),
           "places": prs[0].places, "tolerance": prs[0].tolerance, "methods": {}}
    verified = {}                     # protocol name -> (desc, V, seconds, seconds_map): shared by both signature methods
    banks_cache: dict = {}
    for name in methods:
        hits, secs, smap, nq = np.zeros(max_n), 0.0, 0.0, 0
        for pr in prs:
            if name in ("signatures", "signatures-seq"):
                first = pr.name not in verified
                if first:
                    verified[pr.name] = _verify(ds, pr, cfg, jobs, progress, banks_cache)
                desc, V, s, sm = verified[pr.name]
                sm = sm if first else 0.0     # the map is built once for both
                S = single_scores(desc, V) if name == "signatures" else \
                    sequence_scores(desc, V, int(cfg["sequence_length"]))
            else:
                S, s, sm = _RUNNERS[name](ds, pr, cfg)
            truth = np.array([q[0] for q in pr.queries])
            hits += recall_at(S, truth, pr.tolerance, max_n) * len(truth)
            secs, smap, nq = secs + s, smap + sm, nq + len(truth)
        rec = hits / nq
        doc["methods"][name] = {"recall_at_1": float(rec[0]), "recall_at_5": float(rec[min(4, max_n - 1)]),
                                "seconds_per_query": secs / nq, "recall_at_n": [float(v) for v in rec],
                                "seconds_map": smap}
        if name in ("signatures", "signatures-seq"):
            doc["methods"][name]["shortlist"] = shortlist_size(cfg["shortlist"], prs[0].places)
        if name in ("signatures-seq", "seqslam"):
            doc["methods"][name]["sequence_length"] = int(cfg["sequence_length"])
        print(f"{name}: recall@1 {rec[0]:.3f}, recall@5 {rec[min(4, max_n - 1)]:.3f}, "
              f"{1e3 * secs / nq:.1f} ms/query", file=sys.stderr)
    if json_path is not None:
        json_path = Path(json_path)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = json_path.with_name(json_path.name + ".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        os.replace(tmp, json_path)
        figure(doc, json_path.parent / f"places_{ds.name}.png")
    print(json.dumps({k: v for k, v in doc.items() if k != "methods"} | {
        "methods": {m: {k: v[k] for k in ("recall_at_1", "recall_at_5", "seconds_per_query")}
                    for m, v in doc["methods"].items()}}, indent=1))
    return doc


def figure(doc: dict, path: Path) -> Path:
    """recall@N per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, m in doc["methods"].items():
        r = m["recall_at_n"]
        ax.plot(np.arange(1, len(r) + 1), r, "-o", ms=3, label=f"{name} (@1 {r[0]:.2f})",
                color={"signatures": "tab:red"}.get(name))
    ax.set_xlabel("N (places retrieved)")
    ax.set_ylabel("recall@N")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title(f"place recognition: {doc['dataset']} ({doc['queries']} queries, {doc['places']} places, "
                 f"tolerance {doc['tolerance']})", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scenesig bench places", description=__doc__.split("\n")[0])
    p.add_argument("dataset", help="a GRIEF-layout folder (season_00/ + season_01/, or images/ + ground_truth/)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated, from {', '.join(METHODS)}")
    p.add_argument("--json", required=True, help="output JSON file (the figure goes beside it)")
    p.add_argument("--jobs", type=int, default=2, help="processes mining the signature banks")
    p.add_argument("--shortlist", default=str(default_config["shortlist"]),
                   help="signatures, signatures-seq: places verified per query, N or a share of the places (40%%)")
    p.add_argument("--sequence-length", type=int, default=default_config["sequence_length"],
                   help="signatures-seq and seqslam: frames per sequence (the query and its predecessors)")
    p.add_argument("--protocol", choices=PROTOCOLS, default="standard",
                   help="single-session: every session pair as a one-image map and its queries "
                        "(sessions layout; a development protocol)")
    p.add_argument("--cache", default=None,
                   help="folder caching the mined signature banks (a re-run skips the mining), e.g. maps/places_banks")
    args = p.parse_args(argv)
    sl = args.shortlist.strip()
    try:
        shortlist = sl if sl.endswith("%") else int(sl)
    except ValueError:
        print(f"scenesig bench places: error: --shortlist {sl!r}: expected N or a share such as 40%", file=sys.stderr)
        return 2
    try:
        run_benchmark(args.dataset, args.methods.split(","), args.json, jobs=max(1, args.jobs),
                      config={"shortlist": shortlist, "sequence_length": args.sequence_length, "cache": args.cache},
                      protocol=args.protocol)
    except ValueError as exc:
        print(f"scenesig bench places: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "places", *sys.argv[1:]]))
