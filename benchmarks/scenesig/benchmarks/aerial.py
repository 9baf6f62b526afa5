"""Aerial scene-matching benchmark: the Monte-Carlo protocol of Jin et al. 2016 (§4.3) on real tiles.

Per trial a 400 x 300 sensed image is cut from a random tile at a random position, scaled by
U[0.9, 1.1], rotated by U[-10, 10] deg and given a random photometric change
(:mod:`scenesig.aerial.trials` states the ranges); every method estimates where the sensed centre lies on
that tile, and a trial succeeds when the estimate is within 25 px (the paper's criterion).

Methods: ``mrsmcc`` (MRSM-CC), ``mrsm`` (the same without colour constancy), ``sism`` (whole-image
NCC), ``sift`` / ``orb`` (ratio 0.8 + RANSAC affine), ``signatures`` (a bank mined per tile from
augmented copies, detections + RANSAC affine); ``psd-point`` / ``psd-kdm`` / ``psd-kdmm`` (the
point-set-domain seed's three stages, :mod:`scenesig.aerial.psd`) and ``xfeat-dapc`` / ``xfeat-gms`` /
``sift-dapc`` / ``sift-gms`` (seeds 002 / 004's match filters), which add ``matched_pairs`` and
``putative_match_ratio``.  ``--deform`` / ``--recolour`` draw deformed / recoloured trials
(:mod:`scenesig.aerial.deform`; the default trials are unchanged); ``--measures`` adds the
point-set-domain seed's measures (``benchmarks/_aerial_measures.py``).

JSON (stdout and ``--json OUT``)::

    {"tiles": 8, "trials": 200, "success_px": 25,
     "methods": {NAME: {"success_rate", "mean_error_px", "median_error_px", "seconds_per_trial"}},
     ...}

``success_rate`` is a fraction; ``mean_error_px`` is over the successful trials (as the paper
reports it), ``median_error_px`` over all trials (a trial without an estimate counts as an infinite
error; null when more than half have none); ``seconds_per_trial`` is CPU time per trial of one
process with one thread (OpenCV, BLAS and FFT limited to one), so it measures one core even on a
loaded machine.  Setting up a method on the tiles (feature extraction, mining a bank) is offline map
work and reported apart, in ``setup_seconds``.  Results repeat for a seed.

Every method's JSON entry adds ``per_tile``: ``{TILE: {"trials", "success_rate"}}``.

**Cross-validation** (``--folds K``): trials drawn from the tiles the settings were chosen on do not
measure generalisation.  Tile i is in fold i mod K; for each fold every method's settings are chosen
among :data:`SEARCH` on ``--search-trials`` trials over the other folds' tiles (:func:`choose`: the
highest success, ties to the faster), the MRSM-CC landmark library learns from those tiles only, and
the fold's own tiles -- never seen by the search -- give the reported trials (k = f, f + K, ...).
The JSON adds ``folds`` (tiles, every candidate's training figures, the chosen settings).  Where
candidates tie on training success the faster wins, so on a loaded machine the chosen settings (not
the trials) may differ between runs of one seed.

**The defaults** (``--choose-defaults``): the same search on *all* tiles picks what each method's
``default_config`` holds (:func:`choose_defaults`; no trial is reported); ``--folds`` with K = the
number of tiles (leave one tile out) measures how that choice carries to a tile it did not see.

Run: ``scenesig aerial bench TILES_DIR --methods mrsmcc,sism,sift,orb,signatures --trials 200
--seed 1 --json out/aerial.json --figure out/aerial``.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

from scenesig.surveys.io import atomic_path, atomic_write_text

METHODS = ("mrsmcc", "mrsm", "sism", "sift", "orb", "xfeat", "signatures",
           "psd-point", "psd-kdm", "psd-kdmm", "xfeat-dapc", "xfeat-gms", "sift-dapc", "sift-gms")
#: Point-set-domain stages (:mod:`scenesig.aerial.psd`) and the point matchers with seeds 002 / 004's filters:
#: they always report matched pairs and the putative match ratio (every method does with ``--measures``).
PSD_METHODS = {"psd-point": "point", "psd-kdm": "kdm", "psd-kdmm": "kdmm"}
FILTER_METHODS = {"xfeat-dapc": ("xfeat", "dapc"), "xfeat-gms": ("xfeat", "gms"),
                  "sift-dapc": ("sift", "dapc"), "sift-gms": ("sift", "gms")}
SUCCESS_PX = 25.0


_FINE_ROTATIONS = (-10.0, -7.5, -5.0, -2.5, 0.0, 2.5, 5.0, 7.5, 10.0)   # attitude hypotheses every 2.5 deg
_COARSE_ROTATIONS = (-10.0, -5.0, 0.0, 5.0, 10.0)                     # every 5 deg
#: The MRSM-CC settings the search varies, at the values it varies the others around.
_MRSM_BASE = {"highpass_sigma": 12.0, "cc_grid": (5, 5), "max_iterations": 4,
              "attitude_rotations_deg": _FINE_ROTATIONS}


def _around(base: dict, *changes: dict) -> list:
    """``base`` and ``base`` with each of ``changes``: candidates that name every searched key, so
    the searched settings do not move when a method's defaults do."""
    return [{**base, **c} for c in ({},) + changes]


