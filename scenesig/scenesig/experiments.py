"""The paper's experiments (McManus et al. 2015, §4): feature matching (Figs 11-14) and localisation
(Figs 15-25) -- the computations; their figures and output files are :mod:`scenesig.plots`.

**Matching experiment** (§4.2) -- the front end alone, without geometry or motion checks.  For every
place and every test run, the run's frame nearest the place *by ground truth* (so the live and map
viewpoints agree and the transformation between them is close to identity, by construction) is
matched against the map.  A match counts when the feature sits in the same place in both images:
``||y_map - y_live|| < δ`` with δ = 15 px.  For scene signatures the map positions are the bank's
detections in the reference keyframe (``PlaceData.meta["detections_at_reference"]``) and the live
ones the bank's best detection in the live frame; for ORB and SIFT the map positions are the keyframe
features the point-feature localiser uses (those with a 3D point) and the live ones their matches by
the point localiser's matcher (:mod:`scenesig.localiser.pointmethod`: mutual nearest neighbour + ratio 0.8, no
prior gating).  Outputs: matches per place per run
(Figs 11, 14) and heat maps of where matches fall -- +1 for every pixel inside a matched shape, averaged
over the runs, per place and over all places (Figs 12, 13).

**Localisation experiment** (§4.3-4.4) -- from ``scenesig localise`` outputs (``metrics.json``,
``frames.csv``, ``trajectory.tum``): per run, lateral and heading errors against truth for every method
and for the raw INS, speed, matches per frame with the localised frames marked (Figs 15-24); and the
dead-reckoning plot (Fig. 25): for each distance d, the probability of travelling more than d blind
(distance-weighted, so its value at 20 m is ``blind_fraction_over_20m``), per method over all runs.

``scenesig experiment matching MAP RUN... --out DIR [--reference RUN]`` and
``scenesig experiment localisation RESULT... --out DIR [--runs RUN...]``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenesig.localiser.evaluation import dead_reckoning_curve, lateral_heading_errors, travelled
from scenesig.localiser.outputs import reference_path
from scenesig.localiser.pointmethod import match_to_map, resolve_config as resolve_point_config
from scenesig.mapping.pointmap import point_features
from scenesig.mapping.store import MapStore
from scenesig.signatures.bank import Bank
from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import interpolate_poses, yaw_of
from scenesig.surveys.run import SurveyRun, read_run
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "resolve_config", "MatchingResult", "aligned_frame", "signature_matches", "point_matches",
           "matching_experiment", "LocaliseOutput", "read_localise_output", "find_localise_outputs",
           "frame_distances", "ins_errors", "speed", "dead_reckoning", "summary_rows", "find_runs"]

default_config = {
    "delta_px": 15.0,               # McManus et al. 2015, §4.2: a match agrees when within 15 px in both images
    "methods": ["signatures", "orb", "sift"],
    "max_frame_distance_m": 5.0,    # a run whose nearest frame is further than this does not pass the place
    "max_heading_deg": 30.0,
    "heat_scale": 0.25,             # heat maps accumulated at this fraction of the image size
    "heat_places": 8,               # places shown in the heat-map figure (evenly spread) + the average
    "point": {},                    # overrides of localiser.pointmethod.default_config
}


def _merge(config: dict | None) -> dict:
    cfg = merge_settings(default_config, config, "experiment", open=("point",))
    bad = [m for m in cfg["methods"] if m not in ("signatures", "orb", "sift")]
    if bad:
        raise ValueError(f"unknown method(s) {bad}; choose from signatures, orb, sift")
    resolve_point_config(cfg["point"])          # checked here (point_matches resolves it per call)
    return cfg


def resolve_config(config: dict | None = None) -> dict:
    """Every setting of the matching experiment, its point-feature matcher's included (resolved)."""
    cfg = _merge(config)
    return {**cfg, "point": resolve_point_config(cfg["point"])}


