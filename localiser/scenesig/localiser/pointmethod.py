"""Point-feature weak localisers (ORB, SIFT, XFeat): the baselines of McManus et al. 2015, §4, on the same pipeline.

``scenesig localise MAP RUN --method orb|sift|xfeat|orb-all|sift-all|xfeat-all`` runs this instead of the scene
signatures; replay, the pose graph, SE(2) snapping, the failure rule (20 m blind -> oracle reset),
the outputs and the metrics are the shared code of :mod:`scenesig.localiser.methods` / :mod:`scenesig.localiser.pipeline` / :mod:`scenesig.localiser.replay`.

Set up as hloc users run point features.  Per frame, for the place the localiser chose:

* **features** -- the live image's 2000 strongest upright ORB or SIFT features, or XFeat's top 4096
  (Potje et al. 2024, set up as upstream: :mod:`scenesig.signatures.xfeat`)
  (:func:`scenesig.signatures.pointfeatures.extract`); inside a :func:`scenesig.signatures.pointfeatures.feature_cache`
  block, localisers of one kind replaying the same run (``sift`` and ``sift-all``) extract each frame
  once.
* **point map** -- ``reference`` (methods ``orb``, ``sift``): the reference run's keyframe with its
  triangulated 3D points, the paper's baseline; ``all`` (``orb-all``, ``sift-all``): a keyframe from
  every training run at the place, all in the place frame (:func:`scenesig.mapping.pointmap.build_point_features_all`);
  the live image is matched to each and the keyframe with the most matches is used (retrieval by
  match count).
* **prior-guided matching** (default; ``prior_gating``) -- a map point may only match live
  keypoints inside the window around its projection predicted from the odometry prior, ``±3σ`` of
  ``J P_x Jᵀ + G P_l Gᵀ + σ_px² I`` (at least ``min_radius_px``), exactly the signature detector's
  search windows (:func:`scenesig.localiser.detector.search_windows`); where the localiser is lost, the whole
  image.  Nearest neighbours and ratios are taken among the allowed pairs.
* **matcher** (``match``) -- ``ratio`` (default): mutual nearest neighbours and Lowe's ratio test
  (0.8); ``dapc``: mutual nearest neighbours and the DAPC adaptive-distance test of Zhang et al.
  (CMC 2023, eqs. 6-7); ``gms``: nearest neighbours filtered by grid-based motion statistics
  (Bian et al., CVPR 2017); ``mnn`` (XFeat's default, its authors' matcher): mutual nearest neighbours
  with cosine similarity above 0.82.
* **solve** -- robust absolute pose (:mod:`scenesig.localiser.absolute_pose`: LO-RANSAC, iterations driven
  by a 0.9999 confidence, non-linear refinement), then the same robust Levenberg-Marquardt with the
  motion prior, gating and checks as the signatures' eq. 10 solver
  (:func:`scenesig.localiser.solver.solve_pnp_prior`); accepted with at least 12 inliers (an absolute count,
  not a share of the putative matches).

Keypoint noise grows with the keypoint's scale (``pixel_sigma`` at the finest octave); the 3D points'
map uncertainty (``{kind}_sigma``, across / along the keyframe ray) enters the solver as landmark
covariance, so a far point whose depth is poorly known does not pull the translation.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from scenesig.mapping.pointmap import POINT_MAPS, keypoint_sigma, point_features, point_keyframes, point_map_covariances
from scenesig.mapping.store import MapStore
from scenesig.signatures.pointfeatures import PointFeatures, active_feature_cache, extract, match
from scenesig.surveys.cache import LRUCache
from scenesig.surveys.geometry import Camera
from scenesig.surveys.settings import merge_settings

from .detector import search_windows
from .methods import Measurement, MotionPrior, WeakLocaliser, register_method
from .solver import default_config as solver_default, default_pnp_config, solve_pnp_prior

__all__ = ["default_config", "MATCHERS", "PointObservation", "LiveFrame", "PointLocaliser", "keypoint_sigma",
           "match_to_map", "method_name", "window_mask"]

MATCHERS = ("ratio", "dapc", "gms", "mnn")
#: point-feature kinds with a localiser
POINT_KINDS = ("orb", "sift", "xfeat")

default_config = {
    "n_features": 2000,          # live features per frame (strongest by detector response)
    "xfeat_top_k": 4096,         # XFeat's live keypoints per frame (upstream's top-k)
    "min_cossim": 0.82,          # match="mnn": cosine similarity threshold (upstream XFeat's default)
    "features": {},              # overrides of signatures.pointfeatures.default_config (upright, orb, sift)
    "match": "ratio",            # "ratio": mutual NN + Lowe; "dapc" (mutual NN + DAPC); "gms"
    "ratio": 0.8,                # Lowe's ratio (match="ratio")
    "gms": {},                   # overrides of signatures.pointfeatures.gms_default_config
    "point_map": "reference",    # "reference" (one keyframe per place) or "all" (one per training run)
    "prior_gating": True,        # matches only inside the windows the odometry prior predicts
    "window_sigmas": 3.0,        # gate half-size in σ of the predicted projection ...
    "min_radius_px": 20.0,       # ... but never smaller (map points' own error, keypoint scale)
    "max_window_fraction": 0.5,  # a window wider than this share of the image: not gated
    "min_matches": 12,           # fewer matches: no solve ("too_few_matches")
    "pixel_sigma": 1.0,          # keypoint std. dev. (px) at the finest octave
    # Live features extracted from the image resized by this factor (keypoints scaled back; their σ
    # grows by 1/live_scale): 0.5 costs SIFT about a quarter of the time, at coarser keypoints.
    "live_scale": 1.0,
    "use_point_covariance": True,
    "cache": 4,                  # decoded places kept
    # A pose from a handful of point matches is where wrong localisations come from: after a reset the
    # prior is loose (metres), and 5-10 wrong matches that happen to agree pass every gate.  The gate is
    # an absolute inlier count (as hloc / COLMAP register an image), not a share of the putative
    # matches, which across a change of appearance are mostly wrong.
    "solver": {"min_inliers": 12, "min_inlier_fraction": 0.0},   # overrides of localiser.solver.default_config
    "pnp": {},                   # overrides of localiser.solver.default_pnp_config (robust absolute pose)
}


def _merge(config: dict | None) -> dict:
    cfg = merge_settings(default_config, config, "point-feature method", open=("features", "solver", "pnp", "gms"))
    if cfg["match"] not in MATCHERS:
        raise ValueError(f"match must be one of {MATCHERS}, got {cfg['match']!r}")
    if not 0.1 <= float(cfg["live_scale"]) <= 1.0:
        raise ValueError(f"live_scale must be in [0.1, 1], got {cfg['live_scale']!r}")
    if cfg["point_map"] not in POINT_MAPS:
        raise ValueError(f"point_map must be one of {POINT_MAPS}, got {cfg['point_map']!r}")
    merge_settings(solver_default, cfg["solver"], "solver")          # checked here, passed on as overrides
    merge_settings(default_pnp_config, cfg["pnp"], "PnP")
    return cfg


def resolve_config(config: dict | None = None) -> dict:
    """Every setting of the point-feature method, its sub-stages' included (features, GMS, solver,
    PnP): what ``config`` (overrides of :data:`default_config`) amounts to."""
    from scenesig.signatures.pointfeatures import default_config as features_default, gms_default_config

    cfg = _merge(config)
    return {**cfg, "features": merge_settings(features_default, cfg["features"], "point-feature", open=("xfeat",)),
            "gms": merge_settings(gms_default_config, cfg["gms"], "GMS"),
            "solver": merge_settings(solver_default, cfg["solver"], "solver"),
            "pnp": merge_settings(default_pnp_config, cfg["pnp"], "PnP")}


def match_to_map(live: PointFeatures, mapf: PointFeatures, matcher: str = "ratio", ratio: float = 0.8,
                 mask: np.ndarray | None = None, image_size=None, gms: dict | None = None,
                 min_cossim: float = 0.82):
    """Matches map -> live with one of :data:`MATCHERS` (module docstring).

    ``mask`` (n_map, n_live): pairs allowed (prior gating); ``image_size`` (width, height) of both
    images, for GMS's grid.

    Returns
    -------
    :class:`scenesig.signatures.pointfeatures.Matches` with ``query`` indexing the map features and ``train``
    the live ones.
    """
    if matcher == "ratio":
        return match(mapf, live, filter="ratio", ratio=ratio, mutual=True, mask=mask)
    if matcher == "dapc":
        # the M2Det scene-matching paper's order (§3.4): bidirectional (mutual) matching first, then the
        # dynamic distance test
        return match(mapf, live, filter="dapc", mutual=True, dapc_over="mutual", mask=mask)
    if matcher == "mnn":
        return match(mapf, live, filter="cossim", mutual=True, mask=mask, min_cossim=min_cossim)
    if matcher == "gms":
        size = {} if image_size is None else {"image_size_a": tuple(image_size), "image_size_b": tuple(image_size)}
        return match(mapf, live, filter="gms", mutual=False, mask=mask, gms={**(gms or {}), **size})
    raise ValueError(f"match must be one of {MATCHERS}, got {matcher!r}")


@dataclass
class PointObservation:
    """Matched 2D-3D correspondences of one live image against one place's keyframe.

    Attributes
    ----------
    place : place index.
    uv : (m,2) live keypoints; ``R`` (m,2,2) their covariances.
    xyz : (m,3) map points (place frame); ``cov`` (m,3,3) their covariances (or None).
    map_index : (m,) index of the map point.
    n_live, n_map : features in the live image and the place's map.
    ms : detection + matching time (ms).
    extra : ``keyframe`` (the keyframe matched, for the ``all`` point map), ``gated`` (prior gating
        applied).
    """

    place: int
    uv: np.ndarray
    R: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray | None
    map_index: np.ndarray
    n_live: int = 0
    n_map: int = 0
    ms: float = 0.0
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.uv)


@dataclass
class LiveFrame:
    """A live image's features (:meth:`PointLocaliser.prepare`): what detection needs of the image.

    Attributes
    ----------
    shape : (height, width) of the image.
    features : its :class:`scenesig.signatures.pointfeatures.PointFeatures`.
    ms : extraction time (ms), counted in the detection time.
    """

    shape: tuple
    features: PointFeatures
    ms: float = 0.0


@dataclass
class _MapPlace:
    features: PointFeatures | None
    xyz: np.ndarray
    cov: np.ndarray | None
    keyframe: np.ndarray          # (N,) keyframe of each point (all 0 for the reference map)
    n_keyframes: int = 1


def window_mask(windows: np.ndarray, searchable: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n_windows, n_points) bool: point j lies in window i (``x_min, y_min, x_max, y_max``).

    A window of NaN (too wide) admits every point; an unsearchable one none.  Points are sorted by
    x once, so each window only tests the points in its column range.
    """
    n, m = len(windows), len(xy)
    mask = np.zeros((n, m), bool)
    wide = np.isnan(windows).any(axis=1)
    mask[wide & searchable] = True
    rows = np.flatnonzero(~wide & searchable)
    if not len(rows) or not m:
        return mask
    order = np.argsort(xy[:, 0], kind="stable")
    xs = xy[order, 0].astype(float)
    lo = np.searchsorted(xs, windows[rows, 0], side="left")
    hi = np.searchsorted(xs, windows[rows, 2], side="right")
    count = np.maximum(hi - lo, 0)
    if not count.sum():
        return mask
    r = np.repeat(rows, count)
    start = np.repeat(lo - np.concatenate([[0], np.cumsum(count)[:-1]]), count)
    cols = order[np.arange(int(count.sum())) + start]
    y = xy[cols, 1].astype(float)
    ok = (y >= windows[r, 1]) & (y <= windows[r, 3])
    mask[r[ok], cols[ok]] = True
    return mask


