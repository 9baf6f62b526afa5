"""Map building (paper 003 §3.1-3.2.1): survey runs -> places -> scene-signature banks -> landmarks -> map.

For each place (every 10 m along the reference run):

1. *training images* -- the frame nearest the place from every training run (by INS position and
   heading), the reference run's first;
2. *mining* -- :func:`signatures.mining.mine_place` (iterative discriminative clustering over the
   fixed template of candidate shapes), with images of other places of the reference run as extra
   negatives;
3. *landmark refinement* -- every surviving classifier is fired over the reference run's ±10 m window;
   :func:`mapping.refine.refine_landmarks` runs the temporal RANSAC check, the depth sweep and LM with a
   Huber cost;
4. the kept classifiers, their landmarks (place frame) and covariances go to the map store.

Places are independent, so they build in parallel: joblib locally, or a Dask distributed cluster with
``--scheduler``.  The driver process alone writes the map (:class:`mapping.store.MapWriter`), so an
interrupted build resumes where it stopped and produces the same bytes.

``python -m mapping.build RUN... --reference RUN --out maps/NAME`` is the same as ``scenesig build-map``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from surveys.geometry import invert
from surveys.run import SurveyRun, read_run
from signatures.mining import mine_place
from signatures.bank import Bank
from mapping import places as places_mod
from mapping.refine import Detections, REASONS, refine_landmarks
from mapping.store import MapWriter, PlaceData, encode_keyframe

__all__ = ["default_config", "build_map", "build_place", "run_from_args"]

default_config = {
    "places": {},                 # overrides of mapping.places.default_config
    "mining": {},                 # overrides of signatures.mining.default_config
    "refine": {},                 # overrides of mapping.refine.default_config
    "negative_places": [-3, 3],   # reference images of these place offsets serve as extra negatives
    "max_window_frames": 21,      # refinement window subsampled to at most this many frames
    "keyframe_width": 160,
}


def _merge(config):
    cfg = {k: (dict(v) if isinstance(v, dict) else v) for k, v in default_config.items()}
    for k, v in (config or {}).items():
        if k not in cfg:
            raise ValueError(f"unknown build option {k!r}; known: {sorted(cfg)}")
        cfg[k] = {**cfg[k], **v} if isinstance(cfg[k], dict) else v
    return cfg


def _subsample(window: np.ndarray, centre: int, n: int) -> np.ndarray:
    """At most ``n`` frames of the window, evenly spread, always including the place's own frame."""
    if len(window) <= n:
        return window
    pick = np.unique(np.round(np.linspace(0, len(window) - 1, n)).astype(int))
    out = np.union1d(window[pick], [centre])
    return out


def _true_depths(run: SurveyRun, frame: int, boxes: np.ndarray) -> np.ndarray | None:
    """Ground-truth depth (m) at each box centre of a simulated frame, or None for real data.

    The median of the simulator's depth buffer over the central half of each box: a signature is a
    patch, so one pixel would make the reference as arbitrary as the estimate.
    """
    try:
        from surveys.sim.truth import depth_image
    except ImportError:
        return None
    depth = depth_image(run, frame)
    if depth is None:
        return None
    out = np.full(len(boxes), np.nan)
    h, w = depth.shape
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        cx, cy, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 4, (y1 - y0) / 4
        r0, r1 = int(max(0, cy - hh)), int(min(h, cy + hh + 1))
        c0, c1 = int(max(0, cx - hw)), int(min(w, cx + hw + 1))
        patch = depth[r0:r1, c0:c1]
        patch = patch[np.isfinite(patch)]
        if patch.size:
            out[i] = float(np.median(patch))
    return out


