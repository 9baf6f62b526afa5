"""Map building (McManus et al. 2015, §3.1-3.2.1): survey runs -> places -> scene-signature banks -> landmarks -> map.

For each place (every 10 m along the reference run):

1. *training images* -- the frame nearest the place from every training run (by INS position and
   heading), the reference run's first; with few runs, each run also gives neighbouring frames within
   the place's segment (``frames_per_run``), and a place that still has fewer than ``min_images``
   images gets photometrically augmented copies of them (:mod:`scenesig.signatures.augment`); the
   selection is :mod:`scenesig.mapping.selection`;
2. *mining* -- :func:`scenesig.signatures.mining.mine_place` (iterative discriminative clustering over the
   fixed template of candidate shapes), with images of other places of the reference run as extra
   negatives;
3. *landmark refinement* -- every surviving classifier is fired over the reference run's ±10 m window;
   :func:`scenesig.mapping.refine.refine_landmarks` runs the temporal RANSAC check, the depth sweep and LM with a
   Huber cost;
4. *georeferencing* (:mod:`scenesig.mapping.georef`) -- the kept bank is fired on every training run's
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
   (:mod:`scenesig.signatures.globaldesc`), so a localiser without GPS can retrieve the places a live image
   may show (:mod:`scenesig.localiser.relocalise`); kept in the place file's meta and copied into the
   manifest (``extra["descriptor"]``), where the localiser reads all of them without opening a place.

Places are independent, so they build in parallel: joblib locally, or a Dask distributed cluster with
``--scheduler``.  The driver process alone writes the map (:class:`scenesig.mapping.store.MapWriter`), so an
interrupted build resumes where it stopped and produces the same bytes.

The command line is ``scenesig build-map RUN... --reference RUN --out maps/NAME [--config JSON]``.

This module holds the build options (:data:`default_config`, :func:`resolve_config`, :func:`load_config`),
the per-place assembly (:func:`build_place`, :func:`mine_and_refine`) and the orchestration
(:func:`build_map`: image vetting, joblib/Dask, georeferencing, the manifest).  The other concerns of a
build are their own modules:

* :mod:`scenesig.mapping.selection` -- which frames of which runs feed a place (training images, augmented
  copies, negatives, the refinement window);
* :mod:`scenesig.mapping.truth_scoring` -- landmark depth errors against the simulator's truth;
* :mod:`scenesig.mapping.build_summary` -- the stats journal (``build_stats.jsonl``) and ``build_summary.json``.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenesig.mapping import georef as georef_mod, layers as layers_mod, places as places_mod
from scenesig.mapping.build_summary import BuildSummary, _append_stats, _read_stats, _weak_message, _write_summary
from scenesig.mapping.pointmap import build_point_features, build_point_features_all
from scenesig.mapping.refine import REASONS, WindowDetections, refine_landmarks
from scenesig.mapping.selection import (
    MAX_FRAMES_PER_RUN,
    MIN_IMAGES,
    _subsample,
    frames_per_run,
    mining_images,
    place_negatives,
    place_views,
)
from scenesig.mapping.store import MapWriter, PlaceData, decode_place, encode_keyframe, place_file_name
from scenesig.mapping.truth_scoring import landmark_depth_errors
from scenesig.signatures import experience, globaldesc
from scenesig.signatures.bank import default_config as bank_default_config
from scenesig.signatures.hog import level_scale
from scenesig.signatures.mining import mine_place
from scenesig.surveys.errors import CorruptImageError, DataError
from scenesig.surveys.geometry import invert
from scenesig.surveys.run import SurveyRun
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "resolve_config", "build_map", "build_place", "mine_and_refine", "MinedPlace", "mining_images",
           "place_views", "place_negatives", "vet_images", "load_config"]

log = logging.getLogger(__name__)

default_config = {
    "places": {},                 # overrides of mapping.places.default_config
    "mining": {},                 # overrides of signatures.mining.default_config
    "refine": {},                 # overrides of mapping.refine.default_config
    "negative_places": [-3, 3],   # reference images of these place offsets serve as extra negatives
    "max_window_frames": 21,      # refinement window subsampled to at most this many frames
    "keyframe_width": 160,
    "points": {},                 # overrides of mapping.pointmap.default_config (point-feature baseline map)
    # layers stored (mapping.layers): "signatures" (always), and for the point-feature baselines "orb",
    # "sift", "xfeat" (the reference run's keyframe, the paper's baseline) and "orb-all", "sift-all",
    # "xfeat-all" (a keyframe from every training run at the place).  The default is what the default
    # method needs.
    "layers": list(layers_mod.DEFAULT_LAYERS),
    # overrides of signatures.detection.default_config for the window detections: two pyramid levels either
    # side (the bank's default is one) let the detector follow a patch that grows or shrinks by up to
    # 41 % over the window instead of lagging (measured on the demo world: median landmark depth error
    # 15 % -> 14 %, 8 % more landmarks kept, +1 s per place)
    "detect": {"scale_search": 2},
    "georeference": {"method": "runs"},  # overrides of mapping.georef.default_config ("runs" | "reference")
    # Mining images per place (mining_images).  Each run that sees the place gives ``frames_per_run``
    # frames around it (None: ceil(min_images / runs), at most max_frames_per_run); a place still
    # short of ``min_images`` gets augmented copies.  Six runs or more keep the paper's one frame per
    # run, so such maps are unchanged.
    "frames_per_run": None,
    "min_images": MIN_IMAGES,
    "max_frames_per_run": MAX_FRAMES_PER_RUN,
    "augment_shift_px": 8.0,      # max left/right shift of an augmented copy (a small heading change)
    # overrides of signatures.experience.default_config: a place seen by one run only is mined with
    # the single-experience settings (the rule counts runs, i.e. real appearances)
    "single_experience": {},
    "descriptor": {},             # overrides of signatures.globaldesc.default_config (place retrieval)
}


def _merge(config):
    # every sub-dict is passed on whole to its stage, which checks it (resolve_config checks them all first)
    cfg = merge_settings(default_config, config, "build",
                         open=tuple(k for k, v in default_config.items() if isinstance(v, dict)))
    cfg["layers"] = layers_mod.parse_layers(cfg["layers"])
    kinds = cfg["points"].get("kinds")
    if kinds is not None and set(kinds) != set(layers_mod.point_plan(cfg["layers"])["extract"]):
        raise ValueError(f"points.kinds {list(kinds)} disagrees with the layers {cfg['layers']}: choose the "
                         f"point-feature families with 'layers' (build-map --layers)")
    return cfg


def resolve_config(config: dict | None = None) -> dict:
    """Every build setting, resolved: ``config`` (overrides of :data:`default_config`) merged with the
    defaults of each stage it configures -- places, mining (with its HOG), refinement, point map (with its
    features), window detection, georeferencing, single-experience rule, place descriptor.  A misspelt
    key anywhere is a ``ValueError`` naming it.  The manifest records this (``params.settings``)."""
    from scenesig.mapping import pointmap
    from scenesig.mapping.refine import default_config as refine_default
    from scenesig.signatures import mining

    cfg = _merge(config)
    return {**cfg,
            "places": merge_settings(places_mod.default_config, cfg["places"], "places"),
            "mining": mining.resolve_config(cfg["mining"]),
            "refine": merge_settings(refine_default, cfg["refine"], "refinement"),
            "points": pointmap.resolve_config(cfg["points"]),
            "detect": merge_settings(bank_default_config, cfg["detect"], "detection"),
            "georeference": georef_mod.resolve_config(cfg["georeference"]),
            "single_experience": merge_settings(experience.default_config, cfg["single_experience"],
                                                "single-experience", open=("mining",)),
            "descriptor": merge_settings(globaldesc.default_config, cfg["descriptor"], "descriptor")}


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


@dataclass
class MinedPlace:
    """What mining and landmark refinement make of one place's views (:func:`mine_and_refine`).

    ``bank`` holds the kept classifiers; ``landmarks`` (n, 3), ``covariances`` (n, 3, 3) and ``depths``
    (n,) are in the vehicle frame of ``views[0]``'s training frame; ``boxes`` (n, 2) are the kept
    classifiers' firings there (NaN where none), ``ref_size`` (n, 2) / ``ref_scale`` (n,) the size and
    scale of firings the landmark explains (NaN otherwise); ``images`` the views' gray training images.
    """

    bank: object
    landmarks: np.ndarray
    covariances: np.ndarray
    depths: np.ndarray
    boxes: np.ndarray
    ref_size: np.ndarray
    ref_scale: np.ndarray
    mined: int
    rejected: dict
    mining: object
    images: list
    n_images: int = 0             # images mined: frames and augmented copies (:func:`mining_images`)
    image_counts: dict = None     # frames_per_run, frames, augmented


def mine_and_refine(views: list, negatives: list[np.ndarray], cfg: dict, rng: int) -> MinedPlace:
    """Mining (§3.2) of the views' training images, then the temporal check and depth refinement
    (§3.2.1) of every survivor over ``views[0]``'s window, with that run's odometry.

    ``views[0]`` is the frame the landmarks are expressed in (at build time the reference run's view;
    a lifelong update passes the live run's view, :mod:`scenesig.mapping.update`).  ``cfg`` is a merged build
    configuration; ``rng`` seeds mining.
    """
    ref = views[0]
    camera, T_vc = ref.run.camera, ref.run.T_vehicle_camera
    images = [v.run.image(v.frame, gray=True) for v in views]
    mined_from, offsets, image_counts = mining_images(rng, views, images, cfg)
    # the training-data rule (signatures.experience): a place seen by one run is a single experience
    mcfg = experience.settings_for(len(views), cfg["mining"], cfg["single_experience"])["mining"]
    bank, mstats = mine_place(mined_from, offsets, config=mcfg, negatives=negatives, n_jobs=1, rng=rng)

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
        ss = int(merge_settings(bank_default_config, cfg["detect"], "detection")["scale_search"])
        spo = int(bank.hog["scales_per_octave"])
        scale_range = np.array([[level_scale(c.level + ss, spo), level_scale(max(0, c.level - ss), spo)]
                                for c in bank.classifiers], dtype=float)
        dets = WindowDetections(uv, np.nan_to_num(scale), np.nan_to_num(prob), area, scale_range)
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
        kept_bank = bank
        landmarks, covs, depths = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
        boxes, ref_size, ref_scale = np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    rejected = {"no_data": int(mstats.rejected_no_data), "textureless": int(mstats.rejected_textureless),
                "not_converged": int(mstats.rejected_not_converged), **counts}
    return MinedPlace(kept_bank, landmarks, covs, depths, boxes, ref_size, ref_scale, int(n), rejected, mstats,
                      images, len(mined_from), image_counts)


def _build_place(place, views, negatives, config):
    cfg = _merge(config)
    t0 = time.perf_counter()
    ref = views[0]
    camera, T_vc = ref.run.camera, ref.run.T_vehicle_camera
    mp = mine_and_refine(views, negatives, cfg, rng=place.index)
    images, kept_bank, n = mp.images, mp.bank, mp.mined
    landmarks, covs, depths, boxes = mp.landmarks, mp.covariances, mp.depths, mp.boxes
    ref_size, ref_scale = mp.ref_size, mp.ref_scale
    keep = np.arange(len(kept_bank))

    rel_err, truth_spread = [], []
    if len(keep):
        rel_err, truth_spread = landmark_depth_errors(ref.run, ref.frame, images[0], boxes, ref_size, ref_scale,
                                                      depths)
    # each training run's INS + its visually solved pose relative to the place: one estimate of the
    # place's world pose per run, combined over all places in build_map (mapping.georef)
    georef_obs = georef_mod.observe_place(place, views, images, kept_bank, landmarks, covs,
                                          Q=cfg["refine"].get("Q"), config=cfg["georeference"])
    seconds = {"signatures": time.perf_counter() - t0}
    plan = layers_mod.point_plan(cfg["layers"])
    points = {}
    # every training run's keyframe, moved into the place frame by the visual solve above
    poses = [np.eye(4)] + [None] * (len(views) - 1)
    for k, o in enumerate(georef_obs[:len(views)]):
        if k and o.get("ok") and o.get("T_place_vehicle") is not None:
            poses[k] = np.asarray(o["T_place_vehicle"], float)
    for kind in plan["extract"]:
        # one family at a time, so each layer's build time is its own
        pcfg = {**cfg["points"], "kinds": [kind]}
        t = time.perf_counter()
        ref_points = build_point_features(ref, camera, T_vc, pcfg)
        t_ref = time.perf_counter() - t
        if kind in plan["reference"]:
            points.update(ref_points)
            seconds[kind] = t_ref
        if kind in plan["all"]:
            t = time.perf_counter()
            points.update(build_point_features_all(views, poses, pcfg, reference_points=ref_points))
            # the reference keyframe is the -all map's first: its cost is the layer's when not stored apart
            seconds[f"{kind}-all"] = time.perf_counter() - t + (0.0 if kind in plan["reference"] else t_ref)
    data = PlaceData(
        bank_arrays=kept_bank.to_arrays(), landmarks=landmarks, covariances=covs,
        classifier_ids=np.arange(len(keep), dtype=np.int64),
        keyframe=encode_keyframe(images[0], width=cfg["keyframe_width"]),
        # the point-feature baseline's keyframe features and 3D points live beside the bank
        points=points,
        meta={"reference_run": ref.run.name, "reference_frame": int(ref.frame),
              "training_runs": [v.run.name for v in views], "detections_at_reference": [[float(v) if np.isfinite(v) else None for v in b] for b in boxes],
              "mined": int(n), "kept": int(len(keep)), "georef": georef_obs,
              # one whole-image descriptor per training run: retrieval sees the place at night and in snow too
              "descriptor": globaldesc.encode(np.stack([globaldesc.describe(im, cfg["descriptor"]) for im in images]))},
    )
    stats = {"place": place.index, "seconds": time.perf_counter() - t0, "mining": mp.mining.as_dict(),
             "runs": len(views), "images": mp.n_images, **mp.image_counts,
             # why the candidate shapes that did not become signatures were dropped: mining (too few
             # images to form partitions, texture, no convergence), then landmark refinement
             "rejected": mp.rejected,
             "depth_rel_errors": rel_err, "depth_truth_spread": truth_spread, "signatures": int(len(keep)),
             "georef_runs_ok": int(sum(bool(o["ok"]) for o in georef_obs)),
             # the cell descriptor the bank was mined on (mining's ``features``)
             "features": str(kept_bank.hog.get("features", "hog")),
             # build time per layer (signatures: mining, refinement, georeferencing observations)
             "seconds_by_layer": seconds}
    return data, stats


def _place_task(place, views, negatives, config, pooled: bool = False):
    """One unit of parallel work (a module-level function so joblib and Dask can ship it).

    ``pooled``: one of several worker processes -- OpenCV runs on one thread, as BLAS does: the
    places keep every core busy, and two OpenCV threads per worker would only contend (its parallel
    loops split rows, so the results are the same either way).  Set for the task only, and restored.
    """
    if not pooled:
        return place.index, build_place(place, views, negatives, config)
    import cv2

    saved = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return place.index, build_place(place, views, negatives, config)
    finally:
        cv2.setNumThreads(saved)


def vet_images(runs: list[SurveyRun], jobs: int = 1, progress: bool = True) -> list[list]:
    """Strictly decode every frame of every run; per run, the ``(frame, CorruptImageError)`` that fail.

    A map mines signatures from its training images, so a truncated frame (decoded grey by a lenient
    decoder) must never reach it: this finds every one before hours of mining, not when a worker
    trips over it.  Decoding runs on ``jobs`` threads (libjpeg-turbo releases the GIL).
    """
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    def check(item):
        r, i = item
        try:
            runs[r].image(i, gray=True)
            return None
        except CorruptImageError as exc:
            return r, i, exc

    items = [(r, i) for r, run in enumerate(runs) for i in range(len(run))]
    bad: list[list] = [[] for _ in runs]
    with ThreadPoolExecutor(max_workers=max(1, int(jobs))) as pool:
        for res in tqdm(pool.map(check, items, chunksize=16), total=len(items), desc="build-map: checking images",
                        unit="frame", disable=not progress):
            if res is not None:
                bad[res[0]].append((res[1], res[2]))
    return bad


def _check_resolutions(train: list[SurveyRun]) -> None:
    """Every training run's images must have the reference run's size: a place's classifiers are mined
    over HOG cells of one geometry (McManus et al. 2015, §3.2), and the map records one camera.  A DataError
    naming the first run that differs (its ``run.toml``)."""
    ref = train[0]
    size = (ref.camera.width, ref.camera.height)
    for run in train[1:]:
        if (run.camera.width, run.camera.height) != size:
            where = Path(run.root) / "run.toml" if run.root is not None else Path(run.name)
            raise DataError(where, f"run {run.name!r} has {run.camera.width}x{run.camera.height} images but the "
                                   f"reference run {ref.name!r} has {size[0]}x{size[1]}: a map is built from "
                                   f"images of one size; resample the run's images (and scale its intrinsics) "
                                   f"or leave it out")


def build_map(runs: list[SurveyRun], reference: SurveyRun, out, jobs: int = 1, scheduler: str | None = None,
              config: dict | None = None, progress: bool = True, places_subset=None,
              skip_corrupt: bool = False) -> BuildSummary | dict:
    """Build (or resume) a map from survey runs; returns the build summary (:class:`BuildSummary`, also
    written to disk as ``build_summary.json``; a build of ``places_subset`` that leaves places unbuilt returns
    ``{"partial": True, "built": [...]}``).

    Parameters
    ----------
    runs : training runs (the reference run is added if missing).
    reference : the map run: defines places and the frames of landmarks.
    out : map folder.
    jobs : places built in parallel with joblib (ignored with ``scheduler``).
    scheduler : Dask scheduler address (``tcp://host:port``) or a ``distributed.Client``.
    places_subset : optional iterable of place indices to build (others are left for a later resume).
    skip_corrupt : every frame is decoded strictly first (:func:`vet_images`); a truncated or corrupt
        one stops the build with a :class:`scenesig.surveys.errors.CorruptImageError` naming it, unless this is
        set: then such frames are left out of the runs (listed in the manifest's parameters, so a
        resume must leave out the same ones) and counted in ``build_summary.json``
        (``frames_corrupt``, ``corrupt_frames``).
    """
    from tqdm import tqdm

    cfg = _merge(config)
    settings = resolve_config(config)     # checks every stage's keys before anything is written
    if scheduler is not None:             # ... and that a cluster can be used
        from scenesig.surveys.extras import require

        require("distributed", "distributed", "build-map --scheduler (a Dask cluster)")
    out = Path(out)
    train = [reference] + [r for r in runs if r.name != reference.name]
    names = [r.name for r in train]
    if len(set(names)) != len(names):
        raise ValueError(f"training runs must have distinct names, got {names}")
    _check_resolutions(train)             # before anything is written: a refused build leaves nothing
    if "xfeat" in layers_mod.point_plan(cfg["layers"])["extract"]:
        from scenesig.signatures.xfeat import model_path

        # a missing XFeat model stops the build here, naming where it looked, not in a worker mid-build;
        # the workers get the file by name (a pool started earlier, or a Dask worker, has another
        # environment), and the manifest records which file built the layer
        found = model_path(((cfg["points"].get("features") or {}).get("xfeat") or {}).get("model"))
        features = dict(cfg["points"].get("features") or {})
        features["xfeat"] = {**(features.get("xfeat") or {}), "model": str(found)}
        cfg["points"] = {**cfg["points"], "features": features}
    bad = vet_images(train, jobs, progress)
    corrupt = [(run, i, exc) for run, b in zip(train, bad) for i, exc in b]
    if corrupt and not skip_corrupt:
        _, _, exc = corrupt[0]
        more = f" (and {len(corrupt) - 1} more corrupt frames)" if len(corrupt) > 1 else ""
        raise CorruptImageError(exc.path, f"{exc.message}{more}; build-map --skip-corrupt leaves such frames out")
    left_out = {}
    if corrupt:
        for run, b in zip(train, bad):
            if b:
                log.warning("%s: leaving out %d corrupt frames (first: %s)", run.name, len(b), b[0][1])
                left_out[run.name] = [run.frame_files[i] for i, _ in b]
        train = [run.without_frames([i for i, _ in b]) if b else run for run, b in zip(train, bad)]
        reference = train[0]
    places = places_mod.define_places(reference, cfg["places"])
    if not places:
        raise ValueError(f"reference run {reference.name!r} is too short to define a place")
    if len(train) == 1:
        n = frames_per_run(cfg, 1)
        log.warning(f"a map from one survey run ({reference.name}): each place is mined from up to {n} frames "
                    f"around it and augmented copies of them (at least {int(cfg['min_images'])} images); it "
                    f"has seen one appearance, so expect it to localise runs of similar appearance only")
    params = {"config": cfg, "settings": settings, "reference": reference.name, "runs": names}
    if left_out:                 # only then: maps built from clean runs keep their bytes
        params["frames_left_out"] = left_out
    writer = MapWriter(out, reference.camera, reference.T_vehicle_camera, params)

    todo = [p for p in places if not writer.has_place(p.index)
            and (places_subset is None or p.index in set(places_subset))]
    ref_frames = {p.index: p.reference_frame for p in places}

    def tasks():
        for p in todo:
            yield p, place_views(p, train, reference, cfg), place_negatives(p, ref_frames, reference, cfg)

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
        for idx, (data, st) in par(delayed(_place_task)(p, v, n, cfg, jobs > 1) for p, v, n in tasks()):
            store(idx, data, st)
    bar.close()
    if places_subset is not None and any(not writer.has_place(p.index) for p in places):
        return {"partial": True, "built": sorted(stats)}
    allstats = _read_stats(out)
    if all(allstats.get(p.index, {}).get("signatures", 0) == 0 for p in places):
        _refuse_empty_map(out, writer, places, allstats, time.perf_counter() - t0)

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
        from scenesig.surveys.geometry import interpolate_poses
        truth = interpolate_poses(reference.truth_times, reference.truth_poses,
                                  reference.frame_times[[p.reference_frame for p in places]]).reshape(-1, 4, 4)
        for m, T in zip(metas, truth):
            m["extra"]["T_truth_place"] = T.tolist()
    writer.finalise(metas)
    corrupt_files = [str(run.root / f) if run.root is not None else f
                     for run in train for f in left_out.get(run.name, [])]
    summary = _write_summary(out, places, allstats, time.perf_counter() - t0, corrupt_files)
    if summary["places_weak"]:
        log.warning(_weak_message(summary, allstats))
    return BuildSummary.from_dict(summary)


def _refuse_empty_map(out: Path, writer: MapWriter, places, allstats: dict, seconds: float) -> None:
    """No place kept a signature: such a map cannot localise, so none is written (the place files and the
    journal go, so a re-run with other settings starts afresh); ``build_summary.json`` stays to say why."""
    summary = _write_summary(out, places, allstats, seconds)
    writer.discard()
    rej = {k: v for k, v in summary["rejected"].items() if v}
    images = sorted({st.get("images", 0) for st in allstats.values()})
    runs = sorted({st.get("runs", 0) for st in allstats.values()})
    raise DataError(out, f"no place kept a scene signature (every candidate shape rejected: {rej}; "
                         f"{'/'.join(map(str, images))} images per place from {'/'.join(map(str, runs))} "
                         f"runs), so no map was written (build_summary.json says why per place). "
                         f"Train with more runs of different appearance, or give each run more frames per "
                         f"place with --frames-per-run N (mining needs about {MIN_IMAGES} images per place: "
                         f"two per partition of the clustering).")


def _written_meta(out: Path, places) -> dict:
    """Per-place metadata of the written place files (georeferencing observations, descriptors)."""
    obs = {}
    for p in places:
        path = out / place_file_name(p.index)
        obs[p.index] = decode_place(path.read_bytes(), path, p.index).meta
    return obs


def load_config(text: str | None) -> dict | None:
    """``--config``: build options (see :data:`default_config`) as JSON text or a ``.json`` file."""
    if not text:
        return None
    path = Path(text)
    src = path.read_text() if text.endswith(".json") and path.is_file() else text
    try:
        cfg = json.loads(src)
    except json.JSONDecodeError as exc:
        raise DataError(path if src is not text else None, f"--config is not valid JSON: {exc.msg}",
                        line=exc.lineno) from None
    if not isinstance(cfg, dict):
        raise ValueError("--config must be a JSON object of build options")
    return cfg
