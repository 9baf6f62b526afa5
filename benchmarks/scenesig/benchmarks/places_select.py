"""Choose the place-recognition settings on development data: ``python -m scenesig.benchmarks.places_select``.

The settings of ``scenesig bench places`` that season (the reported set) must not choose are
searched here on GRIEF stromovka's **single-session** protocol (:func:`scenesig.benchmarks.places.protocols`,
``kind="single-session"``): every ordered pair of sessions (i, j), session i's five images the map
(one image per place, like season's one summer image) and session j's five the queries, exact place
-- 660 queries, harder than stromovka's leave-one-session-out protocol, and never season.

Searched:

* the whole-image place descriptor (:mod:`scenesig.signatures.globaldesc`): recall@1 of the descriptor alone
  (the ``hog`` method) for each candidate of :data:`DESCRIPTORS`;
* the signatures' shortlist (a share of the places) and the ``signatures-seq`` sequence length:
  every query is verified against **all** places once, then each (shortlist, length) is scored by
  masking the verifications outside the descriptor's shortlist (exactly what a run with that
  shortlist computes).

Rule (fixed before looking): the highest recall@1; ties go to the cheaper setting (shorter
shortlist, then shorter sequence, then the smaller descriptor).  Prints and writes JSON
(``--json OUT``) with every figure.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from scenesig.benchmarks import places
from scenesig.surveys.grief import load
from scenesig.surveys.io import atomic_write_text

#: Candidate place descriptors (overrides of signatures.globaldesc.default_config).
DESCRIPTORS = [{"width": 64, "cell": 8}, {"width": 96, "cell": 8}, {"width": 128, "cell": 16},
               {"width": 128, "cell": 8}, {"kind": "thumbnail", "width": 64, "patch": 8},
               {"kind": "thumbnail", "width": 32, "patch": 4}]
SHORTLISTS = ("20%", "40%", "60%", "80%", "100%")
LENGTHS = (1, 2, 3, 4, 5)


def _size(d: dict) -> int:
    from scenesig.signatures import globaldesc

    return int(globaldesc.describe(np.zeros((384, 1024), np.uint8), d).size)


def run(dataset, json_path=None, jobs: int = 1, progress: bool = True, cache=None) -> dict:
    ds = load(dataset)
    prs = places.protocols(ds, "single-session")
    cfg = dict(places.default_config)
    out = {"dataset": ds.name, "protocol": "single-session", "queries": sum(len(p.queries) for p in prs),
           "descriptors": [], "signatures": []}
    # 1. the descriptor alone
    for d in DESCRIPTORS:
        c = {**cfg, "descriptor": d}
        hits, n = 0.0, 0
        for pr in prs:
            S, _, _ = places._hog(ds, pr, c)
            truth = np.array([q[0] for q in pr.queries])
            hits += places.recall_at(S, truth, pr.tolerance, 1)[0] * len(truth)
            n += len(truth)
        out["descriptors"].append({"descriptor": d, "values": _size(d), "recall_at_1": hits / n})
        print(f"descriptor {d}: recall@1 {hits / n:.3f}", file=sys.stderr)
    best_d = max(out["descriptors"], key=lambda r: (round(r["recall_at_1"], 6), -r["values"]))
    out["descriptor_chosen"] = best_d["descriptor"]
    # 2. shortlist x sequence length, with the chosen descriptor, everything verified once
    c = {**cfg, "descriptor": best_d["descriptor"], "shortlist": "100%", "cache": cache}
    banks: dict = {}
    res, secs = [], 0.0
    t0 = time.perf_counter()
    for pr in prs:
        desc, V, s, _ = places._verify(ds, pr, c, jobs, False, banks)
        res.append((pr, desc, V))
        secs += s
    out["seconds_verify_all"] = time.perf_counter() - t0
    out["seconds_per_verification"] = secs / max(1, sum(np.isfinite(V).sum() for _, _, V in res))
    for sl in SHORTLISTS:
        for L in LENGTHS:
            hits, n = 0.0, 0
            for pr, desc, V in res:
                K = places.shortlist_size(sl, pr.places)
                order = np.argsort(-desc, axis=1, kind="stable")
                mask = np.zeros_like(V, dtype=bool)
                np.put_along_axis(mask, order[:, :K], True, axis=1)
                Vk = np.where(mask, V, np.nan)
                S = places.single_scores(desc, Vk) if L == 1 else places.sequence_scores(desc, Vk, L)
                truth = np.array([q[0] for q in pr.queries])
                hits += places.recall_at(S, truth, pr.tolerance, 1)[0] * len(truth)
                n += len(truth)
            out["signatures"].append({"shortlist": sl, "sequence_length": L, "recall_at_1": hits / n})
            print(f"shortlist {sl} length {L}: recall@1 {hits / n:.3f}", file=sys.stderr)
    best = max(out["signatures"], key=lambda r: (round(r["recall_at_1"], 6), -float(r["shortlist"][:-1]),
                                                 -r["sequence_length"]))
    out["chosen"] = best
    if json_path:
        from pathlib import Path

        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(Path(json_path), json.dumps(out, indent=1))   # never half a file
    print(json.dumps({k: out[k] for k in ("descriptor_chosen", "chosen")}, indent=1))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m scenesig.benchmarks.places_select", description=__doc__.split("\n")[0])
    p.add_argument("dataset", help="a GRIEF sessions-layout folder (stromovka)")
    p.add_argument("--json", default=None)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--cache", default=None, help="folder caching the mined banks")
    a = p.parse_args(argv)
    try:
        run(a.dataset, a.json, a.jobs, cache=a.cache)
    except ValueError as exc:
        print(f"places_select: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