#: Cross-validation (``--folds K``) and ``--choose-defaults``: the settings each method's search
#: tries, each candidate naming the value of every key searched (the rest stay at the method's
#: ``default_config``).  MRSM-CC: the high-pass of the NCC (off, and three widths), the
#: colour-constancy window grid (the paper's 5 x 5, and 3 x 3), and for speed fewer iterations
#: and attitude hypotheses every 5 deg instead of 2.5; MRSM the same without colour constancy;
#: SISM the search resolution; SIFT / ORB Lowe's ratio; signatures the detection probability
#: (the banks do not depend on it).  The defaults are the candidates ``--choose-defaults`` picks
#: on all shared tiles (docs/aerial.md).
SEARCH = {
    "mrsmcc": _around(_MRSM_BASE, {"highpass_sigma": 0.0}, {"highpass_sigma": 6.0}, {"highpass_sigma": 24.0},
                      {"cc_grid": (3, 3)}, {"max_iterations": 2}, {"attitude_rotations_deg": _COARSE_ROTATIONS},
                      {"attitude_rotations_deg": _COARSE_ROTATIONS, "max_iterations": 2}),
    "mrsm": _around({k: v for k, v in _MRSM_BASE.items() if k != "cc_grid"},
                    {"highpass_sigma": 0.0}, {"highpass_sigma": 6.0}, {"highpass_sigma": 24.0},
                    {"max_iterations": 2}, {"attitude_rotations_deg": _COARSE_ROTATIONS}),
    "sism": [{"coarse_scale": 0.5}, {"coarse_scale": 0.25}],
    "sift": [{"ratio": 0.7}, {"ratio": 0.8}, {"ratio": 0.9}],
    "orb": [{"ratio": 0.7}, {"ratio": 0.8}, {"ratio": 0.9}],
    "signatures": [{"min_prob": 0.2}, {"min_prob": 0.3}, {"min_prob": 0.5}],
    "xfeat": [{}],      # its authors' matcher and settings (Potje et al. 2024): nothing to choose
    # point-set-domain: the settings the seed leaves open (docs/aerial.md: the defaults were chosen on seed 0)
    "psd-point": [{"min_cossim": 0.82}, {"min_cossim": 0.75}],
    "psd-kdm": [{"kdm": {}}, {"kdm": {"rho": 3.0}}, {"kdm": {"scales_px": (80.0, 160.0, 320.0)}}],
    "psd-kdmm": [{"kdmm": {}}, {"kdmm": {"delta": 1}}, {"kdmm": {"keep_fraction": 0.75}}],
    "xfeat-dapc": [{}], "xfeat-gms": [{}], "sift-dapc": [{}], "sift-gms": [{}],   # the seeds' filters as published
}


def method_defaults(method: str) -> dict:
    """A method's ``default_config`` (the module that holds its settings)."""
    from scenesig.aerial import mrsmcc, pointmatch, psd, signatures, sism

    module = {"mrsmcc": mrsmcc, "mrsm": mrsmcc, "sism": sism, "sift": pointmatch, "orb": pointmatch,
              "xfeat": pointmatch, "signatures": signatures, **dict.fromkeys(PSD_METHODS, psd),
              **dict.fromkeys(FILTER_METHODS, pointmatch)}[method]
    return module.default_config


