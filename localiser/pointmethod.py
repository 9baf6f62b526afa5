"""Point-feature weak localisers (ORB, SIFT): the baselines of McManus et al. 2015, §4, on the same pipeline.

``scenesig localise MAP RUN --method orb|sift`` runs this instead of the scene signatures; replay, the
pose graph, SE(2) snapping, the failure rule (20 m blind -> oracle reset), the outputs and the metrics are
the shared code of :mod:`localiser.pipeline` / :mod:`localiser.replay`.

Per frame, for the place the localiser chose:

* **detect** -- the live image's features (upright ORB or SIFT, the strongest ``n_features``;
  :func:`signatures.pointfeatures.extract`), matched to the place's keyframe features
  (:mod:`mapping.pointmap`: those with a triangulated 3D point) by *mutual nearest neighbour* and then
  the *DAPC* adaptive test of "Multi-Modal Scene Matching Location Algorithm Based on M2Det" (§3.4,
  eqs. 6-7): keep a mutual match when its best distance is below
  its second-best distance minus the mean gap (second - best) over the mutual matches.  No ratio to tune:
  the threshold adapts to how separable this image pair's descriptors are -- which is exactly what
  changes between a sunny map and a night or fog live image.
* **solve** -- PnP with RANSAC (EPnP minimal sets) on the 2D-3D correspondences, then the same robust
  Levenberg-Marquardt with the motion prior, gating and checks as the signatures' eq. 10 solver
  (:func:`localiser.solver.solve_pnp_prior`); a localisation constraint with covariance, or none.

Keypoint noise grows with the keypoint's scale (``pixel_sigma`` at the finest octave); the 3D points'
map uncertainty (``{kind}_sigma``, across / along the keyframe ray) enters the solver as landmark
covariance, so a far point whose depth is poorly known does not pull the translation.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from mapping.pointmap import keypoint_sigma, point_covariances, point_features
from mapping.store import MapStore
from signatures.pointfeatures import PointFeatures, extract, match
from surveys.settings import merge_settings
from surveys.geometry import Camera

from .pipeline import Measurement, MotionPrior, WeakLocaliser, register_method
from .solver import default_config as solver_default
from .solver import default_pnp_config, solve_pnp_prior

__all__ = ["default_config", "PointObservation", "LiveFrame", "PointLocaliser", "keypoint_sigma", "match_to_map"]

default_config = {
    "n_features": 1000,          # live features per frame (strongest by detector response)
    "features": {},              # overrides of signatures.pointfeatures.default_config (upright, orb, sift)
    "mutual": True,              # mutual nearest neighbours ...
    "filter": "dapc",            # ... then DAPC (M2Det scene-matching paper, §3.4); "ratio" or "none" for comparisons
    "ratio": 0.8,                # only for filter="ratio"
    "min_matches": 6,            # fewer matches: no solve ("too_few_matches")
    "pixel_sigma": 1.0,          # keypoint std. dev. (px) at the finest octave
    "use_point_covariance": True,
    "cache": 4,                  # decoded places kept
    # A pose from a handful of point matches is where wrong localisations come from: after a reset the
    # prior is loose (metres), and 5-10 wrong matches that happen to agree pass every gate.  PnP-based
    # localisers ask for many more inliers than the signatures' 4 (ORB-SLAM's relocalisation: 50).
    "solver": {"min_inliers": 12},   # overrides of localiser.solver.default_config
    "pnp": {},                   # overrides of localiser.solver.default_pnp_config
}


def _merge(config: dict | None) -> dict:
    cfg = merge_settings(default_config, config, "point-feature method", open=("features", "solver", "pnp"))
    if cfg["filter"] not in ("dapc", "ratio", "none"):
        raise ValueError(f"filter must be 'dapc', 'ratio' or 'none', got {cfg['filter']!r}")
    unknown = set(cfg["solver"]) - set(solver_default)
    if unknown:
        raise ValueError(f"unknown solver option(s) {sorted(unknown)}; known: {sorted(solver_default)}")
    unknown = set(cfg["pnp"]) - set(default_pnp_config)
    if unknown:
        raise ValueError(f"unknown PnP option(s) {sorted(unknown)}; known: {sorted(default_pnp_config)}")
    return cfg


def match_to_map(live: PointFeatures, mapf: PointFeatures, filter: str = "dapc", mutual: bool = True,
                 ratio: float = 0.8):
    """Matches map -> live: mutual nearest neighbours, then DAPC over the mutual pairs (the order of the M2Det
    scene-matching paper, §3.4).

    Returns
    -------
    :class:`signatures.pointfeatures.Matches` with ``query`` indexing the map features and ``train``
    the live ones.
    """
    return match(mapf, live, filter=filter, ratio=ratio, mutual=mutual,
                 dapc_over="mutual" if (mutual and filter == "dapc") else "all")


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
    features : its :class:`signatures.pointfeatures.PointFeatures`.
    ms : extraction time (ms), counted in the detection time.
    """

    shape: tuple
    features: PointFeatures
    ms: float = 0.0