def method_name(kind: str, point_map: str = "reference") -> str:
    """``orb``, ``sift``, ``xfeat`` (reference point map) or ``orb-all``, ``sift-all``, ``xfeat-all``."""
    return kind if point_map == "reference" else f"{kind}-{point_map}"


class PointLocaliser(WeakLocaliser):
    """ORB, SIFT or XFeat against a place's keyframe 3D points (a :class:`scenesig.localiser.methods.WeakLocaliser`).

    Parameters
    ----------
    store : the map (built with point features: ``PlaceData.points``).
    camera, T_vehicle_camera : the live camera and extrinsic.
    config : overrides of :data:`default_config`.
    kind : ``"orb"``, ``"sift"`` or ``"xfeat"`` (the model file: ``features: {xfeat: {model: PATH}}``, else
        ``$SCENESIG_XFEAT_MODEL``, else :data:`scenesig.signatures.xfeat.DEFAULT_MODEL_PATH`).
    """

    color = False

    def __init__(self, store: MapStore, camera: Camera, T_vehicle_camera: np.ndarray, config: dict | None = None,
                 kind: str = "orb"):
        if kind not in POINT_KINDS:
            raise ValueError(f"kind must be one of {POINT_KINDS}, got {kind!r}")
        self.kind = kind
        self.config = _merge(config)
        self.xfeat = None
        if kind == "xfeat":
            from scenesig.signatures.xfeat import get_xfeat

            # load the model now: a missing file is an error before the replay starts, naming where it looked
            self.xfeat = get_xfeat(self.config["features"].get("xfeat"))
        self.name = method_name(kind, self.config["point_map"])
        self.store = store
        self.camera = camera
        self.T_vehicle_camera = np.asarray(T_vehicle_camera, dtype=float)
        self._cache = LRUCache(max(1, int(self.config["cache"])))   # decoded point maps (surveys.cache)
        pm = self.config["point_map"]
        if len(store) and not any(self._place(i).features is not None and len(self._place(i).features)
                                  for i in list(store.places)[: min(3, len(store))]):
            raise ValueError(f"map {store.root} has no {kind.upper()} point features for the {pm!r} point map "
                             f"(places hold no 'points/{kind}{'' if pm == 'reference' else '_all'}_*' arrays): "
                             f"rebuild it with a scenesig whose build-map writes them")

    def method_config(self) -> dict:
        cfg = self.config
        xf = {}
        if self.xfeat is not None:
            xf = {"features": f"XFeat (Potje et al. 2024, ONNX, onnxruntime), the {cfg['xfeat_top_k']} best per "
                              f"live image", "n_features": cfg["xfeat_top_k"], "xfeat": self.xfeat.describe(),
                  "model_sha256": self.xfeat.sha256}
        return {"method": self.name, "family": "point features",
                "features": f"{self.kind.upper()} (OpenCV), upright, the {cfg['n_features']} strongest per live image",
                "n_features": cfg["n_features"], "feature_options": cfg["features"], "live_scale": cfg["live_scale"],
                "matcher": {"ratio": "mutual nearest neighbour + Lowe ratio", "dapc": "mutual nearest neighbour + DAPC",
                            "gms": "nearest neighbour + grid-based motion statistics",
                            "mnn": f"mutual nearest neighbour, cosine similarity > {cfg['min_cossim']}"}[cfg["match"]],
                "min_cossim": cfg["min_cossim"] if cfg["match"] == "mnn" else None,
                **xf,
                "match": cfg["match"], "ratio": cfg["ratio"] if cfg["match"] == "ratio" else None,
                "gms": cfg["gms"] if cfg["match"] == "gms" else None,
                "point_map": cfg["point_map"],
                "point_map_description": ("the reference run's keyframe per place (McManus et al. 2015's baseline)"
                                          if cfg["point_map"] == "reference" else
                                          "a keyframe from every training run per place; the one with the most "
                                          "matches is used"),
                "prior_gating": cfg["prior_gating"],
                "gate": {k: cfg[k] for k in ("window_sigmas", "min_radius_px", "max_window_fraction")},
                "min_matches": cfg["min_matches"],
                "estimator": merge_settings(default_pnp_config, cfg["pnp"], "PnP"),
                "min_inliers": merge_settings(solver_default, cfg["solver"], "solver")["min_inliers"],
                "solver": merge_settings(solver_default, cfg["solver"], "solver")}

    # ------------------------------------------------------------------------------ map side
    def _place(self, index: int) -> _MapPlace:
        index = int(index)
        cached = self._cache.get(index)
        if cached is not None:
            return cached
        data = self.store.load_place(index)
        pm = self.config["point_map"]
        feats = point_features(data.points, self.kind, pm)
        if feats is None:
            mp = _MapPlace(None, np.zeros((0, 3)), None, np.zeros(0, int), 0)
        else:
            pre = self.kind if pm == "reference" else f"{self.kind}_all"
            xyz = np.asarray(data.points[f"{pre}_xyz"], dtype=float).reshape(-1, 3)
            if len(feats) != len(xyz):
                raise ValueError(f"place {index}: {len(feats)} {self.kind} keypoints but {len(xyz)} 3D points")
            cov = None
            if self.config["use_point_covariance"] and len(xyz):
                cov = point_map_covariances(data.points, self.kind, pm, self.T_vehicle_camera)
            keyframe, T_pk = point_keyframes(data.points, self.kind, pm)
            mp = _MapPlace(feats, xyz, cov, keyframe, len(T_pk))
        self._cache.put(index, mp)
        return mp

    def prefetch(self, place):
        # Decoding a place's points takes well under a millisecond; loading it here keeps the
        # detector's timing honest without a thread.
        if place is not None and int(place) in self.store.places:
            self._place(place)

    # ------------------------------------------------------------------------------ detector
    def live_features(self, image: np.ndarray) -> PointFeatures:
        """The live image's features (same extraction as the map keyframe's); inside a
        :func:`scenesig.signatures.pointfeatures.feature_cache` block, taken from its cache when another
        localiser of the block has extracted them (``orb`` and ``orb-all`` replaying one run)."""
        cache = active_feature_cache()
        get = extract if cache is None else cache.extract
        n = int(self.config["xfeat_top_k"] if self.kind == "xfeat" else self.config["n_features"])
        scale = float(self.config["live_scale"])
        if scale == 1.0:
            return get(image, self.kind, n_features=n, config=self.config["features"])
        import cv2

        h, w = image.shape[:2]
        small = cv2.resize(image, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
        f = get(small, self.kind, n_features=n, config=self.config["features"])
        # back to the full image's pixels (pixel centres: x_full = (x_small + 0.5) / scale - 0.5)
        return PointFeatures(f.kind, ((f.xy + 0.5) / scale - 0.5).astype(np.float32), f.response,
                             (f.size / scale).astype(np.float32), f.angle, f.octave, f.descriptors, (h, w))

    def prepare(self, image: np.ndarray) -> LiveFrame:
        """Extract the live image's features (needs neither place nor prior: the replay runs it
        ahead, on another thread, while the previous frame is solved)."""
        if isinstance(image, LiveFrame):
            return image
        t0 = time.perf_counter()
        h, w = image.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(f"image is {w}x{h} but the camera is {self.camera.width}x{self.camera.height}")
        return LiveFrame((h, w), self.live_features(image), (time.perf_counter() - t0) * 1e3)

    def gate(self, mp: _MapPlace, live: PointFeatures, prior: MotionPrior | None) -> np.ndarray | None:
        """(n_map, n_live) pairs allowed by the prior (None: no gating -- off, no prior, or lost)."""
        cfg = self.config
        if not cfg["prior_gating"] or prior is None or prior.lost or not len(mp.xyz):
            return None
        Q = np.eye(2) * float(cfg["pixel_sigma"]) ** 2
        win, ok, _ = search_windows(mp.xyz, mp.cov, prior.T_place_vehicle, prior.covariance, self.camera,
                                    self.T_vehicle_camera, Q,
                                    {"window_sigmas": cfg["window_sigmas"],
                                     "min_window_radius_px": cfg["min_radius_px"],
                                     "max_window_fraction": cfg["max_window_fraction"]})
        return window_mask(win, ok, live.xy)

    def detect(self, image, place: int, prior: MotionPrior | None = None) -> PointObservation:
        """Match the live features (an image, or its :meth:`prepare` result) to the place's map points.

        ``ms`` of the observation includes the extraction, wherever it ran.
        """
        t0 = time.perf_counter()
        frame = self.prepare(image)
        ms_extract = frame.ms if frame is image else 0.0   # extracted here: already in the elapsed time
        mp = self._place(place)
        live = frame.features
        cfg = self.config
        if mp.features is None or not len(mp.features) or not len(live):
            return PointObservation(place, np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 3)), None,
                                    np.zeros(0, int), len(live), 0 if mp.features is None else len(mp.features),
                                    ms_extract + (time.perf_counter() - t0) * 1e3)
        mask = self.gate(mp, live, prior)
        size = (self.camera.width, self.camera.height)
        best, best_k = None, 0
        # hloc-style retrieval by match count: each keyframe of the place is matched, the best is used
        for k in range(mp.n_keyframes):
            rows = np.flatnonzero(mp.keyframe == k) if mp.n_keyframes > 1 else np.arange(len(mp.features))
            if not len(rows):
                continue
            sub = mp.features.subset(rows) if mp.n_keyframes > 1 else mp.features
            m = match_to_map(live, sub, cfg["match"], float(cfg["ratio"]),
                             None if mask is None else mask[rows], size, cfg["gms"], float(cfg["min_cossim"]))
            if best is None or len(m) > len(best[0]):
                best, best_k = (m, rows), k
        m, rows = best
        query = rows[m.query]
        uv = live.xy[m.train].astype(float)
        sig = keypoint_sigma(live.subset(m.train), float(cfg["pixel_sigma"]), cfg["features"]) / float(cfg["live_scale"])
        R = (sig ** 2)[:, None, None] * np.eye(2)[None]
        cov = mp.cov[query] if mp.cov is not None else None
        return PointObservation(place, uv, R, mp.xyz[query], cov, query, len(live), len(mp.features),
                                ms_extract + (time.perf_counter() - t0) * 1e3,
                                {"keyframe": int(best_k), "gated": mask is not None})

    # -------------------------------------------------------------------------------- solver
    def solve(self, obs: PointObservation, place: int, prior: MotionPrior | None) -> Measurement:
        n = len(obs)
        extra = {"live_features": obs.n_live, "map_points": obs.n_map, **obs.extra}
        if n < max(int(self.config["min_matches"]), 4):
            return Measurement(None, n, 0, "too_few_matches", obs.ms, 0.0, False, {**extra, "point_inliers": 0})
        T_prior = prior.T_place_vehicle if prior is not None else None
        P_prior = prior.covariance if prior is not None else None
        res = solve_pnp_prior(obs.uv, obs.xyz, self.camera, self.T_vehicle_camera, T_prior, P_prior, R=obs.R,
                              points_cov=obs.cov, config=self.config["solver"] or None,
                              pnp_config=self.config["pnp"] or None)
        extra["ransac_inliers"] = res.extra.get("ransac_inliers", 0)
        extra["point_inliers"] = res.n_inliers
        c = res.constraint(self.store.places[place].T_world_place)
        return Measurement(c, n, res.n_inliers, res.reason, obs.ms, res.ms, True, extra)

    def close(self):
        self._cache.clear()


def _base(kind: str, point_map: str) -> dict:
    # XFeat is matched as its authors match it (mutual NN on cosine similarity) unless told otherwise
    return {"point_map": point_map, **({"match": "mnn"} if kind == "xfeat" else {})}


def _factory(kind, point_map):
    base = _base(kind, point_map)

    def make(store, camera, T_vehicle_camera, config=None):
        return PointLocaliser(store, camera, T_vehicle_camera, {**base, **(config or {})}, kind=kind)
    make.__name__ = f"make_{method_name(kind, point_map).replace('-', '_')}"
    return make


def _settings(kind, point_map):
    base = _base(kind, point_map)

    def settings(config=None):
        return resolve_config({**base, **(config or {})})
    return settings


for _kind in POINT_KINDS:
    for _pm in POINT_MAPS:
        register_method(method_name(_kind, _pm), _factory(_kind, _pm), _settings(_kind, _pm))