def _same(a, b) -> bool:
    """Settings equality that does not tell a tuple from a list (JSON round trips turn one into the other)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return a == b


def searched_defaults(method: str) -> dict:
    """The method's defaults of the keys its search varies."""
    keys = dict.fromkeys(k for c in SEARCH[method] for k in c)
    defaults = method_defaults(method)
    return {k: defaults[k] for k in keys}


def _setup(method: str, images, landmarks, cache_dir, config: dict | None = None, feature_cache=None):
    """One fitted estimator per tile; returns (list, CPU seconds).  ``config`` overrides the
    method's settings."""
    from scenesig.aerial.mrsmcc import MRSMCC
    from scenesig.aerial.pointmatch import PointMatcher
    from scenesig.aerial.signatures import SignatureMatcher
    from scenesig.aerial.sism import SISM

    config = dict(config or {})
    t0 = time.process_time()
    if method in ("mrsmcc", "mrsm"):
        cfg = {**config, "colour_constancy": method == "mrsmcc"}
        ests = [MRSMCC(cfg, landmarks).fit(im) for im in images]
    elif method == "sism":
        ests = [SISM(config).fit(im) for im in images]
    elif method in ("sift", "orb"):
        ests = [PointMatcher({**config, "kind": method}).fit(im) for im in images]
    elif method == "xfeat":
        from scenesig.benchmarks._models import xfeat_model

        ests = [PointMatcher({**config, "kind": "xfeat", "xfeat": {"model": xfeat_model()}}).fit(im) for im in images]
    elif method == "signatures":
        ests = [SignatureMatcher(config, cache_dir=cache_dir).fit(im) for im in images]
    elif method in PSD_METHODS:
        from scenesig.aerial.psd import PSDMatcher
        from scenesig.benchmarks._models import xfeat_model

        cfg = {**config, "stage": PSD_METHODS[method], "xfeat": {"model": xfeat_model()}, "cache": feature_cache}
        ests = [PSDMatcher(cfg).fit(im) for im in images]
    elif method in FILTER_METHODS:
        kind, filt = FILTER_METHODS[method]
        cfg = {**config, "kind": kind, "filter": filt}
        if kind == "xfeat":
            from scenesig.benchmarks._models import xfeat_model

            cfg["xfeat"] = {"model": xfeat_model()}
        ests = [PointMatcher(cfg).fit(im) for im in images]
    else:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return ests, time.process_time() - t0


def _run_trials(ests: dict, images, indices, seed: int, tile_names, progress=None, protocol=None,
                collector=None, results=None):
    """Run every method's estimators on trials ``indices`` of ``seed`` drawn over ``images``.

    ``protocol`` = ``{"deform": bool, "recolour": bool}`` draws the variant trials
    (:func:`scenesig.aerial.deform.make_trial_variant`); ``collector`` (``--measures``) also runs each
    trial's impostor pair and records the seed's measures; ``results`` (dict of lists) receives the
    estimates.  Returns ``(errors, seconds, rows)``: per method lists of errors (px; inf = no estimate)
    and CPU seconds, and the per-trial rows of ``trials.csv``.
    """
    import cv2

    from scenesig.aerial.trials import make_trial

    errors = {m: [] for m in ests}
    secs = {m: [] for m in ests}
    rows = []
    variant = bool(protocol) and any(protocol.values())
    if variant:
        from scenesig.aerial.deform import make_trial_variant
    for k in indices:
        tr = (make_trial_variant(images, k, seed, bool(protocol.get("deform")), bool(protocol.get("recolour")))
              if variant else make_trial(images, k, seed))
        row = {"trial": k, "tile": tile_names[tr.tile], "x": tr.centre[0], "y": tr.centre[1],
               "scale": tr.scale, "rotation_deg": tr.rotation_deg}
        for m in ests:
            cv2.setRNGSeed(int(seed) * 100003 + k)          # RANSAC repeats for a seed
            t1 = time.process_time()
            res = ests[m][tr.tile].locate(tr.image)
            # a feature extraction read from the disk cache counts at its recorded CPU time
            secs[m].append(time.process_time() - t1 + float(getattr(res, "extra_seconds", 0.0)))
            c = np.asarray(res.centre, float)
            err = float(np.linalg.norm(c - tr.centre)) if np.all(np.isfinite(c)) else np.inf
            errors[m].append(err)
            row[f"{m}_x"], row[f"{m}_y"], row[f"{m}_error_px"] = c[0], c[1], err
            if results is not None:
                results.setdefault(m, []).append(res)
            if collector is not None:
                rec = collector.add(m, tr, res, ests[m])
                row[f"{m}_score"], row[f"{m}_impostor_score"] = rec["score_genuine"], rec["score_impostor"]
        rows.append(row)
        if progress is not None:
            progress.update(1)
    return errors, secs, rows


