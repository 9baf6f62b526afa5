"""The paper's experiments (003 §4): feature matching (Figs 11-14) and localisation (Figs 15-25).

**Matching experiment** (§4.2) -- the front end alone, without geometry or motion checks.  For every
place and every test run, the run's frame nearest the place *by ground truth* (so the live and map
viewpoints agree and the transformation between them is close to identity, by construction) is
matched against the map.  A match counts when the feature sits in the same place in both images:
``||y_map - y_live|| < δ`` with δ = 15 px.  For scene signatures the map positions are the bank's
detections in the reference keyframe (``PlaceData.meta["detections_at_reference"]``) and the live
ones the bank's best detection in the live frame; for ORB and SIFT the map positions are the keyframe
features the point-feature localiser uses (those with a 3D point) and the live ones their mutual
nearest-neighbour + DAPC matches (:mod:`localiser.pointmethod`).  Outputs: matches per place per run
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

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapping.pointmap import point_features
from mapping.store import MapStore
from signatures.bank import Bank
from surveys.errors import DataError
from surveys.geometry import interpolate_poses, yaw_of
from surveys.run import SurveyRun, read_run
from surveys.tum import read_tum

from localiser.evaluation import dead_reckoning_curve, lateral_heading_errors, travelled
from localiser.pointmethod import default_config as point_default
from localiser.pointmethod import match_to_map

__all__ = ["default_config", "MatchingResult", "aligned_frame", "signature_matches", "point_matches",
           "matching_experiment", "write_matching", "plot_matching_counts", "plot_matching_heatmaps",
           "LocaliseOutput", "read_localise_output", "find_localise_outputs", "frame_distances",
           "plot_run", "dead_reckoning", "plot_dead_reckoning", "summary_rows", "localisation_figures",
           "METHOD_COLORS", "FRAMES_REQUIRED"]

default_config = {
    "delta_px": 15.0,               # paper §4.2: a match agrees when within 15 px in both images
    "methods": ["signatures", "orb", "sift"],
    "max_frame_distance_m": 5.0,    # a run whose nearest frame is further than this does not pass the place
    "max_heading_deg": 30.0,
    "heat_scale": 0.25,             # heat maps accumulated at this fraction of the image size
    "heat_places": 8,               # places shown in the heat-map figure (evenly spread) + the average
    "point": {},                    # overrides of localiser.pointmethod.default_config
}

#: Method colours, as in the paper where it has them (signatures red, point features green, INS blue).
METHOD_COLORS = {"signatures": "tab:red", "orb": "tab:green", "sift": "tab:olive", "ins": "tab:blue",
                 "truth": "k"}
FRAMES_REQUIRED = ("time", "place", "detections", "inliers", "localised", "lateral_error", "heading_error",
                   "distance_since_localisation")


def _merge(config: dict | None) -> dict:
    cfg = {k: (dict(v) if isinstance(v, dict) else v) for k, v in default_config.items()}
    for k, v in (config or {}).items():
        if k not in cfg:
            raise ValueError(f"unknown experiment option {k!r}; known: {sorted(cfg)}")
        cfg[k] = {**cfg[k], **v} if isinstance(cfg[k], dict) else v
    bad = [m for m in cfg["methods"] if m not in ("signatures", "orb", "sift")]
    if bad:
        raise ValueError(f"unknown method(s) {bad}; choose from signatures, orb, sift")
    return cfg


def _color(method: str, i: int = 0) -> str:
    return METHOD_COLORS.get(method, f"C{i % 10}")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _savefig(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    _plt().close(fig)
    tmp.replace(path)
    return path


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
    """ORB/SIFT matches (mutual NN + DAPC) of a live image to a place's keyframe features within δ.

    Returns
    -------
    n_matched : int; boxes : (m, 4) squares of the live keypoints' size around the matched ones;
    n_putative : int, matches before the δ test.
    """
    from signatures.pointfeatures import extract

    cfg = {**point_default, **(config or {})}
    mapf = point_features(points, kind)
    if mapf is None or not len(mapf):
        return 0, np.zeros((0, 4)), 0
    live = extract(_image_for(image, False), kind, n_features=int(cfg["n_features"]), config=cfg["features"])
    if not len(live):
        return 0, np.zeros((0, 4)), 0
    m = match_to_map(live, mapf, cfg["filter"], bool(cfg["mutual"]), float(cfg["ratio"]))
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


def plot_matching_counts(result: MatchingResult, path) -> Path:
    """Figs 11 / 14: matched features per place, one line per test run, one panel per method."""
    plt = _plt()
    n = len(result.methods)
    fig, axes = plt.subplots(n, 1, figsize=(10, 2.6 * n + 0.6), sharex=True, squeeze=False)
    x = np.asarray(result.places)
    for ax, m in zip(axes[:, 0], result.methods):
        for r, name in enumerate(result.runs):
            label = f"{name} ({', '.join(result.conditions[r])})" if result.conditions[r] else name
            ax.plot(x, result.counts[m][r], "-o", ms=2.5, lw=1, label=label, color=f"C{r % 10}")
        ax.set_ylabel(f"{m}\nmatches (< {result.delta_px:g} px)")
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    axes[0, 0].set_title("Feature matches per place against the map (ground-truth aligned frames; gaps: "
                         "the run does not pass the place)", fontsize=10)
    axes[-1, 0].set_xlabel("place")
    axes[0, 0].legend(fontsize=7, ncol=min(4, max(1, len(result.runs))), loc="upper right")
    fig.tight_layout()
    return _savefig(fig, path)


def plot_matching_heatmaps(result: MatchingResult, store: MapStore, method: str, path, n_places: int = 8) -> Path:
    """Figs 12 / 13: map keyframe and mean heat map of matches for sample places, and the average place."""
    import cv2

    plt = _plt()
    heat = result.heat[method]
    P = len(result.places)
    pick = np.unique(np.round(np.linspace(0, P - 1, min(n_places, P))).astype(int)) if P else np.zeros(0, int)
    cols = 4
    n_pairs = len(pick) + 1
    rows = int(np.ceil(n_pairs * 2 / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.1 * cols, 2.0 * rows + 0.5), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    hh, hw = heat.shape[1:] if P else (1, 1)
    vmax = float(np.percentile(heat, 99.5)) if heat.size and heat.max() > 0 else 1.0
    keyframes = []
    for k, j in enumerate(pick):
        kf = store.load_place(result.places[j]).keyframe_image()
        kf = np.zeros((hh, hw), np.uint8) if kf is None else cv2.resize(kf, (hw, hh), interpolation=cv2.INTER_AREA)
        keyframes.append(kf.astype(float))
        a, b = axes.ravel()[2 * k], axes.ravel()[2 * k + 1]
        a.imshow(kf, cmap="gray", vmin=0, vmax=255)
        a.set_title(f"place {result.places[j]}: map", fontsize=8)
        b.imshow(heat[j], cmap="inferno", vmin=0, vmax=vmax)
        b.set_title(f"place {result.places[j]}: {method} matches", fontsize=8)
    a, b = axes.ravel()[2 * len(pick)], axes.ravel()[2 * len(pick) + 1]
    if keyframes:
        a.imshow(np.mean(keyframes, axis=0), cmap="gray", vmin=0, vmax=255)
    a.set_title("average place", fontsize=8)
    b.imshow(heat.mean(axis=0) if P else np.zeros((hh, hw)), cmap="inferno")
    b.set_title(f"average heat map ({method})", fontsize=8)
    fig.suptitle(f"Where {method} matches fall (+1 per pixel inside a matched shape, mean over test runs)",
                 fontsize=10)
    fig.tight_layout()
    return _savefig(fig, path)


def write_matching(result: MatchingResult, store: MapStore, out, heat_places: int = 8) -> dict:
    """``matching.json`` and the figures in ``out``; returns ``{name: path}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "matching.json"}
    tmp = out / "matching.json.tmp"
    tmp.write_text(json.dumps(result.to_json(), indent=1, allow_nan=False) + "\n")
    tmp.replace(paths["json"])
    paths["counts"] = plot_matching_counts(result, out / "matching_counts.png")
    for m in result.methods:
        paths[f"heatmap_{m}"] = plot_matching_heatmaps(result, store, m, out / f"matching_heatmap_{m}.png",
                                                       heat_places)
    return paths


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