@dataclass
class _MapPlace:
    features: PointFeatures
    xyz: np.ndarray
    cov: np.ndarray | None


class PointLocaliser(WeakLocaliser):
    """ORB or SIFT against the place keyframe's 3D points (a :class:`localiser.pipeline.WeakLocaliser`).

    Parameters
    ----------
    store : the map (built with point features: ``PlaceData.points``).
    camera, T_vehicle_camera : the live camera and extrinsic.
    config : overrides of :data:`default_config`.
    kind : ``"orb"`` or ``"sift"``.
    """

    color = False

    def __init__(self, store: MapStore, camera: Camera, T_vehicle_camera: np.ndarray, config: dict | None = None,
                 kind: str = "orb"):
        if kind not in ("orb", "sift"):
            raise ValueError(f"kind must be 'orb' or 'sift', got {kind!r}")
        self.kind = kind
        self.name = kind
        self.config = _merge(config)
        self.store = store
        self.camera = camera
        self.T_vehicle_camera = np.asarray(T_vehicle_camera, dtype=float)
        self._cache: OrderedDict[int, _MapPlace] = OrderedDict()
        self._lock = threading.Lock()
        if len(store) and not any(self._place(i).features is not None and len(self._place(i).features)
                                  for i in list(store.places)[: min(3, len(store))]):
            raise ValueError(f"map {store.root} has no {kind.upper()} point features (places hold no "
                             f"'points/{kind}_*' arrays): rebuild it with a scenesig whose build-map writes them")

    # ------------------------------------------------------------------------------ map side
    def _place(self, index: int) -> _MapPlace:
        index = int(index)
        with self._lock:
            if index in self._cache:
                self._cache.move_to_end(index)
                return self._cache[index]
        data = self.store.load_place(index)
        feats = point_features(data.points, self.kind)
        xyz = np.asarray(data.points.get(f"{self.kind}_xyz", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
        cov = None
        if self.config["use_point_covariance"] and f"{self.kind}_sigma" in data.points and len(xyz):
            cov = point_covariances(xyz, data.points[f"{self.kind}_sigma"], self.T_vehicle_camera)
        if feats is not None and len(feats) != len(xyz):
            raise ValueError(f"place {index}: {len(feats)} {self.kind} keypoints but {len(xyz)} 3D points")
        mp = _MapPlace(feats, xyz, cov)
        with self._lock:
            self._cache[index] = mp
            while len(self._cache) > max(1, int(self.config["cache"])):
                self._cache.popitem(last=False)
        return mp

    def prefetch(self, place):
        # Decoding a place's points takes well under a millisecond; loading it here keeps the
        # detector's timing honest without a thread.
        if place is not None and int(place) in self.store.places:
            self._place(place)

    # ------------------------------------------------------------------------------ detector
    def live_features(self, image: np.ndarray) -> PointFeatures:
        """The live image's features (same extraction as the map keyframe's)."""
        return extract(image, self.kind, n_features=int(self.config["n_features"]), config=self.config["features"])

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
        m = match_to_map(live, mp.features, cfg["filter"], bool(cfg["mutual"]), float(cfg["ratio"]))
        uv = live.xy[m.train].astype(float)
        sig = keypoint_sigma(live.subset(m.train), float(cfg["pixel_sigma"]), cfg["features"])
        R = (sig ** 2)[:, None, None] * np.eye(2)[None]
        cov = mp.cov[m.query] if mp.cov is not None else None
        return PointObservation(place, uv, R, mp.xyz[m.query], cov, m.query, len(live), len(mp.features),
                                ms_extract + (time.perf_counter() - t0) * 1e3)

    # -------------------------------------------------------------------------------- solver
    def solve(self, obs: PointObservation, place: int, prior: MotionPrior | None) -> Measurement:
        n = len(obs)
        extra = {"live_features": obs.n_live, "map_points": obs.n_map}
        if n < max(int(self.config["min_matches"]), 4):
            return Measurement(None, n, 0, "too_few_matches", obs.ms, 0.0, False, extra)
        T_prior = prior.T_place_vehicle if prior is not None else None
        P_prior = prior.covariance if prior is not None else None
        res = solve_pnp_prior(obs.uv, obs.xyz, self.camera, self.T_vehicle_camera, T_prior, P_prior, R=obs.R,
                              points_cov=obs.cov, config=self.config["solver"] or None,
                              pnp_config=self.config["pnp"] or None)
        extra["ransac_inliers"] = res.extra.get("ransac_inliers", 0)
        c = res.constraint(self.store.places[place].T_world_place)
        return Measurement(c, n, res.n_inliers, res.reason, obs.ms, res.ms, True, extra)

    def close(self):
        with self._lock:
            self._cache.clear()


def _factory(kind):
    def make(store, camera, T_vehicle_camera, config=None):
        return PointLocaliser(store, camera, T_vehicle_camera, config, kind=kind)
    make.__name__ = f"make_{kind}"
    return make


register_method("orb", _factory("orb"))
register_method("sift", _factory("sift"))
