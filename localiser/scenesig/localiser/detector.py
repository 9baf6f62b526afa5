"""Detector block of the online localiser (McManus et al. 2015, §3.3.1-3.3.2, Fig. 6).

Runs the signature bank of the current place (the localiser says which) on a live image and turns
the firings into measurements for the eq. 10 solver:

* **where to search** -- where the motion prior is good, each classifier only searches around its
  landmark's predicted projection: the window is ``±k σ`` of the projection's covariance

      Σ_uv = J P_x J^T + G P_l G^T + Q,

  with ``J = ∂h/∂ξ`` the projection's Jacobian with respect to the vehicle pose (right perturbation,
  GTSAM's convention, the same as the solver's), ``P_x`` the prior covariance, ``G = ∂h/∂p`` and
  ``P_l`` the landmark's map covariance, and ``Q`` the detector's own resolution; classifiers whose
  window lies off the image are not run at all.  Where the localiser is lost (too far on dead
  reckoning) or a window would cover most of the image, the whole image is searched.  Windows
  make detection cheaper and also remove most false firings before the solver sees them.
* **measurement noise** -- eq. 5, ``R = a / (λ s) Q``: ``a`` the firing's patch area over the
  place's median nominal patch area (so ``a/(λ s)`` is dimensionless and ``Q`` keeps its meaning
  of the covariance of a typical patch at full scale and certainty, as in :mod:`scenesig.mapping.refine`),
  ``λ`` the calibrated detection probability and ``s`` the pyramid scale of the firing.
* **which scales** -- where the prior is good, the scale of a firing is predicted too: a landmark at
  depth ``z_p`` from the place's camera and ``z`` from the live one appears ``z_p / z`` times its
  size at the place, so its classifier (trained at scale ``s_0``) is searched at the pyramid levels
  within ``scale_margin_levels`` of ``s_0 z / z_p`` rather than at its nominal level ±1 -- right when
  the vehicle is metres before or past the place, and fewer levels to build and score.
* **what to compute** -- the HOG pyramid holds exactly the levels searched, and at each level only
  the cells the windows' detections can touch (:meth:`scenesig.signatures.bank.Bank.pyramid`; about half of
  each level when tracking), bit-identical to the whole level's features there; the small
  multiplies run on one BLAS thread (``blas_threads``), and the levels -- each one's features,
  then its filter responses -- on ``threads`` threads for a whole-image search and
  ``window_threads`` for a windowed one (the same detections for any count).
* **prefetching** -- a place's bank is decoded (``Bank.from_arrays``) on a background thread as
  soon as the localiser names the next place, so switching places does not stall detection.

The detector knows nothing of the pose graph; it reads a place index, a prior ``T_place_vehicle``
and its covariance, and returns an :class:`Observation`.

``scenesig bench detector MAP RUN`` times detection on a run's frames with priors from the
run's INS poses (windowed and whole-image) and prints JSON.
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from scenesig.mapping.geometry import detection_covariance_factor, reference_area
from scenesig.mapping.refine import default_config as refine_default
from scenesig.mapping.store import MapStore, PlaceData
from scenesig.signatures.bank import Bank, limit_blas_threads
from scenesig.surveys.cache import LRUCache
from scenesig.surveys.geometry import Camera, invert, point_pose_jacobian
from scenesig.surveys.settings import merge_settings
from scenesig.surveys.validation import check_covariance

__all__ = ["default_config", "Observation", "Detector", "search_windows", "measurement_covariance",
           "projection_jacobians"]

default_config = {
    "top_n": 1,                  # firings per classifier (the best one is the measurement)
    "min_probability": 0.5,      # λ below this: the classifier did not really fire
    "Q": None,                   # base covariance (px², 2x2) at scale 1; None: the map's refinement Q
    "window_sigmas": 3.0,        # half-size of a search window in σ of the predicted projection
    "min_window_radius_px": 12.0,  # never search a smaller neighbourhood (detector resolution, skew)
    "max_window_fraction": 0.5,    # a window wider than this share of the image -> whole image
    "min_depth_m": 0.5,          # landmarks closer than this in front of the camera are skipped
    "bank_cache": 4,             # decoded banks kept (current, next, previous ...)
    "scale_search": 1,           # whole-image search: pyramid levels either side of the nominal one
    "predict_scale": True,       # windowed search: only the levels within ``scale_margin_levels`` of
    "scale_margin_levels": 0.75,  # the scale predicted from the landmark's depth now and at the place
    # BLAS threads while detecting (None: leave numpy's setting).  The multiplies are small: a second
    # thread only spins (~30 % more CPU, taken from the other blocks or the other process), and a
    # fixed count gives the same floating-point sums -- the same detections -- on every machine.
    "blas_threads": 1,
    # Pyramid levels described and scored at once (signatures.detection: the same detections for any
    # count): on two threads for a whole-image search (large levels); a windowed search's regions
    # are small, and a second thread only adds its hand-overs (replays measured no faster).
    "threads": 2,
    "window_threads": 1,
}


@dataclass
class Observation:
    """Detections of one place's bank in one image, paired with their landmarks.

    Attributes
    ----------
    place : place index.
    uv : (m, 2) firing centres (pixels).
    R : (m, 2, 2) their covariances (eq. 5).
    landmarks : (m, 3) landmarks in the place frame.
    landmark_cov : (m, 3, 3) their map covariances.
    classifier : (m,) index of the landmark in the place's arrays.
    prob, score : (m,) calibrated probability λ and raw SVM score.
    searched : number of classifiers run.
    whole_image : True when the whole image was searched (lost, or windows too wide).
    ms : wall time of detection (ms), including the pyramid.
    """

    place: int
    uv: np.ndarray
    R: np.ndarray
    landmarks: np.ndarray
    landmark_cov: np.ndarray
    classifier: np.ndarray
    prob: np.ndarray
    score: np.ndarray
    searched: int = 0
    whole_image: bool = False
    ms: float = 0.0
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.uv)

    @classmethod
    def empty(cls, place: int, ms: float = 0.0, searched: int = 0, whole_image: bool = False) -> "Observation":
        return cls(place, np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 3)), np.zeros((0, 3, 3)),
                   np.zeros(0, int), np.zeros(0), np.zeros(0), searched, whole_image, ms)


def projection_jacobians(landmarks: np.ndarray, T_place_vehicle: np.ndarray, camera: Camera,
                         T_vehicle_camera: np.ndarray, min_depth_m: float = 0.5):
    """Predicted pixels of landmarks and the Jacobians of the projection.

    Parameters
    ----------
    landmarks : (n, 3) points in the place frame.
    T_place_vehicle : (4, 4) vehicle pose in the place frame.
    camera, T_vehicle_camera : the live camera and its extrinsic.

    Returns
    -------
    uv : (n, 2) predicted pixels (NaN where the landmark is not in front of the camera).
    J_pose : (n, 2, 6) ``∂uv/∂ξ`` for ``T = T̄·Exp(ξ)``, ξ = (ω, v) (GTSAM order).
    J_point : (n, 2, 3) ``∂uv/∂p`` (place frame).
    front : (n,) bool, depth > ``min_depth_m``.
    """
    P = np.asarray(landmarks, dtype=float).reshape(-1, 3)
    R_pv, t_pv = T_place_vehicle[:3, :3], T_place_vehicle[:3, 3]
    T_cv = invert(np.asarray(T_vehicle_camera, dtype=float))
    R_cv, t_cv = T_cv[:3, :3], T_cv[:3, 3]
    P_v = (P - t_pv) @ R_pv                       # R_pv^T (p - t)
    P_c = P_v @ R_cv.T + t_cv
    front = P_c[:, 2] > min_depth_m
    safe = np.where(front[:, None], P_c, [0.0, 0.0, 1.0])
    uv, _ = camera.project(safe)
    uv[~front] = np.nan
    Jp = camera.project_jacobian(safe)            # (n, 2, 3), undistorted model (first order)
    D = point_pose_jacobian(P_v)              # P_v(ξ) = Exp(-ξ) P_v ≈ P_v + [P_v]x ω - v
    J_pose = Jp @ (R_cv @ D)
    J_point = Jp @ (R_cv @ R_pv.T)
    return uv, J_pose, J_point, front


def search_windows(landmarks, landmark_cov, T_place_vehicle, P_prior, camera: Camera, T_vehicle_camera,
                   Q: np.ndarray, config: dict | None = None):
    """Per-landmark search windows around the predicted projections.

    Returns
    -------
    windows : (n, 4) ``x_min, y_min, x_max, y_max`` for the detection centre; a row of NaN means
        the whole image (window too wide).
    searchable : (n,) bool, False where the landmark is behind the camera or its window misses the
        image (the classifier is not run).
    uv : (n, 2) predicted pixels.
    """
    cfg = merge_settings(default_config, config, "detector")
    uv, J_pose, J_point, front = projection_jacobians(landmarks, T_place_vehicle, camera, T_vehicle_camera,
                                                      cfg["min_depth_m"])
    n = len(uv)
    S = J_pose @ np.asarray(P_prior, float) @ np.swapaxes(J_pose, 1, 2) + np.asarray(Q, float)
    if landmark_cov is not None and len(landmark_cov):
        S = S + J_point @ np.asarray(landmark_cov, float) @ np.swapaxes(J_point, 1, 2)
    k = float(cfg["window_sigmas"])
    with np.errstate(invalid="ignore"):
        rx = np.maximum(k * np.sqrt(np.maximum(S[:, 0, 0], 0)), cfg["min_window_radius_px"])
        ry = np.maximum(k * np.sqrt(np.maximum(S[:, 1, 1], 0)), cfg["min_window_radius_px"])
    windows = np.column_stack([uv[:, 0] - rx, uv[:, 1] - ry, uv[:, 0] + rx, uv[:, 1] + ry])
    too_wide = (2 * rx > cfg["max_window_fraction"] * camera.width) | \
               (2 * ry > cfg["max_window_fraction"] * camera.height)
    # A window that misses the image entirely: the landmark cannot be seen from the prior.
    misses = ((windows[:, 2] < 0) | (windows[:, 0] > camera.width - 1)
              | (windows[:, 3] < 0) | (windows[:, 1] > camera.height - 1))
    searchable = front & np.isfinite(uv).all(axis=1) & (too_wide | ~misses)
    windows[too_wide] = np.nan
    return windows, searchable if n else np.zeros(0, bool), uv


def measurement_covariance(width, height, prob, scale, Q, area_ref: float) -> np.ndarray:
    """Eq. 5: ``R = a / (λ s) Q`` with ``a = width · height / area_ref`` (arrays (m,) -> (m, 2, 2))."""
    k = detection_covariance_factor(np.asarray(width, float) * np.asarray(height, float), prob, scale, area_ref)
    return k[:, None, None] * np.asarray(Q, float)[None]


@dataclass
class _LoadedPlace:
    data: PlaceData
    bank: Bank
    area_ref: float


class Detector:
    """Runs a place's bank on live images.

    Parameters
    ----------
    store : the map.
    camera : the live camera (must have the map's image size).
    T_vehicle_camera : the live extrinsic.
    config : overrides of :data:`default_config`.
    """

    def __init__(self, store: MapStore, camera: Camera, T_vehicle_camera: np.ndarray, config: dict | None = None):
        self.config = merge_settings(default_config, config, "detector")
        self.store = store
        self.camera = camera
        self.T_vehicle_camera = np.asarray(T_vehicle_camera, dtype=float)
        Q = self.config["Q"]
        if Q is None:
            # The covariance the landmarks were refined with, so map and live weights agree.
            Q = (store.params.get("config", {}).get("refine", {}) or {}).get("Q", refine_default["Q"])
        self.Q = check_covariance(Q, 2, "Q")
        self._cache = LRUCache(max(1, int(self.config["bank_cache"])))   # decoded banks (surveys.cache)
        self._pending: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="bank-prefetch")
        self.ms_total = 0.0
        self.n_detections = 0

    # ---------------------------------------------------------------------------- banks
    def _load(self, place: int) -> _LoadedPlace:
        data = self.store.load_place(place)
        bank = Bank.from_arrays(data.bank_arrays) if data.bank_arrays else Bank([])
        if len(bank) and bank.image_size is not None and bank.image_size != (self.camera.width, self.camera.height):
            raise ValueError(f"place {place}'s bank was trained on {bank.image_size[0]}x{bank.image_size[1]} images "
                             f"but the live camera is {self.camera.width}x{self.camera.height}")
        ids = np.asarray(data.classifier_ids, dtype=int)
        if len(ids) and (ids.min() < 0 or ids.max() >= len(bank)):
            raise ValueError(f"place {place}: classifier ids {ids.min()}..{ids.max()} outside the bank of {len(bank)}")
        areas = np.array([c.box[2] * c.box[3] for c in bank.classifiers], dtype=float)
        return _LoadedPlace(data, bank, reference_area(areas))

    def place(self, index: int) -> _LoadedPlace:
        """The decoded place (waits for a prefetch in flight)."""
        index = int(index)
        with self._lock:
            cached = self._cache.get(index)
            if cached is not None:
                return cached
            fut = self._pending.pop(index, None)
        loaded = fut.result() if fut is not None else self._load(index)
        with self._lock:
            self._cache.put(index, loaded)
        return loaded

    def prefetch(self, index: int | None) -> None:
        """Start decoding a place's bank in the background (no-op if cached or pending)."""
        if index is None:
            return
        index = int(index)
        with self._lock:
            if index in self._cache or index in self._pending or index not in self.store.places:
                return
            self._pending[index] = self._pool.submit(self._load, index)

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    # ------------------------------------------------------------------------ detection
    def detect(self, image: np.ndarray, place: int, T_place_vehicle: np.ndarray | None = None,
               P_prior: np.ndarray | None = None, whole_image: bool = False,
               max_classifiers: int | None = None) -> Observation:
        """Detect the place's signatures in an image.

        Parameters
        ----------
        image : gray or BGR uint8 image of the live camera.
        place : place index.
        T_place_vehicle, P_prior : motion prior and its covariance; without them (or with
            ``whole_image``) every classifier searches the whole image.
        max_classifiers : a whole-image search runs only this many classifiers, those of highest
            mining quality (global localisation verifies several places per frame; None: all).
        """
        with limit_blas_threads(self.config["blas_threads"]):
            return self._detect(image, place, T_place_vehicle, P_prior, whole_image, max_classifiers)

    def _detect(self, image, place, T_place_vehicle, P_prior, whole_image, max_classifiers=None) -> Observation:
        t0 = time.perf_counter()
        lp = self.place(place)
        data, bank = lp.data, lp.bank
        n = len(data.landmarks)
        h, w = image.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(f"image is {w}x{h} but the camera is {self.camera.width}x{self.camera.height}")
        if n == 0 or len(bank) == 0:
            return Observation.empty(place, (time.perf_counter() - t0) * 1e3)
        ids = np.asarray(data.classifier_ids, dtype=int)
        wide = whole_image or T_place_vehicle is None or P_prior is None
        if wide:
            sel = np.arange(n)
            windows = None
            if max_classifiers is not None and n > int(max_classifiers):
                q = np.array([bank.classifiers[k].quality for k in ids], dtype=float)
                sel = np.sort(np.argsort(-np.nan_to_num(q, nan=-np.inf), kind="stable")[:int(max_classifiers)])
        else:
            win, ok, _ = search_windows(data.landmarks, data.covariances, T_place_vehicle, P_prior, self.camera,
                                        self.T_vehicle_camera, self.Q, self.config)
            sel = np.flatnonzero(ok)
            windows = win[sel]
            if len(sel) and np.all(np.isnan(windows)):
                wide, windows = True, None
        if not len(sel):
            ms = (time.perf_counter() - t0) * 1e3
            self._count(ms)
            return Observation.empty(place, ms, 0, wide)
        sub = bank.select(ids[sel])
        levels = None
        if not wide and self.config["predict_scale"]:
            levels = self._predicted_levels(sub, data.landmarks[sel], T_place_vehicle)
        # The bank builds exactly the levels searched, and at each only the cells the windows can
        # reach (a tracking detector looks at a fraction of each level; those cells equal the whole
        # level's), describing and scoring the levels on ``threads`` (``window_threads``) threads.
        threads = int(self.config["threads"] if windows is None else self.config["window_threads"])
        d = sub.detect(image, windows=windows, top_n=int(self.config["top_n"]), levels=levels,
                       config={"scale_search": int(self.config["scale_search"]), "threads": threads})
        x, y, prob = d.x[:, 0], d.y[:, 0], d.prob[:, 0]
        good = np.isfinite(x) & np.isfinite(y) & (prob >= self.config["min_probability"]) & (d.scale[:, 0] > 0)
        j = np.flatnonzero(good)
        li = sel[j]
        R = measurement_covariance(d.width[j, 0], d.height[j, 0], prob[j], d.scale[j, 0], self.Q, lp.area_ref)
        ms = (time.perf_counter() - t0) * 1e3
        self._count(ms)
        return Observation(place, np.column_stack([x[j], y[j]]), R, np.asarray(data.landmarks[li], float),
                           np.asarray(data.covariances[li], float), li, prob[j].astype(float),
                           d.score[j, 0].astype(float), int(len(sel)), wide, ms)

    def _predicted_levels(self, bank: Bank, landmarks: np.ndarray, T_place_vehicle: np.ndarray) -> list:
        """Per classifier, the pyramid levels around the scale predicted from the landmark's depths."""
        T_cv = invert(self.T_vehicle_camera)
        L = np.asarray(landmarks, float)
        z_place = (L @ T_cv[:3, :3].T + T_cv[:3, 3])[:, 2]        # depth from the place's camera
        P_v = (L - T_place_vehicle[:3, 3]) @ T_place_vehicle[:3, :3]
        z_now = (P_v @ T_cv[:3, :3].T + T_cv[:3, 3])[:, 2]       # depth from the live camera
        spo = int(bank.hog["scales_per_octave"])
        m = float(self.config["scale_margin_levels"])
        out = []
        for c, zp, zn in zip(bank.classifiers, z_place, z_now):
            s0 = c.nominal_scale if np.isfinite(c.nominal_scale) and c.nominal_scale > 0 else c.scale
            if zp > 0 and zn > 0:
                k = -spo * np.log2(s0 * zn / zp)
                lo, hi = max(0, int(np.ceil(k - m))), max(0, int(np.floor(k + m)))
                out.append(range(lo, hi + 1))
            else:   # depth unknown: the nominal level +- scale_search
                ss = int(self.config["scale_search"])
                out.append(range(max(0, c.level - ss), c.level + ss + 1))
        return out

    def _count(self, ms: float) -> None:
        self.ms_total += ms
        self.n_detections += 1

    @property
    def ms_per_detection(self) -> float:
        return self.ms_total / max(self.n_detections, 1)