# ==================================================================================================
# matching experiment (§4.2, Figs 11-14)
# ==================================================================================================
def _truth_of(run: SurveyRun):
    if run.truth_times is not None:
        return run.truth_times, run.truth_poses
    if run.groundtruth_times is not None:
        return run.groundtruth_times, run.groundtruth_poses
    where = (run.root / "truth.tum") if run.root is not None else Path(run.name)
    raise DataError(where, "the matching experiment needs ground truth (truth.tum or groundtruth.tum)")


def aligned_frame(run: SurveyRun, T_world_target: np.ndarray, max_distance_m: float = 5.0,
                  max_heading_deg: float = 30.0, frame_poses: np.ndarray | None = None) -> int | None:
    """Index of the run's frame nearest ``T_world_target`` by ground truth (None if it does not pass there).

    Only frames heading within ``max_heading_deg`` of the target count (a place passed the other way
    round shows another scene).
    """
    if frame_poses is None:
        tt, tp = _truth_of(run)
        frame_poses = interpolate_poses(tt, tp, run.frame_times).reshape(-1, 4, 4)
    T = np.asarray(T_world_target, dtype=float)
    d = np.linalg.norm(frame_poses[:, :2, 3] - T[:2, 3], axis=1)
    dyaw = np.abs(np.angle(np.exp(1j * (yaw_of(frame_poses) - yaw_of(T)))))
    d = np.where(dyaw <= np.radians(max_heading_deg), d, np.inf)
    i = int(np.argmin(d))
    return i if d[i] <= max_distance_m else None


def _boxes_heat(heat: np.ndarray, boxes: np.ndarray, scale: float) -> None:
    """Add +1 to every (scaled) pixel inside each box ``x0, y0, x1, y1`` (paper's heat maps)."""
    h, w = heat.shape
    for x0, y0, x1, y1 in np.asarray(boxes, dtype=float).reshape(-1, 4) * scale:
        c0, c1 = int(max(0, np.floor(x0))), int(min(w, np.ceil(x1)))
        r0, r1 = int(max(0, np.floor(y0))), int(min(h, np.ceil(y1)))
        if c1 > c0 and r1 > r0:
            heat[r0:r1, c0:c1] += 1.0


def signature_matches(bank: Bank, reference_xy: np.ndarray, image: np.ndarray, delta_px: float = 15.0):
    """Scene-signature matches of one live image: classifiers whose best detection is within δ of the map's.

    Parameters
    ----------
    bank : the place's bank; ``reference_xy`` (n, 2) its detections in the map keyframe.
    image : live image (gray or BGR; converted as the bank's HOG wants).

    Returns
    -------
    matched : (n,) bool; boxes : (m, 4) ``x0, y0, x1, y1`` of the matched live detections.
    """
    ref = np.asarray(reference_xy, dtype=float).reshape(-1, 2)
    if len(bank) == 0:
        return np.zeros(0, bool), np.zeros((0, 4))
    if len(ref) != len(bank):
        raise ValueError(f"{len(ref)} reference detections for a bank of {len(bank)} classifiers")
    img = _image_for(image, bool(bank.hog.get("color", False)))
    d = bank.detect(img, top_n=1)
    live = np.column_stack([d.x[:, 0], d.y[:, 0]])
    with np.errstate(invalid="ignore"):
        matched = np.linalg.norm(live - ref, axis=1) < delta_px
    return matched, d.boxes(0)[matched]


