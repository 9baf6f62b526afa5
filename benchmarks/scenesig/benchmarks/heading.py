"""The GRIEF heading benchmark: ``scenesig bench heading DATASET --methods signatures,orb,sift``.

Protocol (Krajník et al., "Image features for visual teach-and-repeat navigation in changing
environments", RAS 2017): for every ordered (map image, live image) pair of one place, estimate the
horizontal image displacement map -> live and count it correct when it is within ``tolerance_px``
(20) of the ground truth.  The error rate is incorrect / total; a pair without an estimate is
incorrect.  Pairs come from :meth:`scenesig.surveys.grief.GriefDataset.pairs` (660 on stromovka, 101 on
season).

Methods
-------
``orb``, ``sift`` (also ``rootsift``)
    OpenCV, the 1600 strongest upright keypoints per image, brute-force 2-NN with ratio test 0.9,
    histogram voting of the horizontal offsets in 20-px bins (see :mod:`scenesig.signatures.pointfeatures`).
    ``--baseline-preset grief`` (default) slides the bin over all positions and takes the mean
    offset inside it, as GRIEF's own ``match_all`` does, and drops SIFT's duplicate keypoints (one
    per orientation peak, identical once upright) before choosing the 1600.  ``plain`` reproduces
    a straightforward re-implementation: fixed bins over [-width, width], bin-centre estimate,
    duplicates kept -- it gives the reference numbers of ``../shared/data/README.md`` exactly.
``xfeat``, ``xfeat-1600``
    XFeat learned features (Potje et al. 2024; :mod:`scenesig.signatures.xfeat`) set up as its authors do:
    upstream's top-k 4096 keypoints per image (``xfeat-1600``: the protocol's 1600), mutual nearest
    neighbours with cosine similarity above 0.82 (upstream's ``match`` default), then the same
    histogram voting.  The model is ``$SCENESIG_XFEAT_MODEL`` or ``../shared/models/xfeat/xfeat.onnx``
    (its sha256 is in the JSON).
``signatures``
    :class:`scenesig.signatures.heading.SignatureHeading` (leave-one-session-out banks for the sessions
    layout; augmented map images for the sequence layout).
``signatures-xfeat``, ``signatures-hog+xfeat``
    The same, with banks mined and detected on XFeat's dense descriptor map instead of HOG, or on both
    stacked (mining's ``features``; :func:`scenesig.signatures.hog.describe_cells`).

Output: a JSON file ``{"dataset", "pairs", "tolerance_px", "methods": {NAME: {"error_rate",
"errors", "pairs", "seconds", ...}}}``, a printed table, and a figure
``heading_<dataset>.png`` (one row per place: map image with the signature boxes, live image with
where they fired; ORB's voting inliers when the signatures method is not run).

Run ``scenesig bench heading --help``.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenesig.benchmarks._stages import read_config
from scenesig.commands._types import positive_int
from scenesig.signatures import pointfeatures as pf
from scenesig.surveys.errors import DataError
from scenesig.surveys.grief import GriefDataset, GriefPair, load
from scenesig.surveys.io import atomic_path, atomic_write_text

__all__ = ["default_config", "BASELINE_PRESETS", "METHODS", "MethodResult", "run_benchmark",
           "run_point_features", "run_signatures", "score", "make_figure", "run_from_args", "main"]

log = logging.getLogger(__name__)

#: Benchmark parameters.
default_config = {
    "tolerance_px": 20,
    "n_features": 1600,
    "figure_rows": 5,          # places drawn (spread along the data set when it has more)
}

#: Point-feature settings per ``--baseline-preset`` (overrides of pointfeatures.default_config).
BASELINE_PRESETS = {
    # GRIEF's protocol finds 1600 features per image; OpenCV's default SIFT contrast threshold
    # (0.04) finds fewer on these low-contrast park images, so it is switched off
    "grief": {"sift": {"contrastThreshold": 0.0}},
    "plain": {"dedupe": False,
              "vote": {"voting": "fixed", "estimate": "centre", "origin": "-width"}},
}

POINT_METHODS = ("orb", "sift", "rootsift", "xfeat", "xfeat-1600")
#: XFeat variants: keypoints per image (upstream's top-k, and the protocol's budget)
XFEAT_BUDGETS = {"xfeat": 4096, "xfeat-1600": 1600}
#: Scene signatures and the cell descriptor each variant mines on (None: the settings' ``mining.features``,
#: HOG by default; signatures.hog.describe_cells)
SIGNATURE_METHODS = {"signatures": None, "signatures-xfeat": "xfeat", "signatures-hog+xfeat": "hog+xfeat"}
METHODS = POINT_METHODS + tuple(SIGNATURE_METHODS)


@dataclass
class MethodResult:
    """Estimates of one method on a list of pairs.

    Attributes
    ----------
    name : str
    estimates : ndarray, shape (n_pairs,)
        Displacement map -> live, px (NaN = no estimate).
    seconds : float
        Wall time of the whole method (features, training, matching).
    extra : dict
        Method-specific keys copied into the JSON entry.
    detail : dict
        Per-pair diagnostic objects for the figure, keyed by ``GriefPair``.
    """

    name: str
    estimates: np.ndarray
    seconds: float
    extra: dict = field(default_factory=dict)
    detail: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------- scoring


def score(dataset: GriefDataset, pairs: list[GriefPair], estimates, tolerance: float = 20) -> dict:
    """Error counts of ``estimates`` against the ground truth.

    Returns
    -------
    dict
        ``error_rate``, ``errors``, ``pairs`` and ``per_place`` ({place name: {"errors", "pairs"}}).
        A pair is correct when ``|estimate - truth| < tolerance``; NaN counts as an error.
    """
    est = np.asarray(estimates, float)
    if len(est) != len(pairs):
        raise ValueError(f"{len(est)} estimates for {len(pairs)} pairs")
    truth = np.array([dataset.truth(p) for p in pairs], float)
    with np.errstate(invalid="ignore"):
        wrong = ~(np.abs(est - truth) < tolerance)
    per_place: dict[str, dict] = {}
    for p, w in zip(pairs, wrong):
        d = per_place.setdefault(dataset.places[p.place].name, {"errors": 0, "pairs": 0})
        d["errors"] += int(w)
        d["pairs"] += 1
    n = len(pairs)
    return {"error_rate": float(wrong.sum() / n) if n else float("nan"),
            "errors": int(wrong.sum()), "pairs": n, "per_place": per_place}


# ---------------------------------------------------------------------------------- point features


def _pf_config(preset: str, width: int) -> dict:
    if preset not in BASELINE_PRESETS:
        raise ValueError(f"unknown baseline preset {preset!r}; choose from "
                         f"{', '.join(BASELINE_PRESETS)}")
    cfg = json.loads(json.dumps(BASELINE_PRESETS[preset]))
    if cfg.get("vote", {}).get("origin") == "-width":
        cfg["vote"]["origin"] = -float(width)  # np.histogram over [-width, width]
    return cfg


@dataclass
class _PairOutcome:
    estimate: float
    n_matches: int
    support: int
    dx: np.ndarray


def run_point_features(dataset: GriefDataset, pairs: list[GriefPair], kind: str = "orb",
                       preset: str = "grief", n_features: int = 1600, n_jobs: int = 1,
                       progress: bool = True, keep_detail: set | None = None) -> MethodResult:
    """Estimate every pair's displacement with OpenCV point features.

    Features are extracted once per image and the pairs processed place by place, so memory holds
    one place's descriptors at a time.  Threads (``n_jobs``) run OpenCV, which releases the GIL.

    Parameters
    ----------
    keep_detail : set of GriefPair, optional
        Pairs whose features, matches and vote are kept in ``detail`` (for the figure).
    """
    t0 = time.perf_counter()
    name = kind
    xfeat_info = None
    if kind in XFEAT_BUDGETS:
        from scenesig.benchmarks._models import xfeat_model
        from scenesig.signatures.xfeat import get_xfeat

        n_features, kind = XFEAT_BUDGETS[kind], "xfeat"
        xfeat_info = get_xfeat({"model": xfeat_model()}).describe()
    by_place: dict[int, list[int]] = {}
    for k, p in enumerate(pairs):
        by_place.setdefault(p.place, []).append(k)
    first = pairs[0] if pairs else None
    width = dataset.places[first.place].image(first.map, gray=True).shape[1] if first else 0
    cfg = _pf_config(preset, width)
    if xfeat_info is not None:
        # XFeat's own matcher (upstream's XFeat.match): mutual nearest neighbours, cosine > 0.82
        cfg["match"] = {"filter": "cossim", "mutual": True}
        cfg["xfeat"] = {"model": xfeat_info["model"]}
    estimates = np.full(len(pairs), np.nan)
    from threadpoolctl import threadpool_limits

    mcfg = pf._merge(cfg)["match"]
    symmetric = mcfg["filter"] == "cossim" and mcfg["mutual"]
    done: dict = {}
    outcomes: list[_PairOutcome | None] = [None] * len(pairs)
    detail, n_feat, t_extract, t_match, n_images = {}, [], 0.0, 0.0, 0
    bar = _progress(len(pairs), f"{name} pairs", progress)
    with ThreadPoolExecutor(max(1, n_jobs)) as pool:
        for place_idx, ks in by_place.items():
            place = dataset.places[place_idx]
            sessions = sorted({s for k in ks for s in (pairs[k].map, pairs[k].live)})
            t = time.perf_counter()
            feats = dict(zip(sessions, pool.map(
                lambda s: pf.extract(place.image(s, gray=True), kind, n_features, config=cfg),
                sessions)))
            t_extract += time.perf_counter() - t
            n_images += len(sessions)
            n_feat += [len(f) for f in feats.values()]

            def one(k):
                p = pairs[k]
                m = None
                if symmetric:
                    # mutual nearest neighbours on a symmetric similarity: the pair (live, map) has the
                    # same matches as (map, live) with the roles swapped -- match each image pair once
                    back = done.get((place_idx, p.live, p.map))
                    if back is not None:
                        m = pf.Matches(back.train, back.query, back.distance, back.second)
                if m is None:
                    with threadpool_limits(1):        # one BLAS thread per matching job
                        m = pf.match(feats[p.map], feats[p.live], **pf._merge(cfg)["match"])
                    if symmetric:
                        done[(place_idx, p.map, p.live)] = m
                dx = feats[p.live].xy[m.train, 0] - feats[p.map].xy[m.query, 0]
                dy = feats[p.live].xy[m.train, 1] - feats[p.map].xy[m.query, 1]
                vote = pf.histogram_displacement(dx, dy=dy, **pf._merge(cfg)["vote"])
                return k, vote, m, dx

            t = time.perf_counter()
            for k, vote, m, dx in pool.map(one, ks):
                estimates[k] = vote.displacement
                outcomes[k] = _PairOutcome(vote.displacement, len(m), vote.support, dx)
                if keep_detail and pairs[k] in keep_detail:
                    detail[pairs[k]] = {"map": feats[pairs[k].map], "live": feats[pairs[k].live],
                                        "matches": m, "vote": vote}
                bar.update(1)
            t_match += time.perf_counter() - t
    bar.close()
    seconds = time.perf_counter() - t0
    # The same matches voted both ways: shows how much the bin placement alone moves the rate.
    variants = {}
    for voting in ("fixed", "sliding"):
        ests = [pf.histogram_displacement(o.dx, cfg.get("vote", {}).get("bin_px", 20.0), voting).displacement
                for o in outcomes]
        variants[voting] = score(dataset, pairs, ests)["error_rate"]
    extra = {
        "features": kind, "preset": preset, "n_features": n_features,
        "mean_features_per_image": float(np.mean(n_feat)) if n_feat else 0.0,
        "mean_matches_per_pair": float(np.mean([o.n_matches for o in outcomes])) if pairs else 0.0,
        "ms_per_image_extraction": 1e3 * t_extract / max(n_images, 1),
        "ms_per_pair_matching": 1e3 * t_match / max(len(pairs), 1),
        "threads": n_jobs,
        "config": pf._merge({**cfg, "n_features": n_features}),
        "error_rate_by_voting_mean_estimate": variants,
    }
    if xfeat_info is not None:
        extra["xfeat"] = xfeat_info
    return MethodResult(name, estimates, seconds, extra, detail)


# ---------------------------------------------------------------------------------- signatures


def _training_description(dataset: GriefDataset, cfg: dict, single: bool = False) -> str:
    if dataset.kind == "sessions" and not single:
        return ("leave-one-session-out: for live session j, one bank per place mined from the "
                "place's other sessions, aligned by their ground-truth displacements (never j's); "
                "other places' images of the training sessions as external negatives")
    return (f"one appearance per place: bank mined from the pair's map image plus "
            f"{cfg.get('augment_copies', '?')} photometrically augmented copies (gamma, contrast, "
            f"colour cast, blur, noise, desaturation, synthetic snow) shifted by up to "
            f"+-{cfg.get('augment_shift_px', '?')} px; other places' images of the map session as "
            f"external negatives; live images never used in training")


def run_signatures(dataset: GriefDataset, pairs: list[GriefPair], n_jobs: int = 1,
                   progress: bool = True, config: dict | None = None,
                   single: bool = False, features: str | None = None,
                   name: str = "signatures") -> MethodResult:
    """Estimate every pair with the scene-signature method (:mod:`scenesig.signatures.heading`);
    ``features`` (if given) is the cell descriptor mined on, over the settings' ``mining.features``."""
    from scenesig.signatures.heading import SignatureHeading

    if features is not None:
        config = dict(config or {})
        config["mining"] = {**dict(config.get("mining") or {}), "features": features}
    from scenesig.signatures.mining import resolve_config
    features = resolve_config((config or {}).get("mining"))["features"]
    if "xfeat" in features and not (config or {}).get("xfeat_model"):
        from scenesig.benchmarks._models import xfeat_model
        config = {**(config or {}), "xfeat_model": xfeat_model()}   # to the processes that mine
    t0 = time.perf_counter()
    detail, extra = {}, {}
    est = SignatureHeading(dataset, config, n_jobs=n_jobs, progress=progress, single=single)
    estimates = np.asarray(est.estimate(list(pairs)), float)
    for p in pairs:
        rec = est.records.get(tuple(int(v) for v in p))
        if rec is not None:
            detail[p] = rec
    stats = getattr(est, "bank_stats", [])
    if stats:
        sizes = [s.get("bank_size", 0) for s in stats]
        extra["banks"] = len(stats)
        extra["mean_bank_size"] = float(np.mean(sizes))
        extra["mean_mining_seconds"] = float(np.mean([s.get("seconds", 0.0) for s in stats]))
        n_live = sum(s.get("live_images", 0) for s in stats)
        n_map = sum(s.get("map_images", 0) for s in stats)
        if n_live:
            extra["live_detect_seconds_per_image"] = sum(s.get("live_detect_seconds", 0.0) for s in stats) / n_live
        if n_map:
            extra["map_detect_seconds_per_image"] = sum(s.get("map_detect_seconds", 0.0) for s in stats) / n_map
    cfg = est.config
    extra["features"] = features
    if "xfeat" in features:
        from scenesig.signatures.xfeat import model_path, model_sha256
        extra["model_sha256"] = model_sha256(cfg["xfeat_model"] or model_path())
    # the full resolved settings (the same for every folder) and what the training-data rule made of
    # them per bank
    extra["config"] = dict(cfg)
    if stats:
        extra["calibrated_banks"] = int(sum(bool(s.get("calibrated")) for s in stats))
    extra["training"] = _training_description(dataset, cfg, single)
    extra["jobs"] = n_jobs
    return MethodResult(name, estimates, time.perf_counter() - t0, extra, detail)