def per_tile(rows: list, method: str) -> dict:
    """Per-tile success of one method: ``{tile: {"trials", "success_rate"}}`` (tiles in name order)."""
    out = {}
    for name in sorted({r["tile"] for r in rows}):
        e = np.array([r[f"{method}_error_px"] for r in rows if r["tile"] == name], float)
        out[name] = {"trials": int(len(e)), "success_rate": float(np.mean(e <= SUCCESS_PX))}
    return out


def choose(results: list) -> int:
    """The search's rule: the highest success rate on the training trials; ties (equal success)
    go to the fewer CPU seconds per trial.  ``results`` are :func:`summarise` dicts; returns an index."""
    return min(range(len(results)), key=lambda i: (-results[i]["success_rate"],
                                                   results[i]["seconds_per_trial"] or np.inf))


def summarise(errors: np.ndarray, seconds: np.ndarray) -> dict:
    """The four per-method figures from per-trial errors (inf = no estimate) and CPU seconds."""
    e = np.asarray(errors, dtype=float)
    ok = e <= SUCCESS_PX
    med = float(np.median(e)) if len(e) else float("nan")
    return {"success_rate": float(ok.mean()) if len(e) else float("nan"),
            "mean_error_px": float(e[ok].mean()) if ok.any() else None,
            "median_error_px": med if np.isfinite(med) else None,
            "seconds_per_trial": float(np.mean(seconds)) if len(seconds) else None}


def _search(methods, images, names, landmarks, cache_dir, search_trials: int, search_seed: int, bar=None,
            protocol=None, feature_cache=None):
    """Every method's :data:`SEARCH` on ``search_trials`` trials of ``search_seed`` over ``images``
    (deformed / recoloured as ``protocol`` says); returns ``(search, chosen)``: per method every
    candidate's figures, and the one :func:`choose` keeps."""
    search, chosen = {}, {}
    for m in methods:
        cands = SEARCH[m]
        res = []
        if len(cands) > 1:
            for c in cands:
                ests_c, _ = _setup(m, images, landmarks, cache_dir, c, feature_cache)
                e, sc, _ = _run_trials({m: ests_c}, images, range(int(search_trials)), search_seed, names,
                                       protocol=protocol)
                res.append({"config": c, **summarise(np.array(e[m]), np.array(sc[m]))})
            if bar is not None:
                bar.update(int(search_trials))
        chosen[m] = cands[choose(res)] if res else cands[0]
        search[m] = res
    return search, chosen