def point_matches(points: dict, kind: str, image: np.ndarray, delta_px: float = 15.0, config: dict | None = None):
    """ORB/SIFT matches (the point localiser's matcher, without prior gating) of a live image to a place's keyframe features within δ.

    Returns
    -------
    n_matched : int; boxes : (m, 4) squares of the live keypoints' size around the matched ones;
    n_putative : int, matches before the δ test.
    """
    from scenesig.signatures.pointfeatures import extract

    cfg = resolve_point_config(config)
    mapf = point_features(points, kind)
    if mapf is None or not len(mapf):
        return 0, np.zeros((0, 4)), 0
    live = extract(_image_for(image, False), kind, n_features=int(cfg["n_features"]), config=cfg["features"])
    if not len(live):
        return 0, np.zeros((0, 4)), 0
    m = match_to_map(live, mapf, cfg["match"], float(cfg["ratio"]), image_size=(image.shape[1], image.shape[0]),
                     gms=cfg["gms"])
    dist = np.linalg.norm(live.xy[m.train] - mapf.xy[m.query], axis=1)
    ok = dist < delta_px
    xy = live.xy[m.train[ok]].astype(float)
    half = 0.5 * np.maximum(live.size[m.train[ok]].astype(float), 1.0)[:, None]
    return int(ok.sum()), np.concatenate([xy - half, xy + half], axis=1), int(len(m))


def _image_for(image: np.ndarray, color: bool) -> np.ndarray:
    import cv2

    if color:
        return image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


@dataclass
class MatchingResult:
    """Matches per method, run and place (NaN where a run does not pass a place), and heat maps."""

    places: list
    runs: list
    conditions: list
    methods: list
    counts: dict                      # method -> (R, P) float array
    frames: np.ndarray                # (R, P) aligned frame index (-1: run does not pass)
    heat: dict                        # method -> (P, h, w) mean over runs of +1-per-pixel maps
    delta_px: float = 15.0
    putative: dict = field(default_factory=dict)   # method -> (R, P) matches before the δ test (points)

    def summary(self) -> dict:
        """Per method and run: mean matches per place, share of passed places with >= 1 / >= 10 matches."""
        out = {}
        for m in self.methods:
            rows = {}
            for r, name in enumerate(self.runs):
                c = self.counts[m][r]
                c = c[np.isfinite(c)]
                rows[name] = {"conditions": self.conditions[r], "places": int(len(c)),
                              "matches_mean": float(np.mean(c)) if len(c) else None,
                              "places_with_match": float(np.mean(c >= 1)) if len(c) else None,
                              "places_with_10": float(np.mean(c >= 10)) if len(c) else None}
            out[m] = rows
        return out

    def to_json(self) -> dict:
        def lst(a):
            return [[None if not np.isfinite(v) else float(v) for v in row] for row in np.asarray(a, float)]

        return {"delta_px": self.delta_px, "places": [int(p) for p in self.places], "runs": list(self.runs),
                "conditions": [list(c) for c in self.conditions], "methods": list(self.methods),
                "frames": np.asarray(self.frames).tolist(), "counts": {m: lst(self.counts[m]) for m in self.methods},
                "putative": {m: lst(v) for m, v in self.putative.items()}, "summary": self.summary()}


