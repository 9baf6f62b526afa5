"""Real night, fog and snow: the feature-matching experiment on fixed outdoor webcams.

The front end alone, as in McManus, Upcroft & Newman, "Learning place-dependent features for long-term
vision-based localisation" (Autonomous Robots 2015), §4.2: a correspondence is **correct** when a feature
sits at the same place in the training and the test image, ``||y_train - y_test|| < δ`` with δ = 15 px.
The cameras of the TILDE webcam set do not move, so the true transformation between any two images of a
scene is the identity, exactly what the paper built by aligning its test images with ground truth.

Protocol (per scene folder, images sorted by name = by time):

* ``--train multi``: the even positions train, the odd ones are tested.
* ``--train single``: one training image only -- the even-position image taken nearest 12:00 (time from
  the file name; the first even image where no name parses).  The paper's hardest case: one experience.

Methods:

* ``signatures``: one bank per scene, mined (:func:`scenesig.signatures.mining.mine_place`) from the training
  images with zero alignment offsets (fixed camera), with the training images of the *other* scenes as
  external negatives; in ``single`` mode the one image is joined by photometrically augmented copies
  (:func:`scenesig.signatures.augment.synthesise`) and mined with the single-experience settings
  (:mod:`scenesig.signatures.experience`, ``--config '{"signatures": {"single_experience": {...}}}'``).  Test images are never used in training.  Each classifier's best
  detection in the whole test image (no prior, all scales the bank searches) is a correspondence with its
  position in the training images (``nominal_xy``).
* ``signatures-xfeat``, ``signatures-hog+xfeat``: the same banks mined and detected on XFeat's dense
  descriptor map, or on HOG and XFeat stacked (mining's ``features``;
  :func:`scenesig.signatures.hog.describe_cells`).
* ``orb``, ``sift``: OpenCV features (2000 per image, rotation-invariant, OpenCV's default detector
  thresholds) matched with mutual nearest neighbours and Lowe's ratio test (0.8) against every training
  image; the training image with the most matches is kept (retrieval by match count, as hloc users rank
  database images), and its matches are the correspondences.
* ``xfeat``: XFeat learned features (Potje et al. 2024, :mod:`scenesig.signatures.xfeat`) as its authors set them
  up: the 4096 best keypoints, mutual nearest neighbours with cosine similarity above 0.82, against every
  training image as above.  Model: ``$SCENESIG_XFEAT_MODEL`` or ``../shared/models/xfeat/xfeat.onnx``
  (its sha256 is in the JSON).

Per test image the benchmark counts correct and total correspondences; an image is *localisable* with at
least 10 correct ones.  Periods come from the hour in the file name: night 21-05 h, twilight 05-07 and
19-21 h, day 07-19 h; an image whose hour does not parse counts only in the totals.

Two courbevoie images are left out by default (``--exclude``): the data set's README reports that the
camera moved by about 21 and 18 px when they were taken, more than δ, so the identity is not their truth.

Run ``scenesig bench webcam DIR --json OUT [--train multi|single] [--figure DIR]``; it prints the JSON.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

# the scene-signature variants and the cell descriptor each mines on, as in the heading benchmark
from scenesig.benchmarks.heading import SIGNATURE_METHODS

#: Benchmark settings.  Everything a method uses is here, so the JSON can state it.
default_config = {
    "tolerance_px": 15.0,          # McManus et al. 2015 §4.2: δ = 15 px
    "localisable_min_correct": 10,
    "max_pixels": 640 * 480,       # images are processed at most at this area (scale <= 1), results in full res
    "signatures": {
        "mining": {},              # overrides of signatures.mining.default_config
        "augment_copies": 11,      # single mode: augmented copies of the one training image
        "augment_shift_px": 0.0,   # fixed camera: no shifts
        "external_negatives": 4,  # other scenes' training images used as negatives
        "single_experience": {},   # overrides of signatures.experience.default_config
        "seed": 0,
    },
    "points": {"n_features": 2000, "ratio": 0.8, "mutual": True, "upright": False,
               "sift": {"nOctaveLayers": 3, "contrastThreshold": 0.04, "edgeThreshold": 10,
                        "sigma": 1.6},
               "orb": {"scaleFactor": 1.2, "nlevels": 8, "edgeThreshold": 31, "firstLevel": 0,
                       "WTA_K": 2, "patchSize": 31, "fastThreshold": 20}},
    # upstream's defaults (Potje et al. 2024); model None: $SCENESIG_XFEAT_MODEL or ../shared/models
    "xfeat": {"top_k": 4096, "min_cossim": 0.82, "model": None},
}

#: Images whose camera moved by more than δ (from the data set's README); left out by default.
DEFAULT_EXCLUDE = ("courbevoie/20131029_085701", "courbevoie/20140409_082712")

PERIODS = ("night", "twilight", "day")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
METHODS = tuple(SIGNATURE_METHODS) + ("orb", "sift", "xfeat")


# ---------------------------------------------------------------------------------- data set


def hour_of(name: str) -> float | None:
    """Time of day (hours) from a webcam file name, or None where it does not parse.

    ``YYYYMMDD_HHMMSS`` (AMOS) and ``YYYY_MMDD_HHMMd`` (EPFL panorama: hour, minute, one more digit).
    """
    stem = Path(name).stem
    m = re.fullmatch(r"\d{8}_(\d{2})(\d{2})(\d{2})", stem)
    if m is None:
        m = re.fullmatch(r"\d{4}_\d{4}_(\d{2})(\d{2})\d", stem)
    if m is None:
        return None
    h, mi = int(m.group(1)), int(m.group(2))
    if h > 23 or mi > 59:
        return None
    return h + mi / 60.0


def period_of(hour: float | None) -> str | None:
    """night 21-05 h, twilight 05-07 and 19-21 h, day 07-19 h."""
    if hour is None:
        return None
    if hour >= 21 or hour < 5:
        return "night"
    if hour < 7 or hour >= 19:
        return "twilight"
    return "day"


@dataclass
class Scene:
    """One webcam: its images (sorted by name) and the train / test split."""

    name: str
    files: list
    train: list = field(default_factory=list)
    test: list = field(default_factory=list)


def load_scenes(root, train: str = "multi", exclude=DEFAULT_EXCLUDE) -> list[Scene]:
    """Scenes of a webcam folder (one sub-folder per scene) split for ``train`` = multi | single."""
    from scenesig.surveys.errors import DataError

    root = Path(root)
    if not root.is_dir():
        raise DataError(root, "not a folder (expected one sub-folder of images per scene)")
    if train not in ("multi", "single"):
        raise ValueError(f"train must be 'multi' or 'single', got {train!r}")
    skip = set(exclude or ())
    scenes = []
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        files = sorted(f for f in d.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES
                       and f"{d.name}/{f.stem}" not in skip)
        if len(files) < 2:
            continue
        even, odd = files[0::2], files[1::2]
        if train == "multi":
            tr = even
        else:
            hours = [hour_of(f.name) for f in even]
            known = [i for i, h in enumerate(hours) if h is not None]
            i = min(known, key=lambda i: abs(hours[i] - 12.0)) if known else 0
            tr = [even[i]]
        scenes.append(Scene(d.name, files, tr, odd))
    if not scenes:
        raise DataError(root, f"no scene folder with at least two images ({', '.join(IMAGE_SUFFIXES)})")
    return scenes


def read_image(path) -> np.ndarray:
    from scenesig.surveys.errors import DataError

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(path, "cannot decode the image")
    return img


def processing_scale(shape, max_pixels: float) -> float:
    h, w = shape[:2]
    return min(1.0, float(np.sqrt(max_pixels / float(w * h))))


def _resize(img, s):
    return img if s == 1.0 else cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------------------------- methods


def correct_mask(train_xy, test_xy, tolerance_px: float = 15.0) -> np.ndarray:
    """A correspondence is correct when it sits within δ of its training position (§4.2)."""
    tr = np.asarray(train_xy, float).reshape(-1, 2)
    te = np.asarray(test_xy, float).reshape(-1, 2)
    if len(tr) != len(te):
        raise ValueError(f"{len(tr)} training and {len(te)} test positions")
    with np.errstate(invalid="ignore"):
        return np.linalg.norm(tr - te, axis=1) < float(tolerance_px)


def mine_scene_bank(train_images, negatives, cfg: dict, n_jobs: int = 1):
    """The scene's bank, mined from its training images (+ augmented copies when there is one).

    Returns ``(bank, stats, settings)``: the bank, the mining statistics and what
    :func:`scenesig.signatures.experience.settings_for` made of the number of training images.
    """
    from scenesig.signatures import experience, mining
    from scenesig.signatures.augment import synthesise

    scfg = cfg["signatures"]
    images = list(train_images)
    offsets = [(0.0, 0.0)] * len(images)
    # the training-data rule: settings by the number of real appearances (signatures.experience)
    exp = experience.settings_for(len(images), scfg["mining"], scfg["single_experience"])
    P = int({**mining.default_config, **exp["mining"]}["n_partitions"])
    if len(images) < P or exp["single"]:
        rng = np.random.default_rng(int(scfg["seed"]))
        images, offsets = synthesise(images, offsets, int(scfg["augment_copies"]), rng,
                                     float(scfg["augment_shift_px"]), exp["conditions"])
    bank, stats = mining.mine_place(images, np.asarray(offsets, float), config=exp["mining"],
                                    negatives=negatives, n_jobs=n_jobs, rng=int(scfg["seed"]))
    return bank, stats, exp


def signature_correspondences(bank, image, reference=None) -> tuple[np.ndarray, np.ndarray]:
    """(train_xy, test_xy) of every classifier's best detection in the whole image.

    With ``reference`` (a training image of the same size), the image first gets the reference's
    colours window by window (local exact histogram matching, 5 x 5 windows:
    :func:`scenesig.signatures.colour.local_exact_histogram_match`).
    """
    if len(bank) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    img = image
    if reference is not None:
        from scenesig.signatures.colour import local_exact_histogram_match
        if reference.shape != img.shape:
            reference = cv2.resize(reference, img.shape[1::-1], interpolation=cv2.INTER_AREA)
        img = local_exact_histogram_match(img, reference, (5, 5))
    if not bank.hog.get("color", False) and img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    d = bank.detect(img, top_n=1)
    test = np.column_stack([d.x[:, 0], d.y[:, 0]])
    train = np.array([c.nominal_xy for c in bank.classifiers], dtype=float).reshape(-1, 2)
    ok = np.all(np.isfinite(test), axis=1)
    return train[ok], test[ok]


def point_correspondences(train_feats, test_feats, cfg: dict) -> tuple[np.ndarray, np.ndarray]:
    """Matches of the test image to the training image with the most of them."""
    from scenesig.signatures.pointfeatures import match

    best = (np.zeros((0, 2)), np.zeros((0, 2)))
    for tf in train_feats:
        if not len(tf) or not len(test_feats):
            continue
        if test_feats.kind == "xfeat":
            m = match(test_feats, tf, filter="cossim", mutual=True, min_cossim=float(cfg["min_cossim"]))
        else:
            m = match(test_feats, tf, filter="ratio", ratio=float(cfg["ratio"]), mutual=bool(cfg["mutual"]))
        if len(m) > len(best[0]):
            best = (tf.xy[m.train].astype(float), test_feats.xy[m.query].astype(float))
    return best


def _extract(img, kind, cfg):
    from scenesig.signatures.pointfeatures import extract

    pc = cfg["points"]
    if kind == "xfeat":
        return extract(img, "xfeat", n_features=int(cfg["xfeat"]["top_k"]),
                       config={"xfeat": {"model": cfg["xfeat"]["model"]}})
    return extract(img, kind, n_features=int(pc["n_features"]), upright=bool(pc["upright"]),
                   config={kind: pc[kind], "dedupe": True})


# ---------------------------------------------------------------------------------- benchmark


@dataclass
class ImageResult:
    scene: str
    file: str
    period: str | None
    correct: int
    total: int
    train_xy: np.ndarray
    test_xy: np.ndarray


def run_benchmark(root, methods=("signatures", "orb", "sift"), train: str = "multi", config: dict | None = None,
                  exclude=DEFAULT_EXCLUDE, n_jobs: int = 1, progress: bool = True):
    """Run the protocol; returns (summary dict, {method: [ImageResult]}, scenes)."""
    cfg = _merged(default_config, config or {})
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    scenes = load_scenes(root, train, exclude)
    cell_model = None
    if any(m in SIGNATURE_METHODS and "xfeat" in _signature_features(cfg, m) for m in methods):
        from scenesig.benchmarks._models import xfeat_model
        cell_model = xfeat_model()      # banks on learned cells look the model up the library's way
    from scenesig.signatures.xfeat import using_model

    with using_model(cell_model):
        return _run(cfg, methods, scenes, root, train, exclude, n_jobs, progress)


def _run(cfg, methods, scenes, root, train, exclude, n_jobs, progress):
    """:func:`run_benchmark`'s protocol on loaded scenes with resolved settings."""
    from tqdm import tqdm

    xfeat_info = None
    if "xfeat" in methods:
        from scenesig.benchmarks._models import xfeat_model
        from scenesig.signatures.xfeat import get_xfeat

        cfg["xfeat"] = {**cfg["xfeat"], "model": cfg["xfeat"].get("model") or xfeat_model()}
        xfeat_info = get_xfeat({"model": cfg["xfeat"]["model"]}).describe()
    tol = float(cfg["tolerance_px"])
    results: dict[str, list[ImageResult]] = {m: [] for m in methods}
    seconds = {m: 0.0 for m in methods}
    mining_stats = {m: {} for m in methods if m in SIGNATURE_METHODS}
    detect_seconds = {m: 0.0 for m in methods}
    # Images at processing scale, loaded once.
    cache = {}

    def load(f):
        if f not in cache:
            full = read_image(f)
            s = processing_scale(full.shape, cfg["max_pixels"])
            cache[f] = (_resize(full, s), s)
        return cache[f]

    bar = tqdm(total=len(methods) * sum(len(s.test) for s in scenes), desc=f"webcam ({train})",
               unit="img", disable=not progress)
    for sc in scenes:
        train_imgs = [load(f)[0] for f in sc.train]
        test = [(f, *load(f)) for f in sc.test]
        for m in methods:
            t0 = time.perf_counter()
            if m in SIGNATURE_METHODS:
                size = train_imgs[0].shape[1], train_imgs[0].shape[0]
                negs = []
                for other in scenes:
                    if other is sc:
                        continue
                    for f in other.train[: int(cfg["signatures"]["external_negatives"])]:
                        negs.append(cv2.resize(load(f)[0], size, interpolation=cv2.INTER_AREA))
                bank, stats, exp = mine_scene_bank(train_imgs, negs, _with_features(cfg, SIGNATURE_METHODS[m]),
                                                   n_jobs=n_jobs)
                mining_stats[m][sc.name] = {"classifiers": len(bank), "train_images": len(train_imgs),
                                            "seconds": round(stats.seconds, 2),
                                            "single_experience": exp["single"],
                                            "features": bank.hog.get("features", "hog")}
                ref = train_imgs[0] if exp["colour_constancy"] else None
                corr = lambda img, ref=ref: signature_correspondences(bank, img, ref)  # noqa: E731
            else:
                feats = [_extract(im, m, cfg) for im in train_imgs]
                corr = lambda img, feats=feats, m=m: point_correspondences(  # noqa: E731
                    feats, _extract(img, m, cfg), {**cfg["points"], **cfg["xfeat"]})
            for f, img, s in test:
                td = time.perf_counter()
                tr, te = corr(img)
                detect_seconds[m] += time.perf_counter() - td
                tr, te = tr / s, te / s          # full-resolution pixels
                ok = correct_mask(tr, te, tol)
                results[m].append(ImageResult(sc.name, f.name, period_of(hour_of(f.name)),
                                              int(ok.sum()), int(len(ok)), tr, te))
                bar.update(1)
            seconds[m] += time.perf_counter() - t0
    bar.close()
    summary = {
        "dataset": str(root), "scenes": [s.name for s in scenes],
        "test_images": sum(len(s.test) for s in scenes), "tolerance_px": int(tol) if tol.is_integer() else tol,
        "train": train,
        "train_images": {s.name: [f.name for f in s.train] for s in scenes},
        "excluded": sorted(exclude or ()),
        "methods": {m: _method_summary(results[m], cfg, seconds[m]) for m in methods},
    }
    n_test = max(1, summary["test_images"])
    for m in methods:
        # per test image: features and matching (signatures: detection), training excluded
        summary["methods"][m]["seconds_per_test_image"] = detect_seconds[m] / n_test
        if m in SIGNATURE_METHODS:
            summary["methods"][m]["banks"] = mining_stats[m]
            summary["methods"][m]["config"] = _with_features(cfg, SIGNATURE_METHODS[m])["signatures"]
            summary["methods"][m]["mining_seconds_per_scene"] = float(np.mean(
                [b["seconds"] for b in mining_stats[m].values()])) if mining_stats[m] else 0.0
            features = sorted({b["features"] for b in mining_stats[m].values()})
            summary["methods"][m]["features"] = ",".join(features) if features else None
            if any("xfeat" in f for f in features):
                from scenesig.signatures.xfeat import get_xfeat
                summary["methods"][m]["model_sha256"] = get_xfeat().sha256
    for m in methods:
        if m == "xfeat":
            summary["methods"][m]["config"] = {**cfg["xfeat"], "xfeat": xfeat_info,
                                               "matcher": "mutual nearest neighbour, cosine similarity > min_cossim",
                                               "retrieval": "training image with most matches"}
        elif m not in SIGNATURE_METHODS:
            summary["methods"][m]["config"] = {**{k: v for k, v in cfg["points"].items()
                                                  if k not in ("orb", "sift")}, m: cfg["points"][m],
                                               "retrieval": "training image with most matches"}
    return summary, results, scenes