def choose_defaults(tiles_dir, methods=("mrsmcc",), search_trials: int = 40, search_seed: int = 0,
                    json_path=None, cache_dir=None, progress: bool = True) -> dict:
    """Choose every method's settings on *all* tiles, by the search of the folds (:data:`SEARCH`,
    :func:`choose`, ``search_trials`` trials of ``search_seed``; the landmark library learns from
    all tiles): what the methods' ``default_config`` should hold.

    No figure of this is a held-out one -- it is the selection step alone; ``--folds K`` with
    K = the number of tiles measures how this selection carries to a tile it did not see.  Returns
    (and writes to ``json_path``) ``{"tiles", "search_trials", "search_seed", "search", "chosen",
    "defaults", "defaults_are_chosen"}``: per method every candidate's figures, the chosen
    candidate, the current defaults of the searched keys, and whether they are the chosen ones.
    """
    import cv2
    from threadpoolctl import threadpool_limits

    from scenesig.aerial.geo import load_tiles
    from scenesig.aerial.landmarks import LandmarkModel

    methods = list(dict.fromkeys(methods))
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ValueError(f"unknown method(s) {', '.join(bad)}; choose from {', '.join(METHODS)}")
    if search_trials < 1:
        raise ValueError("--search-trials must be >= 1")
    cv2.setNumThreads(1)
    tiles = load_tiles(tiles_dir)
    images = [t.image() for t in tiles]
    names = [t.name for t in tiles]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=search_trials * sum(len(SEARCH[m]) > 1 for m in methods), desc="aerial search",
                   unit="trial", file=sys.stderr)
    with threadpool_limits(limits=1):
        landmarks = LandmarkModel().fit(images) if {"mrsmcc", "mrsm"} & set(methods) else None
        search, chosen = _search(methods, images, names, landmarks, cache_dir, search_trials, search_seed, bar)
    if bar is not None:
        bar.close()
    defaults = {m: searched_defaults(m) for m in methods}
    doc = {"tiles": names, "search_trials": int(search_trials), "search_seed": int(search_seed),
           "rule": "highest success rate on the search trials; ties to the fewer CPU seconds per trial",
           "search": search, "chosen": chosen, "defaults": defaults,
           "defaults_are_chosen": {m: _same({k: defaults[m][k] for k in chosen[m]}, chosen[m]) for m in methods}}
    if json_path is not None:
        json_path = Path(json_path)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(json_path, json.dumps(doc, indent=1, default=_jsonable) + "\n")
    return doc