def matching_experiment(store: MapStore, runs: list, reference: SurveyRun | None = None, config: dict | None = None,
                        progress: bool = True) -> MatchingResult:
    """Run the matching experiment of §4.2 on a map and test runs.

    Parameters
    ----------
    store : the map (banks, reference detections and point features per place).
    runs : test runs (with images and ground truth).
    reference : the map's reference run; when given (and it has truth), places are located by its
        truth at each place's reference frame, which is where the map keyframe really was (the place
        pose is its INS pose, metres off on a bad day); otherwise by the place pose.
    config : overrides of :data:`default_config`.
    """
    from tqdm import tqdm

    cfg = _merge(config)
    methods = list(cfg["methods"])
    from scenesig.mapping.layers import store_layers

    have = store_layers(store)
    lacking = [m for m in methods if m not in have]
    if lacking:
        # a point-feature family the map was built without (build-map --layers): no keyframe to match
        import logging

        logging.getLogger(__name__).warning("map %s has no %s layer: left out of the matching experiment",
                                            store.root, ", ".join(lacking))
        methods = [m for m in methods if m in have]
    places = sorted(store.places)
    R, P = len(runs), len(places)
    sc = float(cfg["heat_scale"])
    hh, hw = max(1, round(store.camera.height * sc)), max(1, round(store.camera.width * sc))
    counts = {m: np.full((R, P), np.nan) for m in methods}
    putative = {m: np.full((R, P), np.nan) for m in methods if m != "signatures"}
    heat_sum = {m: np.zeros((P, hh, hw), np.float32) for m in methods}
    heat_n = np.zeros(P, int)
    frames = np.full((R, P), -1, int)
    ref_poses = None
    if reference is not None and reference.truth_times is not None:
        ref_poses = interpolate_poses(reference.truth_times, reference.truth_poses, reference.frame_times).reshape(-1, 4, 4)
    run_poses = [interpolate_poses(*_truth_of(r), r.frame_times).reshape(-1, 4, 4) for r in runs]
    bar = tqdm(total=R * P, desc="matching experiment", unit="image", disable=not progress)
    for j, p in enumerate(places):
        data = store.load_place(p)
        target = store.places[p].T_world_place
        rf = data.meta.get("reference_frame")
        if ref_poses is not None and rf is not None and data.meta.get("reference_run") in (None, reference.name):
            target = ref_poses[int(rf)]
        bank = ref_xy = None
        if "signatures" in methods:
            bank = Bank.from_arrays(data.bank_arrays) if data.bank_arrays else Bank([])
            ids = np.asarray(data.classifier_ids, dtype=int)
            if len(bank) and len(ids) and len(ids) != len(bank):
                bank = bank.select(ids)
            ref_xy = data.meta.get("detections_at_reference")
            if ref_xy is None:   # maps without stored reference detections: the classifiers' nominal positions
                ref_xy = [c.nominal_xy for c in bank.classifiers]
            ref_xy = np.asarray(ref_xy, dtype=float).reshape(-1, 2)
        for r, run in enumerate(runs):
            i = aligned_frame(run, target, cfg["max_frame_distance_m"], cfg["max_heading_deg"], run_poses[r])
            bar.update(1)
            if i is None:
                continue
            frames[r, j] = i
            image = run.image(i)
            heat_n[j] += 1
            for m in methods:
                if m == "signatures":
                    matched, boxes = signature_matches(bank, ref_xy, image, cfg["delta_px"])
                    counts[m][r, j] = float(matched.sum())
                else:
                    n, boxes, n_put = point_matches(data.points, m, image, cfg["delta_px"], cfg["point"])
                    counts[m][r, j] = float(n)
                    putative[m][r, j] = float(n_put)
                _boxes_heat(heat_sum[m][j], boxes, sc)
    bar.close()
    heat = {m: heat_sum[m] / np.maximum(heat_n, 1)[:, None, None] for m in methods}
    return MatchingResult(places, [r.name for r in runs], [list(r.conditions) for r in runs], methods, counts,
                          frames, heat, float(cfg["delta_px"]), putative)


# ==================================================================================================
# localisation experiment (§4.3-4.4, Figs 15-25)
# ==================================================================================================
@dataclass
class LocaliseOutput:
    """One ``scenesig localise`` output folder."""

    folder: Path
    metrics: dict
    frames: dict                      # column -> (N,) array (frames.csv)
    times: np.ndarray                 # (N,) frame times
    poses: np.ndarray                 # (N,4,4) estimates (NaN before a localiser without INS/GPS first
                                      # found itself: trajectory.tum has no pose there)

    @property
    def method(self) -> str:
        """The method's name; ``"... (no GPS)"`` for a run localised with ``--oracle none``."""
        name = str(self.metrics.get("method", "?"))
        return f"{name} (no GPS)" if self.metrics.get("oracle") == "none" else name

    @property
    def run(self) -> str:
        return str(self.metrics.get("run", "?"))

    @property
    def localised(self) -> np.ndarray:
        return self.frames["localised"] > 0.5