def _read_frames_csv(path: Path) -> dict:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise DataError(path, "empty file")
            header = [h.strip() for h in header]
            missing = [c for c in FRAMES_REQUIRED if c not in header]
            if missing:
                raise DataError(path, f"missing column(s) {missing}; expected {list(FRAMES_REQUIRED)}", line=1)
            cols = {h: [] for h in header}
            for ln, row in enumerate(reader, start=2):
                if not row:
                    continue
                if len(row) != len(header):
                    raise DataError(path, f"expected {len(header)} values, got {len(row)}", line=ln)
                for h, v in zip(header, row):
                    try:
                        cols[h].append(float(v))
                    except ValueError:
                        raise DataError(path, f"column {h!r}: {v!r} is not a number", line=ln) from None
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text: {exc}") from None
    return {h: np.asarray(v, dtype=float) for h, v in cols.items()}


def read_localise_output(folder) -> LocaliseOutput:
    """Read ``metrics.json``, ``frames.csv`` and ``trajectory.tum`` of a localise output folder."""
    folder = Path(folder)
    mpath = folder / "metrics.json"
    if not mpath.is_file():
        raise DataError(mpath, "missing: not a `scenesig localise` output folder")
    try:
        metrics = json.loads(mpath.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DataError(mpath, f"invalid JSON: {exc.msg}", line=exc.lineno) from None
    if not isinstance(metrics, dict) or "method" not in metrics or "run" not in metrics:
        raise DataError(mpath, "expected an object with at least 'method' and 'run'")
    fpath = folder / "frames.csv"
    if not fpath.is_file():
        raise DataError(fpath, "missing")
    frames = _read_frames_csv(fpath)
    tpath = folder / "trajectory.tum"
    if not tpath.is_file():
        raise DataError(tpath, "missing")
    times, poses = read_tum(tpath)
    n = len(frames["time"])
    if len(times) != n and metrics.get("oracle") != "none":
        raise DataError(tpath, f"{len(times)} poses but frames.csv has {n} frames")
    if len(times) != n:
        # without INS/GPS there is no pose before the first fix: the trajectory is a tail of the frames
        if len(times) > n or (len(times) and np.max(np.abs(times - frames["time"][n - len(times):])) > 1e-3):
            raise DataError(tpath, f"its {len(times)} poses are not the last frames of frames.csv's {n}")
        poses = np.concatenate([np.full((n - len(times), 4, 4), np.nan), poses.reshape(-1, 4, 4)])
        times = np.asarray(frames["time"], float)
    if n and np.max(np.abs(times - frames["time"])) > 1e-3:
        raise DataError(tpath, "times differ from frames.csv's")
    return LocaliseOutput(folder, metrics, frames, times, poses)


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


def _ins_errors(output: LocaliseOutput, run: SurveyRun):
    """Lateral and heading errors of the raw INS/GPS against truth, across the map's reference path."""
    from localiser.replay import reference_path

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


def _speed(times: np.ndarray, poses: np.ndarray, window_s: float = 0.5) -> np.ndarray:
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


def plot_run(outputs: list, path, run: SurveyRun | None = None) -> Path:
    """Figs 15-24 for one run: lateral / heading error, speed, matches per frame, localised frames.

    ``outputs``: the localise outputs of every method on this run; ``run``: the survey run (for the raw
    INS errors, the true speed and distances along the truth), optional.
    """
    plt = _plt()
    outputs = sorted(outputs, key=lambda o: (o.method != "signatures", o.method))
    name = outputs[0].run
    conds = outputs[0].metrics.get("conditions") or (list(run.conditions) if run is not None else [])
    fig, axes = plt.subplots(5, 1, figsize=(11, 12), sharex=True,
                             gridspec_kw={"height_ratios": [2, 2, 1.4, 1.6, 0.25 + 0.25 * len(outputs)]})
    ax_lat, ax_head, ax_v, ax_m, ax_loc = axes
    ins_done = False
    for k, o in enumerate(outputs):
        s = frame_distances(o, run)
        c = _color(o.method, k)
        met = o.metrics
        lat_med = (met.get("lateral_error_m") or {}).get("median")
        lab = o.method + (f" (median |lateral| {lat_med:.2f} m)" if lat_med is not None else "")
        ax_lat.plot(s, o.frames["lateral_error"], color=c, lw=1, label=lab)
        ax_head.plot(s, o.frames["heading_error"], color=c, lw=1, label=o.method)
        ax_v.plot(s, _speed(o.times, o.poses), color=c, lw=0.8, label=f"{o.method} estimate")
        det = o.frames["detections"] > 0
        ran = det | (o.frames["inliers"] > 0) | o.localised
        ax_m.plot(s[ran], o.frames["detections"][ran], color=c, lw=0.6, alpha=0.5)
        ax_m.plot(s[ran], o.frames["inliers"][ran], color=c, lw=1.2, label=f"{o.method}: inliers (faint: matches)")
        ax_loc.eventplot([s[o.localised]], lineoffsets=[k], linelengths=0.8, colors=[c], linewidths=0.6)
        if not ins_done and run is not None:
            ins = _ins_errors(o, run)
            if ins is not None:
                ax_lat.plot(s, ins[0], color=METHOD_COLORS["ins"], lw=0.9, ls="--", label="INS/GPS (raw)")
                ax_head.plot(s, ins[1], color=METHOD_COLORS["ins"], lw=0.9, ls="--", label="INS/GPS (raw)")
                ins_done = True
            if run.truth_times is not None and not any(l.get_label() == "truth" for l in ax_v.lines):
                tru = interpolate_poses(run.truth_times, run.truth_poses, o.times).reshape(-1, 4, 4)
                ax_v.plot(s, _speed(o.times, tru), color="k", lw=1, ls=":", label="truth")
    for ax, lab in ((ax_lat, "lateral error (m)"), (ax_head, "heading error (deg)"), (ax_v, "speed (m/s)"),
                    (ax_m, "matches per frame")):
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right", ncol=2)
    ax_lat.axhline(0, color="0.5", lw=0.5)
    ax_head.axhline(0, color="0.5", lw=0.5)
    ax_m.set_ylim(bottom=0)
    ax_loc.set_yticks(range(len(outputs)))
    ax_loc.set_yticklabels([o.method for o in outputs], fontsize=8)
    ax_loc.set_ylim(-0.6, len(outputs) - 0.4)
    ax_loc.set_xlabel("distance travelled (m)   [bottom: frames each method localised on]")
    title = f"{name}" + (f" [{', '.join(conds)}]" if conds else "")
    fails = ", ".join(f"{o.method} {o.metrics.get('failures', '?')}" for o in outputs)
    ax_lat.set_title(f"Localisation results: {title} -- failures: {fails}", fontsize=10)
    fig.tight_layout()
    return _savefig(fig, path)


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


def plot_dead_reckoning(curves: dict, d_grid, path) -> Path:
    """Fig. 25: probability of travelling more than d on dead reckoning, per method."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for k, (m, c) in enumerate(sorted(curves.items(), key=lambda kv: (kv[0] != "signatures", kv[0]))):
        ax.plot(d_grid, c["p"], color=_color(m, k), lw=1.8,
                label=f"{m} ({c['runs']} runs, {c['distance_m'] / 1000:.2f} km)")
    ax.axvline(20.0, color="0.5", lw=0.8, ls="--")
    ax.text(20.5, 0.96, "failure: 20 m", fontsize=7, color="0.4", va="top")
    ax.set_xlabel("distance d travelled blind (m)")
    ax.set_ylabel("P(travelling more than d blind)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlim(d_grid[0], d_grid[-1])
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Distance travelled on dead reckoning (all runs; lower left is better)", fontsize=10)
    fig.tight_layout()
    return _savefig(fig, path)


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
                     # localising without INS/GPS (--oracle none)
                     "oracle": m.get("oracle", "ins"), "oracle_reads": m.get("oracle_reads"),
                     "first_fix_m": m.get("first_fix_m"), "relocalisations": m.get("relocalisations"),
                     "false_fixes": m.get("false_fixes"),
                     "relocalise_median_m": (m.get("relocalise_m") or {}).get("median"),
                     "folder": str(o.folder)})
    return rows


def localisation_figures(outputs: list, out, runs: dict | None = None, d_max: float | None = None) -> dict:
    """Every localisation figure into ``out``: ``run_<name>.png`` per run and ``dead_reckoning.png``.

    Returns ``{"runs": {run: path}, "dead_reckoning": path, "curves": {method: {...}}, "d_grid": list}``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    by_run: dict = {}
    for o in outputs:
        by_run.setdefault(o.run, []).append(o)
    paths = {}
    for name, outs in sorted(by_run.items()):
        safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)
        paths[name] = plot_run(outs, out / f"run_{safe}.png", (runs or {}).get(name))
    if d_max is None:
        longest = 0.0
        for o in outputs:
            s = frame_distances(o, (runs or {}).get(o.run))
            if len(s) > 1:
                longest = max(longest, float(s[-1] - s[0]))
        d_max = float(np.clip(longest, 40.0, 100.0))
    d_grid = np.linspace(0.0, d_max, 201)
    curves = dead_reckoning(outputs, d_grid, runs)
    dr = plot_dead_reckoning(curves, d_grid, out / "dead_reckoning.png")
    return {"runs": paths, "dead_reckoning": dr, "curves": curves, "d_grid": d_grid.tolist()}


# ==================================================================================================
# command line
# ==================================================================================================
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