def run_benchmark(tiles_dir, methods=("mrsmcc", "sism", "sift", "orb", "signatures"),
                  trials: int = 200, seed: int = 1, json_path=None, figure_dir=None,
                  cache_dir=None, progress: bool = True, folds: int | None = None,
                  search_trials: int = 40, search_seed: int = 0, deform: bool = False, recolour: bool = False,
                  measures: bool = False, feature_cache=None) -> dict:
    """Run the protocol; returns the JSON document (also written to ``json_path``).

    Per-trial rows (truth, estimates, errors) go to ``trials.csv`` beside the JSON.

    With ``folds`` = K >= 2 the tiles are cross-validated: tile i (``map.csv`` order) is in fold
    i mod K.  For each fold, every method's settings are chosen among :data:`SEARCH` by
    :func:`choose` on ``search_trials`` trials of ``search_seed`` drawn over the *other* folds'
    tiles (the landmark library, too, learns from those tiles only); then trials k = f, f + K, ...
    (k < ``trials``) of ``seed`` are drawn over the fold's own, held-out tiles and located with the
    chosen settings.  Every reported figure is a held-out one; the JSON adds ``folds`` (per fold:
    its training and held-out tiles, every candidate's training figures and the chosen settings).

    ``deform`` / ``recolour`` draw the variant trials of :mod:`scenesig.aerial.deform` (search trials too);
    ``measures`` adds the point-set-domain seed's measures per method (``benchmarks/_aerial_measures.py``);
    ``feature_cache`` is a folder keeping the point-set-domain methods' XFeat features.
    """
    import cv2
    from threadpoolctl import threadpool_limits

    from scenesig.aerial.geo import load_tiles
    from scenesig.aerial.landmarks import LandmarkModel
    from scenesig.aerial.trials import GEOMETRY, PHOTOMETRIC

    methods = list(dict.fromkeys(methods))
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ValueError(f"unknown method(s) {', '.join(bad)}; choose from {', '.join(METHODS)}")
    if trials < 1:
        raise ValueError("trials must be >= 1")
    cv2.setNumThreads(1)
    tiles = load_tiles(tiles_dir)
    images = [t.image() for t in tiles]
    names = [t.name for t in tiles]
    if folds is not None and not 2 <= int(folds) <= len(tiles):
        raise ValueError(f"--folds must be between 2 and the number of tiles ({len(tiles)}), got {folds}")
    if folds is not None and (search_trials < 1 or trials < int(folds)):
        raise ValueError(f"--search-trials must be >= 1 and --trials >= --folds ({folds})")
    bar = None
    if progress:
        from tqdm import tqdm
        searched = sum(len(SEARCH[m]) > 1 for m in methods)
        total = trials if folds is None else trials + int(folds) * search_trials * searched
        bar = tqdm(total=total, desc="aerial trials", unit="trial", file=sys.stderr)
    fold_docs = []
    protocol = {"deform": bool(deform), "recolour": bool(recolour)} if (deform or recolour) else None
    collector = None
    if measures:
        from scenesig.benchmarks._aerial_measures import MeasureCollector
        collector = MeasureCollector(images, seed)
    results: dict = {}
    with threadpool_limits(limits=1):
        if folds is None:
            setup, ests, landmarks = {}, {}, None
            if {"mrsmcc", "mrsm"} & set(methods):
                t0 = time.process_time()
                landmarks = LandmarkModel().fit(images)        # the landmark library: all tiles
                setup["landmarks"] = time.process_time() - t0
            for m in methods:
                ests[m], setup[m] = _setup(m, images, landmarks, cache_dir, feature_cache=feature_cache)
            errors, secs, rows = _run_trials(ests, images, range(int(trials)), seed, names, bar, protocol,
                                             collector, results)
        else:
            K = int(folds)
            setup = {m: 0.0 for m in methods}
            errors = {m: [] for m in methods}
            secs = {m: [] for m in methods}
            rows = []
            for f in range(K):
                test = [i for i in range(len(tiles)) if i % K == f]
                train = [i for i in range(len(tiles)) if i % K != f]
                tr_img, te_img = [images[i] for i in train], [images[i] for i in test]
                landmarks = None
                if {"mrsmcc", "mrsm"} & set(methods):
                    t0 = time.process_time()
                    landmarks = LandmarkModel().fit(tr_img)    # the landmark library: training tiles only
                    setup["landmarks"] = setup.get("landmarks", 0.0) + time.process_time() - t0
                fd = {"fold": f, "train_tiles": [names[i] for i in train], "test_tiles": [names[i] for i in test],
                      "search_trials": int(search_trials), "search_seed": int(search_seed)}
                fd["search"], fd["chosen"] = _search(methods, tr_img, [names[i] for i in train], landmarks,
                                                     cache_dir, search_trials, search_seed, bar, protocol,
                                                     feature_cache)
                chosen = fd["chosen"]
                ests = {}
                for m in methods:
                    ests[m], t = _setup(m, te_img, landmarks, cache_dir, chosen[m], feature_cache)
                    setup[m] += t
                idx = range(f, int(trials), K)
                if collector is not None:          # impostors: the fold's other held-out tiles
                    collector.images = te_img
                e, sc, r = _run_trials(ests, te_img, idx, seed, [names[i] for i in test], bar, protocol,
                                       collector, results)
                for m in methods:
                    errors[m] += e[m]
                    secs[m] += sc[m]
                fd["held_out"] = {m: summarise(np.array(e[m]), np.array(sc[m])) for m in methods}
                rows += r
                fold_docs.append(fd)
            order = np.argsort([r["trial"] for r in rows], kind="stable")
            rows = [rows[i] for i in order]
            errors = {m: [errors[m][i] for i in order] for m in methods}
            secs = {m: [secs[m][i] for i in order] for m in methods}
    if bar is not None:
        bar.close()
    if "xfeat" in methods:       # which model file ran (its sha256) and its settings
        from scenesig.signatures.xfeat import get_xfeat

        xfeat_info = get_xfeat(ests["xfeat"][0].config["xfeat"]).describe() if ests["xfeat"] else None
    doc = {"tiles": len(tiles), "trials": int(trials), "success_px": int(SUCCESS_PX),
           "methods": {m: {**summarise(np.array(errors[m]), np.array(secs[m])), "per_tile": per_tile(rows, m)}
                       for m in methods},
           **({"protocol": _protocol_doc(protocol)} if protocol else {}),
           "seed": int(seed), "best_method": None,
           "setup_seconds": {m: round(v, 2) for m, v in setup.items()},
           "seconds": "CPU seconds of one single-threaded process",
           "geometry": {k: list(v) for k, v in GEOMETRY.items()},
           **({"xfeat": xfeat_info} if "xfeat" in methods else {}),
           "photometric": {k: (list(v) if isinstance(v, tuple) else v)
                           for k, v in PHOTOMETRIC.items()}}
    if measures or set(methods) & (set(PSD_METHODS) | set(FILTER_METHODS)):
        from scenesig.benchmarks._aerial_measures import DEFINITIONS, matching_summary

        for m in methods:
            if measures or m in PSD_METHODS or m in FILTER_METHODS:
                doc["methods"][m].update(matching_summary(results.get(m, [])))
            if collector is not None:
                doc["methods"][m]["measures"] = collector.summary(m)
        if measures:
            doc["measures"] = DEFINITIONS
    if "xfeat" not in doc and set(methods) & (set(PSD_METHODS) | {"xfeat-dapc", "xfeat-gms"}):
        from scenesig.benchmarks._models import xfeat_model
        from scenesig.signatures.xfeat import get_xfeat

        doc["xfeat"] = get_xfeat({"model": xfeat_model()}).describe()
    if folds is not None:
        doc["evaluation"] = (f"{int(folds)}-fold cross-validation over tiles: every figure is on held-out tiles, "
                             "settings chosen on the other folds' tiles")
        doc["folds"] = fold_docs
    ranked = sorted(methods, key=lambda m: (-doc["methods"][m]["success_rate"],
                                            doc["methods"][m]["mean_error_px"] or np.inf))
    doc["best_method"] = ranked[0]
    if json_path is not None:
        json_path = Path(json_path)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(json_path, json.dumps(doc, indent=1, default=_jsonable) + "\n")
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
        atomic_write_text(json_path.with_name("trials.csv"), buf.getvalue())
    if figure_dir is not None:
        plot_errors(errors, Path(figure_dir) / "aerial_errors.png", trials, seed)
        if "mrsmcc" in methods and folds is None:
            from scenesig.aerial.trials import make_trial
            tr = make_trial(images, 0, seed)
            plot_example(ests["mrsmcc"][tr.tile], tr, tiles[tr.tile].name,
                         Path(figure_dir) / "aerial_example.png")
    return doc