def read_localise_output(folder) -> LocaliseOutput:
    """Read ``metrics.json``, ``frames.csv`` and ``trajectory.tum`` of a localise output folder."""
    from scenesig.surveys.localisation import Localisation

    loc = Localisation.from_folder(folder)
    return LocaliseOutput(Path(folder), loc.metrics or {}, loc.frames, loc.times, loc.poses)


def find_localise_outputs(paths) -> list[Path]:
    """Localise output folders: each path itself if it has ``metrics.json``, else those below it (sorted)."""
    found = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise DataError(p, "no such file or folder")
        if (p / "metrics.json").is_file():
            found.append(p)
        elif p.is_dir():
            found.extend(sorted(m.parent for m in p.rglob("metrics.json")))
        else:
            raise DataError(p, "not a localise output folder (no metrics.json) nor a folder containing them")
    seen, out = set(), []
    for f in found:
        r = f.resolve()
        if r not in seen:
            seen.add(r)
            out.append(f)
    return out


def frame_distances(output: LocaliseOutput, run: SurveyRun | None = None) -> np.ndarray:
    """Cumulative distance (m) at each frame: along the truth when the run is at hand, else the estimate.

    The estimate jumps at oracle resets; steps longer than 5x the median step (and 3 m) are replaced by
    the median so a reset does not add distance.
    """
    if run is not None:
        tt, tp = _truth_of(run)
        return travelled(interpolate_poses(tt, tp, output.times).reshape(-1, 4, 4)[:, :3, 3])
    p = output.poses[:, :3, 3]
    if len(p) < 2:
        return np.zeros(len(p))
    step = np.nan_to_num(np.linalg.norm(np.diff(p, axis=0), axis=1))     # no pose yet: no distance
    med = float(np.median(step))
    step = np.where(step > max(5 * med, 3.0), med, step)
    return np.concatenate([[0.0], np.cumsum(step)])


def ins_errors(output: LocaliseOutput, run: SurveyRun):
    """Lateral and heading errors of the raw INS/GPS against truth, across the map's reference path."""
    if run is None or run.truth_times is None or run.groundtruth_times is None:
        return None
    mp = output.metrics.get("map")
    if not mp or not (Path(mp) / "manifest.json").is_file():
        return None
    path = reference_path(MapStore.open(mp))
    ins = interpolate_poses(run.groundtruth_times, run.groundtruth_poses, output.times).reshape(-1, 4, 4)
    tru = interpolate_poses(run.truth_times, run.truth_poses, output.times).reshape(-1, 4, 4)
    lat, head, _ = lateral_heading_errors(ins, tru, path)
    return lat, head


def speed(times: np.ndarray, poses: np.ndarray, window_s: float = 0.5) -> np.ndarray:
    """Speed (m/s) from positions: central differences over ``window_s`` (smooths per-frame jitter)."""
    t = np.asarray(times, dtype=float)
    if len(t) < 2:
        return np.zeros(len(t))
    p = poses[:, :3, 3]
    lo = np.searchsorted(t, t - window_s / 2)
    hi = np.clip(np.searchsorted(t, t + window_s / 2, side="right") - 1, 0, len(t) - 1)
    lo = np.minimum(lo, hi - 1).clip(0)
    hi = np.maximum(hi, lo + 1).clip(max=len(t) - 1)
    dt = t[hi] - t[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dt > 0, np.linalg.norm(p[hi] - p[lo], axis=1) / dt, np.nan)


