"""Are the localiser's 95 % bounds honest?  ``scenesig bench uncertainty LOCDIR... [--json OUT]``.

Reads ``scenesig localise`` outputs of runs with truth (``metrics.json``, ``frames.csv``,
``trajectory.tum``; the map and run they name) and measures, per output and pooled:

* ``bound_coverage_95`` -- share of the localised frames whose absolute lateral error relative to the
  map (:func:`scenesig.localiser.outputs.map_relative_truth`; relative to the truth where the map has none) is
  within the stated ``lateral_bound_95_m``; ``bound_coverage_95_all`` over every frame with a pose;
* ``lateral_bound_95_m_median`` over the localised frames;
* ``raw_ratio_p95`` -- the 95th percentile of ``|error| / bound_raw`` over the localised frames, where
  ``bound_raw`` is the bound without the inflation the output was written with (``bound_inflation`` in
  its ``metrics.json``; 1 where absent, as before it existed) -- the marginal with the localiser's
  innovation term (:func:`scenesig.localiser.uncertainty.innovation_variance`): the inflation that would
  make those bounds cover exactly 95 % of them;
* ``coverage_at`` -- the coverage the raw bounds times each factor of ``--factors`` would give.

Nothing is timed; the figures depend only on the outputs.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _errors(folder: Path):
    """(metrics, lateral error relative to the map, stated bound, localised flags, times) per frame of one
    output."""
    from scenesig.localiser.evaluation import lateral_heading_errors
    from scenesig.localiser.outputs import map_relative_truth, reference_path, run_truth
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.geometry import interpolate_poses
    from scenesig.surveys.localisation import Localisation
    from scenesig.surveys.run import read_run

    loc = Localisation.from_folder(folder)
    metrics, frames, times, poses = loc.metrics, loc.frames, loc.times, loc.poses
    store = MapStore.open(metrics["map"])
    run = read_run(metrics["run_path"], check_images=False)
    tt, tp, source = run_truth(run)
    tmap = map_relative_truth(store, tp) if source == "truth" else None
    ref = tp if tmap is None else tmap
    n = len(times)
    lat = np.full(n, np.nan)
    v = np.isfinite(poses[:, :3, 3]).all(axis=1) & (times >= tt[0]) & (times <= tt[-1])
    if v.any():
        tru = interpolate_poses(tt, ref, times[v]).reshape(-1, 4, 4)
        lat[v] = lateral_heading_errors(poses[v], tru, reference_path(store))[0]
    return metrics, np.abs(lat), frames["lateral_bound_95_m"], frames["localised"] > 0, times


def _raw(metrics, bound):
    return bound / float(metrics.get("bound_inflation", 1.0))


def _stats(err, bound, raw, loc, factors) -> dict:
    ok = np.isfinite(err) & np.isfinite(bound) & (bound > 0)
    lo = ok & loc
    ratio = err[lo] / raw[lo]
    return {
        "localised_frames": int(lo.sum()), "frames_with_pose": int(ok.sum()),
        "bound_coverage_95": float(np.mean(err[lo] <= bound[lo])) if lo.any() else None,
        "bound_coverage_95_all": float(np.mean(err[ok] <= bound[ok])) if ok.any() else None,
        "lateral_bound_95_m_median": float(np.median(bound[lo])) if lo.any() else None,
        "lateral_error_map_m_median": float(np.median(err[lo])) if lo.any() else None,
        "raw_ratio_p95": float(np.percentile(ratio, 95)) if lo.any() else None,
        "coverage_at": {f"{f:g}": float(np.mean(ratio <= f)) for f in factors} if lo.any() else {},
    }


def main(argv=None) -> int:
    from scenesig.benchmarks._stages import emit_json

    ap = argparse.ArgumentParser(prog="scenesig bench uncertainty", description=__doc__.splitlines()[0])
    ap.add_argument("outputs", nargs="+", help="'scenesig localise' output folders (runs with truth)")
    ap.add_argument("--factors", default="1,1.5,2,2.5,3,4,5", help="inflation factors to report coverage at")
    ap.add_argument("--json", help="write the result JSON here")
    args = ap.parse_args(argv)
    factors = [float(f) for f in args.factors.split(",")]
    per, pooled = {}, [[], [], [], []]
    for folder in args.outputs:
        metrics, err, bound, loc, _ = _errors(Path(folder))
        raw = _raw(metrics, bound)
        key = f"{metrics['run']}/{metrics['method']}" + ("/no-gps" if metrics.get("oracle") == "none" else "")
        per[key] = {**_stats(err, bound, raw, loc, factors), "bound_inflation": metrics.get("bound_inflation", 1.0),
                    "failures": metrics.get("failures"), "false_fixes": metrics.get("false_fixes")}
        for acc, a in zip(pooled, (err, bound, raw, loc)):
            acc.append(a)
    err, bound, raw, loc = (np.concatenate(a) for a in pooled)
    emit_json({"runs": per, "pooled": _stats(err, bound, raw, loc, factors)}, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
