"""Aerial scene-matching benchmark: the Monte-Carlo protocol of Jin et al. 2016 (§4.3) on real tiles.

Per trial a 400 x 300 sensed image is cut from a random tile at a random position, scaled by
U[0.9, 1.1], rotated by U[-10, 10] deg and given a random photometric change
(:mod:`scenesig.aerial.trials` states the ranges); every method estimates where the sensed centre lies on
that tile, and a trial succeeds when the estimate is within 25 px (the paper's criterion).

Methods: ``mrsmcc`` (MRSM-CC), ``mrsm`` (the same without colour constancy), ``sism`` (whole-image
NCC), ``sift`` / ``orb`` (ratio 0.8 + RANSAC affine), ``signatures`` (a bank mined per tile from
augmented copies, detections + RANSAC affine).

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

METHODS = ("mrsmcc", "mrsm", "sism", "sift", "orb", "xfeat", "signatures")
SUCCESS_PX = 25.0


_COARSE_ROTATIONS = (-10.0, -5.0, 0.0, 5.0, 10.0)      # attitude hypotheses every 5 deg (default 2.5)

#: Cross-validation (``--folds K``): the settings each method's search tries on the training tiles,
#: as overrides of the method's ``default_config`` (``{}`` = the defaults).  MRSM-CC: the high-pass
#: of the NCC (off, and three widths), the colour-constancy window grid, and for speed fewer
#: iterations and attitude hypotheses every 5 deg instead of 2.5;
#: MRSM the same without colour constancy; SISM the search resolution; SIFT / ORB Lowe's ratio;
#: signatures the detection probability (the banks do not depend on it).
SEARCH = {
    "mrsmcc": [{}, {"highpass_sigma": 0.0}, {"highpass_sigma": 6.0}, {"highpass_sigma": 24.0},
               {"cc_grid": (3, 3)}, {"max_iterations": 2}, {"attitude_rotations_deg": _COARSE_ROTATIONS},
               {"attitude_rotations_deg": _COARSE_ROTATIONS, "max_iterations": 2}],
    "mrsm": [{}, {"highpass_sigma": 0.0}, {"highpass_sigma": 6.0}, {"highpass_sigma": 24.0},
             {"max_iterations": 2}, {"attitude_rotations_deg": _COARSE_ROTATIONS}],
    "sism": [{}, {"coarse_scale": 0.25}],
    "sift": [{"ratio": 0.7}, {}, {"ratio": 0.9}],
    "orb": [{"ratio": 0.7}, {}, {"ratio": 0.9}],
    "signatures": [{"min_prob": 0.2}, {}, {"min_prob": 0.5}],
    "xfeat": [{}],      # its authors' matcher and settings (Potje et al. 2024): nothing to choose
}


def _setup(method: str, images, landmarks, cache_dir, config: dict | None = None):
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
    else:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return ests, time.process_time() - t0


def _run_trials(ests: dict, images, indices, seed: int, tile_names, progress=None):
    """Run every method's estimators on trials ``indices`` of ``seed`` drawn over ``images``.

    Returns ``(errors, seconds, rows)``: per method lists of errors (px; inf = no estimate) and CPU
    seconds, and the per-trial rows of ``trials.csv``.
    """
    import cv2

    from scenesig.aerial.trials import make_trial

    errors = {m: [] for m in ests}
    secs = {m: [] for m in ests}
    rows = []
    for k in indices:
        tr = make_trial(images, k, seed)
        row = {"trial": k, "tile": tile_names[tr.tile], "x": tr.centre[0], "y": tr.centre[1],
               "scale": tr.scale, "rotation_deg": tr.rotation_deg}
        for m in ests:
            cv2.setRNGSeed(int(seed) * 100003 + k)          # RANSAC repeats for a seed
            t1 = time.process_time()
            res = ests[m][tr.tile].locate(tr.image)
            secs[m].append(time.process_time() - t1)
            c = np.asarray(res.centre, float)
            err = float(np.linalg.norm(c - tr.centre)) if np.all(np.isfinite(c)) else np.inf
            errors[m].append(err)
            row[f"{m}_x"], row[f"{m}_y"], row[f"{m}_error_px"] = c[0], c[1], err
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


def run_benchmark(tiles_dir, methods=("mrsmcc", "sism", "sift", "orb", "signatures"),
                  trials: int = 200, seed: int = 1, json_path=None, figure_dir=None,
                  cache_dir=None, progress: bool = True, folds: int | None = None,
                  search_trials: int = 40, search_seed: int = 0) -> dict:
    """Run the protocol; returns the JSON document (also written to ``json_path``).

    Per-trial rows (truth, estimates, errors) go to ``trials.csv`` beside the JSON.

    With ``folds`` = K >= 2 the tiles are cross-validated: tile i (``map.csv`` order) is in fold
    i mod K.  For each fold, every method's settings are chosen among :data:`SEARCH` by
    :func:`choose` on ``search_trials`` trials of ``search_seed`` drawn over the *other* folds'
    tiles (the landmark library, too, learns from those tiles only); then trials k = f, f + K, ...
    (k < ``trials``) of ``seed`` are drawn over the fold's own, held-out tiles and located with the
    chosen settings.  Every reported figure is a held-out one; the JSON adds ``folds`` (per fold:
    its training and held-out tiles, every candidate's training figures and the chosen settings).
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
        total = trials if folds is None else trials + int(folds) * search_trials * sum(len(SEARCH[m]) > 1 for m in methods)
        bar = tqdm(total=total, desc="aerial trials", unit="trial", file=sys.stderr)
    fold_docs = []
    with threadpool_limits(limits=1):
        if folds is None:
            setup, ests, landmarks = {}, {}, None
            if {"mrsmcc", "mrsm"} & set(methods):
                t0 = time.process_time()
                landmarks = LandmarkModel().fit(images)        # the landmark library: all tiles
                setup["landmarks"] = time.process_time() - t0
            for m in methods:
                ests[m], setup[m] = _setup(m, images, landmarks, cache_dir)
            errors, secs, rows = _run_trials(ests, images, range(int(trials)), seed, names, bar)
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
                      "search_trials": int(search_trials), "search_seed": int(search_seed),
                      "search": {}, "chosen": {}}
                chosen = {}
                for m in methods:
                    cands = SEARCH[m]
                    res = []
                    if len(cands) > 1:
                        for c in cands:
                            ests_c, _ = _setup(m, tr_img, landmarks, cache_dir, c)
                            e, sc, _ = _run_trials({m: ests_c}, tr_img, range(int(search_trials)), search_seed,
                                                   [names[i] for i in train])
                            res.append({"config": c, **summarise(np.array(e[m]), np.array(sc[m]))})
                        if bar is not None:
                            bar.update(int(search_trials))
                    chosen[m] = cands[choose(res)] if res else cands[0]
                    fd["search"][m] = res
                    fd["chosen"][m] = chosen[m]
                ests = {}
                for m in methods:
                    ests[m], t = _setup(m, te_img, landmarks, cache_dir, chosen[m])
                    setup[m] += t
                idx = range(f, int(trials), K)
                e, sc, r = _run_trials(ests, te_img, idx, seed, [names[i] for i in test], bar)
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
           "seed": int(seed), "best_method": None,
           "setup_seconds": {m: round(v, 2) for m, v in setup.items()},
           "seconds": "CPU seconds of one single-threaded process",
           "geometry": {k: list(v) for k, v in GEOMETRY.items()},
           **({"xfeat": xfeat_info} if "xfeat" in methods else {}),
           "photometric": {k: (list(v) if isinstance(v, tuple) else v)
                           for k, v in PHOTOMETRIC.items()}}
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
    p.add_argument("--no-progress", action="store_true")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scenesig aerial bench", description=__doc__.split("\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        doc = run_benchmark(args.tiles, [m.strip() for m in args.methods.split(",") if m.strip()],
                            args.trials, args.seed, args.json, args.figure, args.cache,
                            progress=not args.no_progress, folds=args.folds,
                            search_trials=args.search_trials, search_seed=args.search_seed)
    except ValueError as exc:
        print(f"scenesig aerial bench: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(doc, indent=1, default=_jsonable))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