def build_place(place: places_mod.Place, views: list, negatives: list[np.ndarray], config: dict | None = None):
    """Mine and refine one place.

    Parameters
    ----------
    place : Place
    views : list of TrainingView
        The reference run's view first.
    negatives : list of ndarray
        Gray images of other places.

    Returns
    -------
    data : PlaceData
    stats : dict
        ``seconds``, ``mining`` (MiningStats.as_dict()), ``rejected`` counts, ``depth_rel_errors``.
    """
    cfg = _merge(config)
    t0 = time.perf_counter()
    ref = views[0]
    camera, T_vc = ref.run.camera, ref.run.T_vehicle_camera
    images = [v.run.image(v.frame, gray=True) for v in views]
    bank, mstats = mine_place(images, config=cfg["mining"], negatives=negatives, n_jobs=1, rng=place.index)

    window = _subsample(ref.window, ref.frame, cfg["max_window_frames"])
    rows = np.searchsorted(ref.window, window)
    T_frame_window = ref.T_frame_window[rows]
    reference = int(np.searchsorted(window, ref.frame))
    n = len(bank)
    counts = {r: 0 for r in REASONS}
    if n:
        uv = np.full((n, len(window), 2), np.nan)
        scale = np.zeros((n, len(window)))
        prob = np.zeros((n, len(window)))
        area = np.zeros((n, len(window)))
        for f, j in enumerate(window):
            img = images[0] if j == ref.frame else ref.run.image(int(j), gray=True)
            d = bank.detect(img, top_n=1)
            uv[:, f, 0], uv[:, f, 1] = d.x[:, 0], d.y[:, 0]
            scale[:, f], prob[:, f] = d.scale[:, 0], d.prob[:, 0]
            # patch area a of eq. 5: the firing's box in image pixels (0 = no firing: not used)
            area[:, f] = np.nan_to_num(d.width[:, 0] * d.height[:, 0], nan=0.0)
        dets = Detections(uv, scale, prob, area)
        # T_{j,p}: the place frame (the reference frame's vehicle pose) seen from window frame j
        res = refine_landmarks(dets, invert(T_frame_window), camera, T_vc, reference=reference,
                               config=cfg["refine"] or None)
        keep = np.nonzero(res.kept)[0]
        counts.update({r: int((res.reason == r).sum()) for r in REASONS})
        kept_bank = bank.select(keep)
        landmarks, covs, depths = res.points[keep], res.covariances[keep], res.depth[keep]
        boxes = np.stack([uv[keep, reference, 0], uv[keep, reference, 1]], axis=1) if len(keep) else np.zeros((0, 2))
    else:
        keep = np.zeros(0, int)
        kept_bank = bank
        landmarks, covs, depths = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
        boxes = np.zeros((0, 2))

    rel_err = []
    if len(keep):
        sizes = np.array([[c.box[2], c.box[3]] for c in kept_bank.classifiers], dtype=float)
        box_xyxy = np.concatenate([boxes - sizes / 2, boxes + sizes / 2], axis=1)
        truth = _true_depths(ref.run, ref.frame, box_xyxy)
        if truth is not None:
            ok = np.isfinite(truth) & (truth > 0)
            rel_err = (np.abs(depths[ok] - truth[ok]) / truth[ok]).tolist()
    data = PlaceData(
        bank_arrays=kept_bank.to_arrays(), landmarks=landmarks, covariances=covs,
        classifier_ids=np.arange(len(keep), dtype=np.int64),
        keyframe=encode_keyframe(images[0], width=cfg["keyframe_width"]),
        meta={"reference_run": ref.run.name, "reference_frame": int(ref.frame),
              "training_runs": [v.run.name for v in views], "detections_at_reference": boxes.tolist(),
              "mined": int(n), "kept": int(len(keep))},
    )
    stats = {"place": place.index, "seconds": time.perf_counter() - t0, "mining": mstats.as_dict(),
             "rejected": {"not_converged": int(mstats.rejected_not_converged), **counts},
             "depth_rel_errors": rel_err, "signatures": int(len(keep))}
    return data, stats


def _place_task(place, views, negatives, config):
    """One unit of parallel work (a module-level function so joblib and Dask can ship it)."""
    return place.index, build_place(place, views, negatives, config)