def dead_reckoning(outputs: list, d_grid, runs: dict | None = None) -> dict:
    """Fig. 25: per method, P(travelling more than d blind) over all its runs (distance-weighted).

    Returns ``{method: {"p": (G,) array, "distance_m": total, "runs": n}}``.
    """
    d_grid = np.asarray(d_grid, dtype=float)
    acc: dict = {}
    for o in outputs:
        s = frame_distances(o, (runs or {}).get(o.run))
        if len(s) < 2 or s[-1] <= s[0]:
            continue
        total = float(s[-1] - s[0])
        curve = dead_reckoning_curve(s, o.localised, d_grid, weighting="distance")
        a = acc.setdefault(o.method, {"over": np.zeros_like(d_grid), "distance_m": 0.0, "runs": 0})
        a["over"] += curve * total
        a["distance_m"] += total
        a["runs"] += 1
    return {m: {"p": a["over"] / a["distance_m"], "distance_m": a["distance_m"], "runs": a["runs"]}
            for m, a in sorted(acc.items())}


SUMMARY_COLUMNS = ("run", "conditions", "method", "lateral_median_m", "heading_median_deg", "lateral_map_median_m",
                   "localised_fraction", "failures", "failures_per_km", "blind_fraction_over_20m", "distance_m")


def summary_rows(outputs: list) -> list[dict]:
    """Per run and method: the table of the report (from ``metrics.json``)."""
    rows = []
    for o in sorted(outputs, key=lambda o: (o.run, o.method != "signatures", o.method)):
        m = o.metrics
        rows.append({"run": o.run, "conditions": list(m.get("conditions") or []), "method": o.method,
                     "lateral_median_m": (m.get("lateral_error_m") or {}).get("median"),
                     "heading_median_deg": (m.get("heading_error_deg") or {}).get("median"),
                     # relative to the map (simulated maps only): the localiser's own error, without the
                     # map's georeferencing error that every method inherits
                     "lateral_map_median_m": (m.get("lateral_error_map_m") or {}).get("median"),
                     "localised_fraction": m.get("localised_fraction"), "failures": m.get("failures"),
                     "failures_per_km": m.get("failures_per_km"),
                     "blind_fraction_over_20m": m.get("blind_fraction_over_20m"), "distance_m": m.get("distance_m"),
                     # frames skipped because their image failed strict decoding, and (real time)
                     # frames dropped to keep up: None where the output predates these counts
                     "frames_corrupt": m.get("frames_corrupt"), "frames_dropped": m.get("frames_dropped"),
                     # localising without INS/GPS (--oracle none)
                     "oracle": m.get("oracle", "ins"), "oracle_reads": m.get("oracle_reads"),
                     "first_fix_m": m.get("first_fix_m"), "relocalisations": m.get("relocalisations"),
                     "false_fixes": m.get("false_fixes"),
                     "relocalise_median_m": (m.get("relocalise_m") or {}).get("median"),
                     # uncertainty (localiser.uncertainty): the median 95 % lateral bound of the localised
                     # frames, and with truth the share of them within it; "none" where no truth was given
                     "lateral_bound_95_median_m": m.get("lateral_bound_95_m_median"),
                     "bound_coverage_95": m.get("bound_coverage_95"),
                     "truth_source": m.get("truth_source"),
                     # which measurement types the solver kept (hybrid: both), and the cost
                     "heading_map_median_deg": (m.get("heading_error_map_deg") or {}).get("median"),
                     "signature_inliers_mean": m.get("signature_inliers_mean"),
                     "point_inliers_mean": m.get("point_inliers_mean"),
                     "realtime_factor": m.get("realtime_factor"), "cpu_ms_per_frame": m.get("cpu_ms_per_frame"),
                     "folder": str(o.folder)})
    return rows


def find_runs(paths, names=None) -> dict:
    """Survey runs (folders with ``run.toml``) at or below ``paths``, by run name (only ``names`` if given)."""
    out = {}
    for p in paths:
        p = Path(p)
        cands = [p] if (p / "run.toml").is_file() else sorted(t.parent for t in p.rglob("run.toml")) if p.is_dir() else []
        for c in cands:
            try:
                r = read_run(c)
            except DataError:
                continue
            if names is None or r.name in names:
                out.setdefault(r.name, r)
    return out