def _protocol_doc(protocol: dict) -> dict:
    """The variant trials' switches and ranges, for the JSON."""
    from scenesig.aerial.deform import DEFORM, RECOLOUR

    out = dict(protocol)
    if protocol.get("deform"):
        out["deform_ranges"] = DEFORM
    if protocol.get("recolour"):
        out["recolour_ranges"] = RECOLOUR
    return out


def _jsonable(o):
    if isinstance(o, tuple):
        return list(o)
    if isinstance(o, (np.integer, np.floating)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def plot_example(est, trial, tile_name: str, path: Path) -> None:
    """One trial as MRSM-CC sees it: the sensed image, its colour-corrected version with the
    registered landmark regions, and the tile with the true and estimated footprints."""
    import cv2
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scenesig.aerial.affine import apply_affine

    loc = est.locate(trial.image)
    cc = est.colour_constancy(trial.image, loc.transform)
    h, w = trial.image.shape[:2]
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1], [0, 0]], float)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    axes[0].imshow(cv2.cvtColor(trial.image, cv2.COLOR_BGR2RGB))
    axes[0].set_title(f"sensed (scale {trial.scale:.2f}, rotation {trial.rotation_deg:.1f} deg)")
    axes[1].imshow(cv2.cvtColor(cc, cv2.COLOR_BGR2RGB))
    half = (est.config["region_size"] - 1) / 2
    consistent = np.linalg.norm(apply_affine(loc.transform, loc.src) - loc.dst, axis=1) \
        <= float(est.config["consistency_px"])
    for x, y in loc.src[consistent]:
        axes[1].add_patch(plt.Rectangle((x - half, y - half), 2 * half, 2 * half, fill=False,
                                        ec="r", lw=1))
    axes[1].set_title(f"local EHM; {int(consistent.sum())} of {len(loc.src)} registrations "
                      f"consistent ({loc.method})")
    axes[2].imshow(cv2.cvtColor(est.reference_.image, cv2.COLOR_BGR2RGB))
    for T, col, lab in ((trial.affine, "w", "truth"), (loc.transform, "r", "MRSM-CC")):
        p = apply_affine(T, corners)
        axes[2].plot(p[:, 0], p[:, 1], color=col, lw=1.5, label=lab)
    axes[2].plot(*loc.dst[consistent].T, "r+", ms=6)
    err = float(np.linalg.norm(loc.centre - trial.centre))
    axes[2].set_title(f"{tile_name}: error {err:.1f} px")
    axes[2].legend(loc="lower right", fontsize=8)
    for a in axes:
        a.set_axis_off()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)


