"""Leave-one-place-out choice of the heading bench's ``spread_sigma_px``: ``python -m scenesig.benchmarks.heading_lopo``.

``spread_sigma_px`` weights a signature's vote by ``1 / (1 + (spread_x / sigma)^2)^2``
(:mod:`scenesig.signatures.heading`).  It was chosen on stromovka's evaluation pairs, which are then
reported.  Here it is chosen by leave-one-place-out on stromovka: the 660 pairs are estimated once
with the heading bench's settings (banks mined leave-one-session-out, as the bench does), every
pair's detections are kept, and the votes are re-weighted for every candidate sigma (the weight
does not change mining or detection, so this is exactly what a run with that sigma computes).  For
each place, sigma is chosen on the other four places' pairs (fewest errors; ties: the candidate
nearest the current default, then the smaller) and the held-out place's pairs are scored with it.

Prints and writes JSON (``--json OUT``): errors per candidate over all pairs, per place, the
per-fold choices and the leave-one-place-out total beside the default's.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from scenesig.benchmarks._stages import emit_json
from scenesig.signatures import heading
from scenesig.surveys.grief import load

CANDIDATES = (1.5, 3.0, 6.0, 12.0, 24.0, 1e6)      # 1e6: no spread weighting


def revote(rec, cfg: dict, sigma: float) -> float:
    """The estimate of one pair re-voted with ``spread_sigma_px = sigma`` (as ``_vote_pair``)."""
    if rec.bank_size == 0 or rec.live_top.size == 0:
        return float("nan")
    scale = float(cfg["scale"])
    n_top = int(cfg["live_top_n"])
    pm = rec.map_prob
    pl = rec.live_top[:, :n_top, 1]
    votes = (rec.live_top[:, :n_top, 0] - rec.map_x[:, None]) / scale
    fired = (pm[:, None] >= cfg["min_prob"]) & (pl >= cfg["min_prob"]) & np.isfinite(votes)
    use = fired if fired[:, 0].sum() >= int(cfg["min_votes"]) else np.isfinite(votes)
    sx = np.nan_to_num(rec.spread[:, 0], nan=1e3)
    w = np.where(use, (np.nan_to_num(pm)[:, None] * np.nan_to_num(pl)) ** float(cfg["prob_weight"]), 0.0)
    w = w / ((1.0 + (sx / float(sigma)) ** 2) ** 2)[:, None]
    w = w * float(cfg["rank_decay"]) ** np.arange(n_top)[None, :]
    est, _ = heading.densest_window_displacement(votes.ravel(), w.ravel(), float(cfg["vote_window_px"]))
    return est


def run(dataset, json_path=None, jobs: int = 1, records=None, live=None, reduced: bool = False) -> dict:
    import pickle

    ds = load(dataset)
    pairs = [p for p in ds.pairs() if live is None or p[2] in live]
    config = None
    if reduced:
        from scenesig.benchmarks.places import SIGNATURE_MINING
        config = {"mining": SIGNATURE_MINING}
    rec_path = Path(records) if records else None
    if rec_path is not None and rec_path.is_file():
        recs = pickle.loads(rec_path.read_bytes())
    else:
        est = heading.SignatureHeading(ds, config, jobs, True)
        est.estimate(pairs)
        recs = {k: est.records[k] for k in pairs}
        if rec_path is not None:
            rec_path.parent.mkdir(parents=True, exist_ok=True)
            rec_path.write_bytes(pickle.dumps(recs))
    base = {**heading.default_config, **(config or {})}
    default = float(base["spread_sigma_px"])
    truth = np.array([ds.truth(p) for p in pairs])
    place = np.array([p[0] for p in pairs])
    wrong = {}
    for s in CANDIDATES:
        est = np.array([revote(recs[p], heading.bank_config(base, 11), s) for p in pairs])
        wrong[s] = ~(np.abs(est - truth) < 20)
    out = {"dataset": ds.name, "pairs": len(pairs), "default": default, "candidates": list(CANDIDATES),
           "live_sessions": None if live is None else [s + 1 for s in sorted(live)],
           "mining": "reduced template (bench places)" if reduced else "heading bench default",
           "errors": {str(s): int(wrong[s].sum()) for s in CANDIDATES},
           "errors_per_place": {str(s): [int(wrong[s][place == p].sum()) for p in range(len(ds.places))]
                                for s in CANDIDATES},
           "folds": []}
    lopo = 0
    for p in range(len(ds.places)):
        train = place != p
        best = min(CANDIDATES, key=lambda s: (int(wrong[s][train].sum()), abs(np.log(s / default)), s))
        e = int(wrong[best][~train].sum())
        lopo += e
        out["folds"].append({"held_out_place": p + 1, "chosen": best, "held_out_errors": e,
                             "held_out_pairs": int((~train).sum())})
    same = [np.isclose(revote(recs[k], heading.bank_config(base, 11), default), recs[k].estimate, equal_nan=True)
            for k in pairs]
    out["revote_reproduces_estimates"] = float(np.mean(same))     # 1.0: the re-vote is the bench's vote
    out["lopo_errors"] = lopo
    out["default_errors"] = int(wrong[default].sum())
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
    emit_json(out, json_path)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m scenesig.benchmarks.heading_lopo", description=__doc__.split("\n")[0])
    p.add_argument("dataset", help="a GRIEF sessions-layout folder (stromovka)")
    p.add_argument("--json", default=None)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--records", default=None, help="pickle of the pairs' detections (re-used when present)")
    p.add_argument("--live-sessions", default=None,
                   help="only pairs whose live session is one of these (1-based, comma-separated): fewer banks")
    p.add_argument("--reduced", action="store_true",
                   help="mine with bench places' reduced candidate template (96 shapes; ~3x faster)")
    a = p.parse_args(argv)
    live = None if a.live_sessions is None else {int(v) - 1 for v in a.live_sessions.split(",")}
    run(a.dataset, a.json, a.jobs, a.records, live, a.reduced)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