def _with_features(cfg: dict, features: str | None) -> dict:
    """``cfg`` with the signatures' mining ``features`` set (None: unchanged)."""
    if features is None:
        return cfg
    sig = dict(cfg["signatures"])
    sig["mining"] = {**dict(sig.get("mining") or {}), "features": features}
    return {**cfg, "signatures": sig}


def _signature_features(cfg: dict, method: str) -> str:
    """The cell descriptor a signature ``method`` mines on under ``cfg`` (mining's ``features``)."""
    return (_with_features(cfg, SIGNATURE_METHODS[method])["signatures"]["mining"] or {}).get("features", "hog")


def _merged(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        if k not in base:
            raise ValueError(f"unknown webcam setting {k!r}; known: {', '.join(sorted(base))}")
        # An empty default dict holds overrides another module validates (e.g. mining's).
        nested = isinstance(base[k], dict) and base[k] and isinstance(v, dict)
        out[k] = _merged(base[k], v) if nested else v
    return out


def _method_summary(rs: list[ImageResult], cfg, seconds: float) -> dict:
    k = int(cfg["localisable_min_correct"])

    def stats(sub):
        n = len(sub)
        return {"images": n,
                "correct_per_image_mean": float(np.mean([r.correct for r in sub])) if n else 0.0,
                "localisable_fraction": float(np.mean([r.correct >= k for r in sub])) if n else 0.0}

    tot = sum(r.total for r in rs)
    out = stats(rs)
    del out["images"]
    out["precision"] = float(sum(r.correct for r in rs) / tot) if tot else 0.0
    out["by_period"] = {p: stats([r for r in rs if r.period == p]) for p in PERIODS}
    out["seconds"] = round(float(seconds), 2)
    return out


# ---------------------------------------------------------------------------------- figures


def plot_strips(results, scenes, root, out_dir, config=None, per_scene: int = 6) -> list[Path]:
    """Per scene: a strip of test images with correct (green) and wrong (red) correspondences."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = {**default_config, **(config or {})}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    methods = list(results)
    paths = []
    for sc in scenes:
        tests = sc.test
        pick = [tests[i] for i in np.linspace(0, len(tests) - 1, min(per_scene, len(tests))).round().astype(int)]
        fig, axes = plt.subplots(len(methods), len(pick), figsize=(2.6 * len(pick), 2.2 * len(methods)),
                                 squeeze=False)
        for mi, m in enumerate(methods):
            byname = {r.file: r for r in results[m] if r.scene == sc.name}
            for j, f in enumerate(pick):
                ax = axes[mi, j]
                ax.imshow(cv2.cvtColor(read_image(f), cv2.COLOR_BGR2RGB))
                r = byname.get(f.name)
                if r is not None and len(r.test_xy):
                    ok = correct_mask(r.train_xy, r.test_xy, cfg["tolerance_px"])
                    ax.scatter(*r.test_xy[~ok].T, s=4, c="red", lw=0)
                    ax.scatter(*r.test_xy[ok].T, s=6, c="lime", lw=0)
                    ax.set_title(f"{f.stem}\n{r.correct}/{r.total}", fontsize=7)
                ax.set_xticks([])
                ax.set_yticks([])
                if j == 0:
                    ax.set_ylabel(m, fontsize=9)
        fig.suptitle(f"{sc.name}: correct (green) and wrong (red) correspondences, δ = "
                     f"{cfg['tolerance_px']:g} px", fontsize=9)
        fig.tight_layout()
        p = out_dir / f"webcam_{sc.name}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def plot_periods(summary: dict, out_path) -> Path:
    """Paper-style bar chart: correct matches per test image, per period and method."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(summary["methods"])
    fig, ax = plt.subplots(figsize=(6.5, 3.4))
    w = 0.8 / max(len(methods), 1)
    x = np.arange(len(PERIODS))
    for i, m in enumerate(methods):
        bp = summary["methods"][m]["by_period"]
        vals = [bp[p]["correct_per_image_mean"] for p in PERIODS]
        loc = [bp[p]["localisable_fraction"] for p in PERIODS]
        bars = ax.bar(x + (i - (len(methods) - 1) / 2) * w, vals, w, label=m)
        for b, l in zip(bars, loc):
            ax.text(b.get_x() + b.get_width() / 2, b.get_height(), f"{100 * l:.0f}%", ha="center",
                    va="bottom", fontsize=7)
    ax.set_xticks(x, [f"{p}\n({summary['methods'][methods[0]]['by_period'][p]['images']} images)"
                      for p in PERIODS] if methods else PERIODS)
    ax.set_ylabel(f"correct correspondences per image\n(< {summary['tolerance_px']} px)")
    ax.set_title(f"webcam, train {summary['train']} (labels: share of images with "
                 f"≥ {default_config['localisable_min_correct']} correct)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=120)
    plt.close(fig)
    return out_path


# ---------------------------------------------------------------------------------- CLI


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="scenesig bench webcam", description=__doc__.split("\n\n")[0])
    p.add_argument("dir", help="folder with one sub-folder of images per scene (e.g. ../shared/data/webcam)")
    p.add_argument("--methods", default="signatures,orb,sift",
                   help="comma-separated: signatures,signatures-xfeat,signatures-hog+xfeat,orb,sift,xfeat "
                        "(the xfeat ones need its model file)")
    p.add_argument("--json", required=True, help="output JSON file")
    p.add_argument("--train", choices=["multi", "single"], default="multi")
    p.add_argument("--figure", default=None, help="figure folder (default: none)")
    p.add_argument("--exclude", nargs="*", default=list(DEFAULT_EXCLUDE), metavar="SCENE/STEM",
                   help="images left out (default: the two courbevoie images whose camera moved)")
    p.add_argument("--jobs", type=int, default=1, help="mining workers (joblib)")
    p.add_argument("--config", default=None, metavar="JSON",
                   help="JSON file of overrides of the benchmark settings (default_config)")
    return p


def main(argv=None) -> int:
    """``scenesig bench webcam ARGS``; a :class:`~surveys.errors.DataError` is left to the CLI's handler."""
    from scenesig.benchmarks._stages import read_config
    from scenesig.surveys.io import atomic_write_text

    args = build_parser().parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    config = read_config(args.config)
    summary, results, scenes = run_benchmark(args.dir, methods, args.train, config=config,
                                             exclude=args.exclude, n_jobs=args.jobs)
    if args.figure:
        fig = Path(args.figure)
        plot_strips(results, scenes, args.dir, fig / args.train)
        plot_periods(summary, fig / f"webcam_{args.train}_periods.png")
    text = json.dumps(summary, indent=2)
    atomic_write_text(Path(args.json), text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "webcam", *sys.argv[1:]]))
