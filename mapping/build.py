"""Map building (McManus et al. 2015, §3.1-3.2.1): survey runs -> places -> scene-signature banks -> landmarks -> map.

For each place (every 10 m along the reference run):

1. *training images* -- the frame nearest the place from every training run (by INS position and
   heading), the reference run's first;
2. *mining* -- :func:`signatures.mining.mine_place` (iterative discriminative clustering over the
   fixed template of candidate shapes), with images of other places of the reference run as extra
   negatives;
3. *landmark refinement* -- every surviving classifier is fired over the reference run's ±10 m window;
   :func:`mapping.refine.refine_landmarks` runs the temporal RANSAC check, the depth sweep and LM with a
   Huber cost;
4. *georeferencing* (:mod:`mapping.georef`) -- the kept bank is fired on every training run's
   image and that image's pose relative to the place is solved by robust PnP; each run's INS pose
   composed with it is an independent estimate of the place's world pose (the place frame itself is
   exact relative to the scene, but the reference INS alone carries its metre-level per-run offset into
   every place).  Once all places are built, the estimates are combined (Huber mean of position and
   yaw over the runs with a good PnP, roll and pitch from the reference INS), the correction of the
   reference INS pose is smoothed along the route, and the result is the place's ``T_world_place`` in
   the manifest; ``extra["georeference"]`` records the runs used, their spread and the correction.
   ``config["georeference"]["method"] = "reference"`` keeps the paper's reference-INS poses;
5. the kept classifiers, their landmarks (place frame) and covariances go to the map store (the
   per-run georeferencing observations in the place file's meta, so a resumed build recombines them);
6. *place descriptors* -- a compact whole-image descriptor of every training image of the place
   (:mod:`signatures.globaldesc`), so a localiser without GPS can retrieve the places a live image
   may show (:mod:`localiser.relocalise`); kept in the place file's meta and copied into the
   manifest (``extra["descriptor"]``), where the localiser reads all of them without opening a place.

Places are independent, so they build in parallel: joblib locally, or a Dask distributed cluster with
``--scheduler``.  The driver process alone writes the map (:class:`mapping.store.MapWriter`), so an
interrupted build resumes where it stopped and produces the same bytes.

The command line is ``scenesig build-map RUN... --reference RUN --out maps/NAME [--config JSON]``.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from surveys.settings import merge_settings
from surveys.geometry import invert
from surveys.run import SurveyRun
from signatures import globaldesc
from signatures.mining import mine_place
from signatures.bank import default_config as bank_default_config
from signatures.hog import level_scale
from mapping import georef as georef_mod
from mapping import places as places_mod
from mapping.pointmap import build_point_features
from mapping.refine import Detections, REASONS, refine_landmarks
from mapping.store import MapWriter, PlaceData, decode_place, encode_keyframe, place_file_name
from surveys.io import atomic_write_bytes

__all__ = ["default_config", "build_map", "build_place", "load_config"]

default_config = {
    "places": {},                 # overrides of mapping.places.default_config
    "mining": {},                 # overrides of signatures.mining.default_config
    "refine": {},                 # overrides of mapping.refine.default_config
    "negative_places": [-3, 3],   # reference images of these place offsets serve as extra negatives
    "max_window_frames": 21,      # refinement window subsampled to at most this many frames
    "keyframe_width": 160,
    "points": {},                 # overrides of mapping.pointmap.default_config (ORB/SIFT baseline map)
    # overrides of signatures.bank.default_config for the window detections: two pyramid levels either
    # side (the bank's default is one) let the detector follow a patch that grows or shrinks by up to
    # 41 % over the window instead of lagging (measured on the demo world: median landmark depth error
    # 15 % -> 14 %, 8 % more landmarks kept, +1 s per place)
    "detect": {"scale_search": 2},
    "georeference": {"method": "runs"},  # overrides of mapping.georef.default_config ("runs" | "reference")
    "descriptor": {},             # overrides of signatures.globaldesc.default_config (place retrieval)
}


def _merge(config):
    # every sub-dict is passed on whole to its stage, which checks it
    return merge_settings(default_config, config, "build",
                          open=tuple(k for k, v in default_config.items() if isinstance(v, dict)))


def _subsample(window: np.ndarray, centre: int, n: int, positions: np.ndarray | None = None) -> np.ndarray:
    """At most ``n`` frames of the window, evenly spread, always including the place's own frame.

    With ``positions`` (W, 3) of the window frames, the frames are spread evenly in distance travelled,
    not in frame count: a stop in the window would otherwise fill it with views from one spot, which
    carry no parallax and outvote the moving frames in the depth fit.
    """
    if len(window) <= n:
        return window
    if positions is None:
        pick = np.unique(np.round(np.linspace(0, len(window) - 1, n)).astype(int))
    else:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
        pick = np.unique(np.searchsorted(s, np.linspace(0.0, s[-1], n)).clip(0, len(window) - 1))
    out = np.union1d(window[pick], [centre])
    return out


def _true_depths(run: SurveyRun, frame: int, image: np.ndarray, boxes: np.ndarray, scales: np.ndarray):
    """Ground-truth depth (m) of each signature's patch in a simulated frame, or None for real data.

    A signature is a patch, not a point, and its classifier sees the patch's HOG: image gradients at the
    pyramid level it fired at.  So the reference depth is the median of the simulator's depth buffer over
    the whole firing box, each pixel weighted by the gradient magnitude of ``image`` at that level (sky
    has no depth and is left out; textureless road or wall, which HOG hardly sees, counts little).  The
    spread ``(q75 - q25) / median`` of the same weighted distribution says how far the patch is from
    having one depth (large when it straddles a depth discontinuity).

    Parameters
    ----------
    image : (H, W) gray reference image; boxes : (n, 4) ``x0, y0, x1, y1`` firing boxes (pixels);
    scales : (n,) pyramid scale of each firing.

    Returns
    -------
    (depth, spread) : two (n,) arrays (NaN where the box holds no textured non-sky pixel), or None.
    """
    import cv2

    from surveys.sim.truth import depth_image

    depth = depth_image(run, frame)
    if depth is None:
        return None
    out = np.full(len(boxes), np.nan)
    spread = np.full(len(boxes), np.nan)
    h, w = depth.shape
    img = np.asarray(image, dtype=np.float32)
    grads = {}
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        if not (np.isfinite([x0, y0, x1, y1]).all() and np.isfinite(scales[i]) and scales[i] > 0):
            continue
        s = round(float(scales[i]), 4)
        if s not in grads:  # gradient magnitude at the firing's level, brought back to full resolution
            small = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
            g = np.hypot(cv2.Sobel(small, cv2.CV_32F, 1, 0), cv2.Sobel(small, cv2.CV_32F, 0, 1))
            grads[s] = cv2.resize(g, (w, h), interpolation=cv2.INTER_LINEAR)
        r0, r1 = int(max(0, np.floor(y0))), int(min(h, np.ceil(y1)))
        c0, c1 = int(max(0, np.floor(x0))), int(min(w, np.ceil(x1)))
        d = depth[r0:r1, c0:c1].ravel()
        wt = grads[s][r0:r1, c0:c1].ravel()
        ok = np.isfinite(d) & (wt > 0)
        if not ok.any():
            continue
        order = np.argsort(d[ok], kind="stable")
        ds, cw = d[ok][order], np.cumsum(wt[ok][order], dtype=float)
        q25, q50, q75 = ds[np.searchsorted(cw, np.array([0.25, 0.5, 0.75]) * cw[-1]).clip(0, ds.size - 1)]
        out[i], spread[i] = float(q50), float((q75 - q25) / q50)
    return out, spread


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

    Notes
    -----
    BLAS runs on one thread here, whatever process this lands in: a multi-threaded BLAS sums in another
    order, so a place built in the driver (``--jobs 1``) would differ in its last bits from one built in
    a joblib or Dask worker (which start with one BLAS thread each) -- and a map must be the same bytes
    however it was built.  Places, not BLAS threads, are the unit of parallelism.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return _build_place(place, views, negatives, config)


def _build_place(place, views, negatives, config):
    cfg = _merge(config)
    t0 = time.perf_counter()
    ref = views[0]
    camera, T_vc = ref.run.camera, ref.run.T_vehicle_camera
    images = [v.run.image(v.frame, gray=True) for v in views]
    bank, mstats = mine_place(images, config=cfg["mining"], negatives=negatives, n_jobs=1, rng=place.index)

    window = _subsample(ref.window, ref.frame, cfg["max_window_frames"], ref.T_frame_window[:, :3, 3])
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
        size = np.full((n, len(window), 2), np.nan)
        for f, j in enumerate(window):
            img = images[0] if j == ref.frame else ref.run.image(int(j), gray=True)
            d = bank.detect(img, top_n=1, config=cfg["detect"] or None)
            uv[:, f, 0], uv[:, f, 1] = d.x[:, 0], d.y[:, 0]
            scale[:, f], prob[:, f] = d.scale[:, 0], d.prob[:, 0]
            size[:, f, 0], size[:, f, 1] = d.width[:, 0], d.height[:, 0]
            # patch area a of eq. 5: the firing's box in image pixels (0 = no firing: not used)
            area[:, f] = np.nan_to_num(d.width[:, 0] * d.height[:, 0], nan=0.0)
        # the scales the detector searched (nominal level +- scale_search): refinement gates firings by
        # the scale the landmark's depth predicts (mapping.refine, "scale_tolerance")
        ss = int({**bank_default_config, **cfg["detect"]}["scale_search"])
        spo = int(bank.hog["scales_per_octave"])
        scale_range = np.array([[level_scale(c.level + ss, spo), level_scale(max(0, c.level - ss), spo)]
                                for c in bank.classifiers], dtype=float)
        dets = Detections(uv, np.nan_to_num(scale), np.nan_to_num(prob), area, scale_range)
        # T_{j,p}: the place frame (the reference frame's vehicle pose) seen from window frame j
        res = refine_landmarks(dets, invert(T_frame_window), camera, T_vc, reference=reference,
                               config=cfg["refine"] or None)
        keep = np.nonzero(res.kept)[0]
        counts.update({r: int((res.reason == r).sum()) for r in REASONS})
        kept_bank = bank.select(keep)
        landmarks, covs, depths = res.points[keep], res.covariances[keep], res.depth[keep]
        boxes = np.stack([uv[keep, reference, 0], uv[keep, reference, 1]], axis=1) if len(keep) else np.zeros((0, 2))
        # the firing at the reference frame, where it is one the landmark explains (else it is not the
        # landmark's patch and there is no truth to compare with)
        at_ref = res.fit_inliers[keep, reference]
        ref_size = np.where(at_ref[:, None], size[keep, reference], np.nan)
        ref_scale = np.where(at_ref, scale[keep, reference], np.nan)
    else:
        keep = np.zeros(0, int)
        kept_bank = bank
        landmarks, covs, depths = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
        boxes = np.zeros((0, 2))

    rel_err, truth_spread = [], []
    if len(keep):
        # Detections' (x, y) are window centres in pixel-centre coordinates (pixel i spans i-0.5..i+0.5)
        centre = boxes + 0.5
        box_xyxy = np.concatenate([centre - ref_size / 2, centre + ref_size / 2], axis=1)
        truth = _true_depths(ref.run, ref.frame, images[0], box_xyxy, ref_scale)
        if truth is not None:
            truth, spread = truth
            ok = np.isfinite(truth) & (truth > 0)
            rel_err = (np.abs(depths[ok] - truth[ok]) / truth[ok]).tolist()
            truth_spread = spread[ok].tolist()
    # each training run's INS + its visually solved pose relative to the place: one estimate of the
    # place's world pose per run, combined over all places in build_map (mapping.georef)
    georef_obs = georef_mod.observe_place(place, views, images, kept_bank, landmarks, covs,
                                          Q=cfg["refine"].get("Q"), config=cfg["georeference"])
    data = PlaceData(
        bank_arrays=kept_bank.to_arrays(), landmarks=landmarks, covariances=covs,
        classifier_ids=np.arange(len(keep), dtype=np.int64),
        keyframe=encode_keyframe(images[0], width=cfg["keyframe_width"]),
        # the point-feature baseline's keyframe features and 3D points live beside the bank
        points=build_point_features(ref, camera, T_vc, cfg["points"]),
        meta={"reference_run": ref.run.name, "reference_frame": int(ref.frame),
              "training_runs": [v.run.name for v in views], "detections_at_reference": [[float(v) if np.isfinite(v) else None for v in b] for b in boxes],
              "mined": int(n), "kept": int(len(keep)), "georef": georef_obs,
              # one whole-image descriptor per training run: retrieval sees the place at night and in snow too
              "descriptor": globaldesc.encode(np.stack([globaldesc.describe(im, cfg["descriptor"]) for im in images]))},
    )
    stats = {"place": place.index, "seconds": time.perf_counter() - t0, "mining": mstats.as_dict(),
             "rejected": {"not_converged": int(mstats.rejected_not_converged), **counts},
             "depth_rel_errors": rel_err, "depth_truth_spread": truth_spread, "signatures": int(len(keep)),
             "georef_runs_ok": int(sum(bool(o["ok"]) for o in georef_obs))}
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

    def store(idx, data, st):
        # Stats first, then the place file: killed in between, the place is not built and is rebuilt
        # (its later stats line wins); the other order would keep the place and lose its stats.
        _append_stats(out, st)
        writer.write_place(idx, data)
        stats[idx] = st
        bar.update(1)

    if scheduler is not None:
        from distributed import Client, as_completed

        client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
        try:
            futures = [client.submit(_place_task, p, v, n, cfg, pure=False) for p, v, n in tasks()]
            for fut in as_completed(futures):
                idx, (data, st) = fut.result()
                store(idx, data, st)
        finally:
            if not isinstance(scheduler, Client):
                client.close()
    else:
        from joblib import Parallel, delayed

        par = Parallel(n_jobs=jobs, return_as="generator_unordered", backend="loky" if jobs > 1 else "sequential")
        for idx, (data, st) in par(delayed(_place_task)(p, v, n, cfg) for p, v, n in tasks()):
            store(idx, data, st)
    bar.close()
    if places_subset is not None and any(not writer.has_place(p.index) for p in places):
        return {"partial": True, "built": sorted(stats)}

    metas = [p.to_dict() for p in places]
    # Georeferencing from every training run (mapping.georef); the per-run observations are read back
    # from the place files so a resumed build combines exactly what an uninterrupted one would.
    metas_written = _written_meta(out, places)
    poses, georef_extra = georef_mod.georeference_places(
        places, {i: w.get("georef", []) for i, w in metas_written.items()}, cfg["georeference"])
    for m in metas:
        m["T_world_place"] = poses[m["index"]].tolist()
        m["extra"] = {"georeference": georef_extra[m["index"]]}
        if "descriptor" in metas_written[m["index"]]:
            m["extra"]["descriptor"] = metas_written[m["index"]]["descriptor"]
    if reference.truth_times is not None:
        # Simulated reference run: record where each place truly is, so the evaluation can tell the
        # localiser's error relative to the map from the map's own georeferencing error.
        from surveys.geometry import interpolate_poses
        truth = interpolate_poses(reference.truth_times, reference.truth_poses,
                                  reference.frame_times[[p.reference_frame for p in places]]).reshape(-1, 4, 4)
        for m, T in zip(metas, truth):
            m["extra"]["T_truth_place"] = T.tolist()
    writer.finalise(metas)
    return _write_summary(out, places, stats, time.perf_counter() - t0)


def _written_meta(out: Path, places) -> dict:
    """Per-place metadata of the written place files (georeferencing observations, descriptors)."""
    obs = {}
    for p in places:
        path = out / place_file_name(p.index)
        obs[p.index] = decode_place(path.read_bytes(), path, p.index).meta
    return obs


def _append_stats(out: Path, st: dict) -> None:
    """Journal one place's build stats just before its file is written, so they survive an interruption
    (a resumed build skips the place and would otherwise lose them); a later line for a place wins."""
    with (Path(out) / "build_stats.jsonl").open("a") as fh:
        fh.write(json.dumps(st) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def _write_summary(out: Path, places, stats: dict, seconds: float) -> dict:
    """``build_summary.json`` from every place's stats in ``build_stats.jsonl`` (this and earlier runs)."""
    path = out / "build_summary.json"
    per_place_path = out / "build_stats.jsonl"
    allstats = {}
    for line in (per_place_path.read_text().splitlines() if per_place_path.exists() else []):
        try:
            st = json.loads(line)
        except json.JSONDecodeError:  # a torn last line of a killed build: that place was rebuilt
            continue
        allstats[st["place"]] = st
    files = sorted((out / "places").glob("place_*.npz"))
    sizes = [f.stat().st_size for f in files]
    errs = [e for st in allstats.values() for e in st["depth_rel_errors"]]
    # truth spread of each error's patch ((q75 - q25) / median of its depths): < 0.3 = one surface
    spread = [s for st in allstats.values() for s in st.get("depth_truth_spread", [np.nan] * len(st["depth_rel_errors"]))]
    single = [e for e, s in zip(errs, spread) if s < 0.3]
    rejected = {"not_converged": 0, **{r: 0 for r in REASONS}}
    for st in allstats.values():
        for k, v in st["rejected"].items():
            rejected[k] = rejected.get(k, 0) + v
    summary = {
        "places": len(places),
        "signatures_per_place_mean": float(np.mean([st["signatures"] for st in allstats.values()])) if allstats else 0.0,
        "bytes_per_place_mean": float(np.mean(sizes)) if sizes else 0.0,
        # where the bytes go: the scene-signature bank and its landmarks, the point-feature baseline's
        # keyframe features, the keyframe image for figures, and the metadata
        "bytes_per_place_by_part_mean": _bytes_by_part(files),
        "seconds_per_place_mean": float(np.mean([st["seconds"] for st in allstats.values()])) if allstats else 0.0,
        "landmark_depth_rel_error_median": float(np.median(errs)) if errs else None,
        "landmark_depth_rel_error_quartiles": [float(q) for q in np.percentile(errs, [25, 50, 75])] if errs else None,
        "landmarks_with_truth": len(errs),
        # patches on one surface only (no depth discontinuity inside): the truth is unambiguous there
        "landmark_depth_rel_error_median_single_depth": float(np.median(single)) if single else None,
        "landmarks_single_depth": len(single),
        "rejected": rejected,
        "seconds": seconds,
    }
    atomic_write_bytes(path, (json.dumps(summary, indent=2) + "\n").encode())
    return summary