def plot_errors(errors: dict, path: Path, trials: int, seed: int) -> None:
    """Cumulative distribution of the localisation error per method, with the 25-px criterion."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for m, e in errors.items():
        e = np.sort(np.asarray(e, float))
        ax.step(np.minimum(e, 1e4), np.arange(1, len(e) + 1) / len(e), where="post",
                label=f"{m} ({np.mean(e <= SUCCESS_PX):.1%})")
    ax.axvline(SUCCESS_PX, color="k", ls="--", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlim(0.1, 2000)
    ax.set_ylim(0, 1)
    ax.set_xlabel("error of the sensed centre on the tile (px, log)")
    ax.set_ylabel("fraction of trials")
    ax.set_title(f"Aerial scene matching, {trials} Monte-Carlo trials (seed {seed})")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("tiles", help="folder with map.csv and the tiles (e.g. ../shared/data/wildnav)")
    p.add_argument("--methods", default="mrsmcc,sism,sift,orb,signatures",
                   help=f"comma-separated, from {','.join(METHODS)}")
    p.add_argument("--trials", type=int, default=200)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", help="output JSON file (trials.csv is written beside it)")
    p.add_argument("--figure", help="folder for aerial_errors.png")
    p.add_argument("--cache", default="maps/aerial_banks",
                   help="folder caching the mined signature banks (default maps/aerial_banks)")
    p.add_argument("--folds", type=int, default=None,
                   help="K >= 2: cross-validate over tiles (settings chosen on the other folds' tiles, "
                        "success reported on held-out tiles only)")
    p.add_argument("--search-trials", type=int, default=40,
                   help="with --folds: training trials per candidate setting and fold")
    p.add_argument("--search-seed", type=int, default=0, help="with --folds: seed of the training trials")
    p.add_argument("--choose-defaults", action="store_true",
                   help="run only the search, on all tiles (--search-trials, --search-seed): prints every "
                        "candidate's figures, the chosen settings and whether they are the methods' defaults")
    p.add_argument("--deform", action="store_true",
                   help="deformed trials: camera tilt up to 15 deg and a smooth displacement field (exact truth)")
    p.add_argument("--recolour", action="store_true",
                   help="recoloured trials: region-wise ground-cover change (snow, grass, bare soil)")
    p.add_argument("--measures", action="store_true",
                   help="add the point-set-domain seed's measures (RPR, RR, AR, QR, RT, RMSE-DI, RRMSE-DI, ROC AUC; "
                        "runs every trial's impostor pair too)")
    p.add_argument("--feature-cache", default=None,
                   help="folder keeping the point-set-domain methods' XFeat features between runs")
    p.add_argument("--no-progress", action="store_true")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scenesig aerial bench", description=__doc__.split("\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    try:
        if args.choose_defaults:
            if args.folds is not None:
                raise ValueError("--choose-defaults searches all tiles; it takes no --folds")
            doc = choose_defaults(args.tiles, methods, args.search_trials, args.search_seed, args.json, args.cache,
                                  progress=not args.no_progress)
            print(json.dumps(doc, indent=1, default=_jsonable))
            return 0
        doc = run_benchmark(args.tiles, [m.strip() for m in args.methods.split(",") if m.strip()],
                            args.trials, args.seed, args.json, args.figure, args.cache,
                            progress=not args.no_progress, folds=args.folds,
                            search_trials=args.search_trials, search_seed=args.search_seed,
                            deform=args.deform, recolour=args.recolour, measures=args.measures,
                            feature_cache=args.feature_cache)
    except ValueError as exc:
        print(f"scenesig aerial bench: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(doc, indent=1, default=_jsonable))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