def build_map(runs: list[SurveyRun], reference: SurveyRun, out, jobs: int = 1, scheduler: str | None = None,
              config: dict | None = None, progress: bool = True, places_subset=None) -> dict:
    """Build (or resume) a map from survey runs; returns the build summary (also written to disk).

    Parameters
    ----------
    runs : training runs (the reference run is added if missing).
    reference : the map run: defines places and the frames of landmarks.
    out : map folder.
    jobs : places built in parallel with joblib (ignored with ``scheduler``).
    scheduler : Dask scheduler address (``tcp://host:port``) or a ``distributed.Client``.
    places_subset : optional iterable of place indices to build (others are left for a later resume).
    """
    from tqdm import tqdm

    cfg = _merge(config)
    out = Path(out)
    train = [reference] + [r for r in runs if r.name != reference.name]
    names = [r.name for r in train]
    if len(set(names)) != len(names):
        raise ValueError(f"training runs must have distinct names, got {names}")
    places = places_mod.define_places(reference, cfg["places"])
    if not places:
        raise ValueError(f"reference run {reference.name!r} is too short to define a place")
    params = {"config": cfg, "reference": reference.name, "runs": names}
    writer = MapWriter(out, reference.camera, reference.T_vehicle_camera, params)

    todo = [p for p in places if not writer.has_place(p.index)
            and (places_subset is None or p.index in set(places_subset))]
    ref_frames = {p.index: p.reference_frame for p in places}

    def tasks():
        for p in todo:
            views = places_mod.training_views(p, train, cfg["places"])
            views = [v for v in views if v.run.name == reference.name] + [v for v in views if v.run.name != reference.name]
            negs = []
            for off in cfg["negative_places"]:
                q = p.index + off
                if q in ref_frames:
                    negs.append(reference.image(ref_frames[q], gray=True))
            yield p, views, negs

    stats = {}
    t0 = time.perf_counter()
    bar = tqdm(total=len(places), initial=len(places) - len(todo), desc="build-map places",
               disable=not progress, unit="place")
    if scheduler is not None:
        from distributed import Client, as_completed

        client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
        try:
            futures = [client.submit(_place_task, p, v, n, cfg, pure=False) for p, v, n in tasks()]
            for fut in as_completed(futures):
                idx, (data, st) = fut.result()
                writer.write_place(idx, data)
                stats[idx] = st
                bar.update(1)
        finally:
            if not isinstance(scheduler, Client):
                client.close()
    else:
        from joblib import Parallel, delayed

        par = Parallel(n_jobs=jobs, return_as="generator_unordered", backend="loky" if jobs > 1 else "sequential")
        for idx, (data, st) in par(delayed(_place_task)(p, v, n, cfg) for p, v, n in tasks()):
            writer.write_place(idx, data)
            stats[idx] = st
            bar.update(1)
    bar.close()
    if places_subset is not None and any(not writer.has_place(p.index) for p in places):
        return {"partial": True, "built": sorted(stats)}

    metas = [p.to_dict() for p in places]
    if reference.truth_times is not None:
        # Simulated reference run: record where each place truly is, so the evaluation can tell the
        # localiser's error relative to the map from the map's own (reference INS) georeferencing error.
        from surveys.geometry import interpolate_poses
        truth = interpolate_poses(reference.truth_times, reference.truth_poses,
                                  reference.frame_times[[p.reference_frame for p in places]]).reshape(-1, 4, 4)
        for m, T in zip(metas, truth):
            m["extra"] = {"T_truth_place": T.tolist()}
    writer.finalise(metas)
    return _write_summary(out, places, stats, time.perf_counter() - t0)


def _write_summary(out: Path, places, stats: dict, seconds: float) -> dict:
    """``build_summary.json``: stats of places built in this invocation are merged with earlier ones."""
    path = out / "build_summary.json"
    per_place_path = out / "build_stats.jsonl"
    # per-place stats survive interruptions: append what this invocation built
    with per_place_path.open("a") as fh:
        for idx in sorted(stats):
            st = dict(stats[idx])
            fh.write(json.dumps(st) + "\n")
    allstats = {}
    for line in per_place_path.read_text().splitlines():
        if line.strip():
            st = json.loads(line)
            allstats[st["place"]] = st
    files = sorted((out / "places").glob("*"))
    sizes = [f.stat().st_size for f in files]
    errs = [e for st in allstats.values() for e in st["depth_rel_errors"]]
    rejected = {"not_converged": 0, **{r: 0 for r in REASONS}}
    for st in allstats.values():
        for k, v in st["rejected"].items():
            rejected[k] = rejected.get(k, 0) + v
    summary = {
        "places": len(places),
        "signatures_per_place_mean": float(np.mean([st["signatures"] for st in allstats.values()])) if allstats else 0.0,
        "bytes_per_place_mean": float(np.mean(sizes)) if sizes else 0.0,
        "seconds_per_place_mean": float(np.mean([st["seconds"] for st in allstats.values()])) if allstats else 0.0,
        "landmark_depth_rel_error_median": float(np.median(errs)) if errs else None,
        "landmarks_with_truth": len(errs),
        "rejected": rejected,
        "seconds": seconds,
    }
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    os.replace(tmp, path)
    return summary


def run_from_args(args) -> int:
    runs = [read_run(r) for r in args.runs]
    ref_path = Path(args.reference).resolve()
    reference = next((r for r in runs if r.root.resolve() == ref_path), None) or read_run(args.reference)
    summary = build_map(runs, reference, args.out, jobs=args.jobs, scheduler=args.scheduler)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    from localiser.cli import main as _cli  # noqa: F401  (same arguments as `scenesig build-map`)
    p = argparse.ArgumentParser(prog="python -m mapping.build")
    p.add_argument("runs", nargs="+")
    p.add_argument("--reference", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--scheduler", default=None)
    sys.exit(run_from_args(p.parse_args()))