#: Parts of a place file, by member-name prefix (mapping.store's layout).
_PARTS = {"signatures": ("bank/", "landmarks", "covariances", "classifier_ids"), "point_features": ("points/",),
          "keyframe": ("keyframe",)}


def _bytes_by_part(files) -> dict:
    """Mean stored (compressed) bytes per place file of each part in :data:`_PARTS` (the rest: ``meta``)."""
    import zipfile

    totals = {k: 0 for k in (*_PARTS, "meta")}
    for f in files:
        with zipfile.ZipFile(f) as z:
            for info in z.infolist():
                part = next((k for k, prefixes in _PARTS.items() if info.filename.startswith(prefixes)), "meta")
                # the member's share of the file: its compressed data plus its local and central headers
                totals[part] += info.compress_size + 30 + 46 + 2 * len(info.filename.encode())
    return {k: (v / len(files) if files else 0.0) for k, v in totals.items()}


def load_config(text: str | None) -> dict | None:
    """``--config``: build options (see :data:`default_config`) as JSON text or a ``.json`` file."""
    if not text:
        return None
    path = Path(text)
    src = path.read_text() if text.endswith(".json") and path.is_file() else text
    try:
        cfg = json.loads(src)
    except json.JSONDecodeError as exc:
        from surveys.errors import DataError
        raise DataError(path if src is not text else None, f"--config is not valid JSON: {exc.msg}",
                        line=exc.lineno) from None
    if not isinstance(cfg, dict):
        raise ValueError("--config must be a JSON object of build options")
    return cfg