# ---------------------------------------------------------------------------------- figure


def figure_pairs(dataset: GriefDataset, rows: int = 5) -> list[GriefPair]:
    """The pair drawn for each figure row (a fixed rule, not chosen by outcome).

    sessions layout: each place (at most ``rows``, spread evenly), map = its first session, live =
    the session half the sequence later (about six months on monthly sessions).  sequence layout:
    ``rows`` places spread evenly along the sequence.
    """
    all_pairs = list(dataset.pairs())
    places = sorted({p.place for p in all_pairs})
    if len(places) > rows:
        places = [places[int(round(k))] for k in np.linspace(0, len(places) - 1, rows)]
    out = []
    for pl in places:
        cand = [p for p in all_pairs if p.place == pl]
        if dataset.kind == "sessions":
            m = cand[0].map
            target = m + dataset.n_sessions // 2
            cand = [p for p in cand if p.map == m]
            out.append(min(cand, key=lambda p: abs(p.live - target)))
        else:
            out.append(cand[0])
    return out


def make_figure(dataset: GriefDataset, results: dict[str, MethodResult], path: Path,
                pairs: list[GriefPair], all_pairs: list[GriefPair], tolerance: float = 20) -> str:
    """Draw one row per pair: map image and live image with what the estimate rests on.

    Uses the signatures method's boxes when it ran (map: where each classifier was found; live:
    where it fired; green = agreed with the estimate, orange = fired but outvoted), otherwise the
    first point-feature method's matches (green = in the winning bin).  ``all_pairs`` is the
    order of the methods' ``estimates``.

    Returns
    -------
    str
        The method whose evidence was drawn.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    source = "signatures" if "signatures" in results and results["signatures"].detail else None
    if source is None:
        source = next((n for n in results if n in POINT_METHODS and results[n].detail), None)
    index = {p: k for k, p in enumerate(all_pairs)}
    fig, axes = plt.subplots(len(pairs), 2, figsize=(14, 2.75 * len(pairs)), squeeze=False)
    for row, p in enumerate(pairs):
        place = dataset.places[p.place]
        truth = dataset.truth(p)
        imgs = [place.image(p.map)[:, :, ::-1], place.image(p.live)[:, :, ::-1]]
        for c, (ax, img) in enumerate(zip(axes[row], imgs)):
            ax.imshow(img)
            ax.set_xticks([])
            ax.set_yticks([])
        r = results.get(source) if source else None
        d = r.detail.get(p) if r is not None else None
        k = index.get(p)
        est = float(r.estimates[k]) if r is not None and k is not None else float("nan")
        ok = np.isfinite(est) and abs(est - truth) < tolerance
        if source == "signatures" and d is not None:
            fired = np.asarray(d.fired, bool)
            inl = np.asarray(d.inlier, bool)
            for c, boxes in enumerate((d.map_boxes, d.live_boxes)):
                for b, (f, i) in enumerate(zip(fired, inl)):
                    if not (f or i):
                        continue
                    x0, y0, x1, y1 = boxes[b]
                    color = "lime" if i else "orange"
                    axes[row][c].add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False,
                                                     lw=1.2, ec=color))
            what = f"{int(fired.sum())} of {len(fired)} classifiers fired, {int(inl.sum())} agree"
        elif d is not None:
            m, vote = d["matches"], d["vote"]
            inl = vote.inliers
            for c, (feat, idx) in enumerate(((d["map"], m.query), (d["live"], m.train))):
                xy = feat.xy[idx]
                axes[row][c].scatter(xy[~inl, 0], xy[~inl, 1], s=6, c="orange", lw=0)
                axes[row][c].scatter(xy[inl, 0], xy[inl, 1], s=14, c="lime", lw=0)
            what = f"{len(m)} matches, {int(inl.sum())} in the winning bin"
        else:
            what = "no detail"
        axes[row][0].set_title(f"place {place.name}: map {dataset.session_names[p.map]}",
                               fontsize=9, loc="left")
        axes[row][1].set_title(
            f"live {dataset.session_names[p.live]} | truth {truth:+.0f} px, {source or '-'} "
            f"{est:+.0f} px {'correct' if ok else 'WRONG'} | {what}", fontsize=9, loc="left")
    fig.suptitle(f"{dataset.name}: heading benchmark evidence ({source or 'no method'}); "
                 f"green = agrees with the estimate, orange = outvoted", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
    return source or ""


# ---------------------------------------------------------------------------------- driver


def _progress(total: int, desc: str, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="pair", disable=not enabled, leave=False,
                mininterval=1.0)


def run_benchmark(dataset_path, methods=("signatures", "orb", "sift"), json_path=None,
                  figure_dir=None, n_jobs: int = 1, preset: str = "grief",
                  progress: bool = True, signatures_config: dict | None = None,
                  max_pairs: int | None = None, single: bool = False,
                  map_sessions=None) -> dict:
    """Run the benchmark and write the JSON (and figure).

    Parameters
    ----------
    dataset_path : str or Path
        A GRIEF-layout folder.
    methods : sequence of str
        From :data:`METHODS`.
    json_path : str or Path, optional
        Output JSON.  ``figure_dir`` defaults to its folder.
    figure_dir : str or Path, optional
        Where ``heading_<dataset>.png`` goes; no figure when both this and ``json_path`` are None.
    n_jobs : int
        Threads for point features, processes for signature banks.
    preset : {"grief", "plain"}
        Point-feature variant (:data:`BASELINE_PRESETS`).
    max_pairs : int, optional
        Only the first N protocol pairs (quick checks; the full protocol is the default).
    single : bool
        Signatures: every bank from the pair's map image alone plus synthesised copies
        (:class:`scenesig.signatures.heading.SignatureHeading`'s ``single``); the sequence layout always is.
    map_sessions : sequence of int, optional
        Only the pairs whose map image is from these sessions (0-based).

    Returns
    -------
    dict
        The JSON document.
    """
    methods = [m.strip() for m in methods if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise ValueError(f"unknown method(s) {', '.join(unknown) or '(none given)'}; "
                         f"choose from {', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise ValueError(f"method listed twice in {','.join(methods)}")
    dataset = load(dataset_path)
    pairs = list(dataset.pairs())
    if map_sessions is not None:
        keep = {int(m) for m in map_sessions}
        pairs = [p for p in pairs if p.map in keep]
    if max_pairs is not None:
        pairs = pairs[:max_pairs]
    if not pairs:
        raise DataError(dataset.root, "no protocol pairs (every place needs images in 2 sessions)")
    tol = default_config["tolerance_px"]
    fig_pairs = [p for p in figure_pairs(dataset, default_config["figure_rows"]) if p in set(pairs)]

    print(dataset.describe(), file=sys.stderr)
    results: dict[str, MethodResult] = {}
    for name in methods:
        if name in SIGNATURE_METHODS:
            r = run_signatures(dataset, pairs, n_jobs=n_jobs, progress=progress,
                               config=signatures_config, single=single,
                               features=SIGNATURE_METHODS[name], name=name)
        else:
            r = run_point_features(dataset, pairs, name, preset, default_config["n_features"],
                                   n_jobs, progress, keep_detail=set(fig_pairs))
        results[name] = r

    doc = {"dataset": dataset.name, "pairs": len(pairs), "tolerance_px": tol, "methods": {}}
    if single or map_sessions is not None:        # a development protocol, not GRIEF's: say so
        doc["single"] = bool(single)
        doc["map_sessions"] = None if map_sessions is None else sorted({int(m) + 1 for m in map_sessions})
    for name, r in results.items():
        s = score(dataset, pairs, r.estimates, tol)
        entry = {"error_rate": s["error_rate"], "errors": s["errors"], "pairs": s["pairs"],
                 "seconds": float(r.seconds)}
        entry.update(r.extra)
        entry["per_place"] = s["per_place"]
        entry["per_pair"] = [[dataset.places[p.place].name, p.map, p.live, dataset.truth(p),
                              None if not np.isfinite(e) else round(float(e), 2)]
                             for p, e in zip(pairs, r.estimates)]
        doc["methods"][name] = entry

    print_table(doc)
    if json_path is not None:
        json_path = Path(json_path)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(json_path, json.dumps(doc, indent=1))
    if figure_dir is None and json_path is not None:
        figure_dir = json_path.parent
    if figure_dir is not None and fig_pairs:
        fig_path = Path(figure_dir) / f"heading_{dataset.name}.png"
        source = make_figure(dataset, results, fig_path, fig_pairs, pairs, tol)
        print(f"figure: {fig_path} ({source or 'no method'} evidence)", file=sys.stderr)
    return doc


def print_table(doc: dict, file=None) -> None:
    """Print the benchmark table."""
    out = file or sys.stdout
    print(f"heading benchmark: {doc['dataset']}, {doc['pairs']} pairs, correct when within "
          f"{doc['tolerance_px']} px", file=out)
    print(f"{'method':<22}{'errors':>8}{'pairs':>8}{'error rate':>12}{'seconds':>10}", file=out)
    for name, m in doc["methods"].items():
        print(f"{name:<22}{m['errors']:>8d}{m['pairs']:>8d}{100 * m['error_rate']:>11.1f}%"
              f"{m['seconds']:>10.1f}", file=out)


def _sessions(text):
    if not text:
        return None
    try:
        out = [int(t) - 1 for t in text.split(",") if t.strip()]
    except ValueError:
        raise ValueError(f"--map-sessions takes 1-based session numbers, got {text!r}") from None
    if not out or min(out) < 0:
        raise ValueError(f"--map-sessions takes 1-based session numbers, got {text!r}")
    return out


def run_from_args(args) -> int:
    """Entry point of ``scenesig bench heading`` (args: dataset, methods, json, figure[, jobs,
    baseline_preset, max_pairs])."""
    try:
        run_benchmark(args.dataset, args.methods.split(","), args.json,
                      getattr(args, "figure", None), n_jobs=int(getattr(args, "jobs", 1) or 1),
                      preset=getattr(args, "baseline_preset", "grief") or "grief",
                      max_pairs=getattr(args, "max_pairs", None),
                      single=bool(getattr(args, "single", False)),
                      map_sessions=_sessions(getattr(args, "map_sessions", None)),
                      signatures_config=read_config(getattr(args, "config", None)))
    except (ValueError, RuntimeError) as exc:
        print(f"scenesig bench heading: error: {exc}", file=sys.stderr)
        return 2
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The subcommand's arguments ."""
    p.add_argument("dataset", help="a GRIEF-layout folder (images/ + ground_truth/, or "
                                   "season_00/ + season_01/)")
    p.add_argument("--methods", default="signatures,orb,sift",
                   help=f"comma-separated, from {', '.join(METHODS)}")
    p.add_argument("--json", required=True, help="output JSON file")
    p.add_argument("--figure", default=None, help="figure folder (default: beside the JSON)")
    p.add_argument("--jobs", type=positive_int, default=2, help="threads (point features) / processes "
                                                       "(signature banks)")
    p.add_argument("--baseline-preset", choices=sorted(BASELINE_PRESETS), default="grief",
                   help="point-feature variant: grief (sliding 20-px bin, mean; default) or "
                        "plain (fixed bins, bin centre, SIFT duplicates kept)")
    p.add_argument("--max-pairs", type=positive_int, default=None, help="only the first N pairs (quick look)")
    p.add_argument("--single", action="store_true",
                   help="signatures: mine every bank from the pair's map image alone plus synthesised "
                        "copies (the sequence layout's protocol; on a sessions layout, a "
                        "single-experience development set)")
    p.add_argument("--map-sessions", default=None, metavar="I,J,...",
                   help="only pairs whose map image is from these sessions (1-based, as the folders)")
    p.add_argument("--config", default=None, metavar="JSON",
                   help="JSON file of overrides of signatures.heading.default_config")


def main(argv=None) -> int:
    """``scenesig bench heading ARGS``; a :class:`~surveys.errors.DataError` is left to the CLI's handler."""
    p = argparse.ArgumentParser(prog="scenesig bench heading", description=__doc__.split("\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    return run_from_args(args)


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "heading", *sys.argv[1:]]))
