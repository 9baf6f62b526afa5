"""Global localisation and relocalisation from the map alone (no INS/GPS).

The paper's localiser (McManus et al. 2015, §3.3) starts from, and recovers through, the vehicle's
INS/GPS.  Without one the localiser must find where it is on the map from images and odometry:

1. **Coarse retrieval** (:class:`PlaceRetrieval`) -- every place stores compact whole-image
   descriptors of its training images (:mod:`scenesig.signatures.globaldesc`, written by the map builder);
   the live image's descriptor is compared with all of them and the best places form a shortlist.
2. **Verification** -- each shortlisted place's weak localiser (for scene signatures: its bank
   searched over the whole image, then the eq. 10 solver) runs with a vague prior centred on the
   place; it counts when the solver accepts a pose with at least ``verify_min_inliers`` inliers.
3. **Sequence consistency** (SeqSLAM-like, Milford & Wyeth 2012) -- a verified pose is accepted
   only when at least ``sequence_length`` verified detections from distinct frames agree with the
   odometry between them: each earlier one, carried forward by the dead-reckoned motion, must land
   within ``agree_m + agree_per_m * d`` metres and ``agree_deg`` degrees of the newest.  A single
   wrong verification (perceptual aliasing: another place that looks alike) cannot pass.

Until a pose is accepted the localiser reports itself as not localised.  When it is **lost** (the
paper's failure rule: more than 20 m on dead reckoning), the search starts with the places within
the dead-reckoning uncertainty of its estimate (``3 sigma`` of the pose graph's position covariance
plus ``search_radius_m``), and the radius doubles every ``widen_every`` frames without a verified
detection until it covers the whole map.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.signatures import globaldesc
from scenesig.signatures.bank import limit_blas_threads
from scenesig.surveys.geometry import yaw_of
from scenesig.surveys.settings import merge_settings

from .methods import Measurement, MotionPrior, WeakLocaliser
from .pipeline import Localiser

__all__ = ["default_config", "PlaceRetrieval", "Relocaliser", "SearchResult", "place_descriptors"]

default_config = {
    "shortlist": 3,                # places verified per detector frame
    "verify_classifiers": 40,      # classifiers (the best by mining quality) searched per verified place
    "verify_min_inliers": 6,       # a verification needs this many solver inliers
    # Vague prior around a shortlisted place (GTSAM Pose3 order: rotation rad, translation m): the
    # vehicle is somewhere near the place, roughly facing its way.
    "prior_sigma": [0.05, 0.05, 0.3, 6.0, 3.0, 0.5],
    "sequence_length": 3,          # verified detections (distinct frames) that must agree
    "sequence_window_m": 40.0,     # ... within this odometry distance of the newest
    "agree_m": 2.0,                # position tolerance between a carried-forward and a new pose
    "agree_per_m": 0.05,           # ... plus this per metre of odometry between them (drift)
    "agree_deg": 5.0,              # heading tolerance
    "search_radius_m": 20.0,       # lost: places within this + 3 sigma of the dead-reckoned estimate
    "widen_every": 4,              # lost: frames without a verified detection before doubling it
}


def place_descriptors(store: MapStore):
    """Stacked descriptors of the map's places: ``(D (m, d) unit rows, owner (m,) place index)``.

    Read from the manifest (``extra["descriptor"]``, written by the builder).  A map built without
    them falls back on its places' keyframes (the reference run's image only); a map with neither
    returns empty arrays (every place then ranks equally).
    """
    ids = sorted(store.places)
    cfg = (store.params.get("config", {}) or {}).get("descriptor") or {}
    rows, owner = [], []
    for i in ids:
        entry = store.places[i].extra.get("descriptor")
        if entry is not None:
            d = globaldesc.decode(entry)
        else:
            kf = store.load_place(i).keyframe_image()
            if kf is None:
                continue
            d = globaldesc.describe(kf, cfg)[None]
        rows.append(d)
        owner += [i] * len(d)
    if not rows:
        return np.zeros((0, 0), np.float32), np.zeros(0, int)
    return np.concatenate(rows).astype(np.float32), np.asarray(owner, int)


class PlaceRetrieval:
    """Coarse place retrieval: the places whose stored descriptors best match a live image."""

    def __init__(self, store: MapStore):
        self.store = store
        self.ids = np.array(sorted(store.places), dtype=int)
        self._pos = {int(i): k for k, i in enumerate(self.ids)}
        self.config = merge_settings(globaldesc.default_config,
                                     (store.params.get("config", {}) or {}).get("descriptor") or None, "descriptor")
        D, owner = place_descriptors(store)
        self.D = D
        self.owner = np.array([self._pos[int(o)] for o in owner], dtype=int)

    def scores(self, image: np.ndarray) -> np.ndarray:
        """Similarity of the image to every place (order of :attr:`ids`; 0 for all without descriptors)."""
        if not len(self.D):
            return np.zeros(len(self.ids), np.float32)
        q = globaldesc.describe(image, self.config)
        if q.shape[0] != self.D.shape[1]:
            raise ValueError(f"the map's place descriptors have {self.D.shape[1]} values, the live image's "
                             f"{q.shape[0]}: different image size or descriptor settings")
        # one BLAS thread: a threaded matrix-vector product only spins against the other blocks
        with limit_blas_threads(1):
            return globaldesc.similarity(q, self.D, self.owner, len(self.ids))

    def rank(self, image: np.ndarray, candidates=None) -> list[int]:
        """Place indices, best first (only ``candidates`` if given)."""
        s = self.scores(image)
        order = np.argsort(-s, kind="stable")
        ranked = [int(self.ids[k]) for k in order]
        if candidates is None:
            return ranked
        keep = {int(c) for c in candidates}
        return [p for p in ranked if p in keep]


@dataclass
class SearchResult:
    """One frame of global search: what the recorder needs, and the counts."""

    measurement: Measurement
    place: int
    accepted: bool
    verified: int = 0
    candidates: int = 0
    ms_retrieval: float = 0.0
    ms_detect: float = 0.0
    ms_solve: float = 0.0


@dataclass
class _Fix:
    t: float
    place: int
    T: np.ndarray
    cov: np.ndarray
    inliers: int
    d: float = 0.0     # odometry distance of the localiser at t
    measurement: Measurement | None = None


class Relocaliser:
    """Global localisation at start-up and relocalisation when lost (module docstring).

    Parameters
    ----------
    store : the map.
    method : the weak localiser that verifies a shortlisted place (``detect`` + ``solve``).
    localiser : the :class:`scenesig.localiser.pipeline.Localiser` (its odometry, estimate and :meth:`fix`).
    config : overrides of :data:`default_config`.
    retrieval : the coarse retrieval (default: :class:`PlaceRetrieval` of ``store``); anything with
        ``rank(image, candidates=None) -> [place, ...]``.
    """

    def __init__(self, store: MapStore, method: WeakLocaliser, localiser: Localiser, config: dict | None = None,
                 retrieval=None):
        self.config = merge_settings(default_config, config, "relocalisation")
        self.store = store
        self.method = method
        self.loc = localiser
        self.retrieval = retrieval if retrieval is not None else PlaceRetrieval(store)
        self._prior_cov = np.diag(np.asarray(self.config["prior_sigma"], float) ** 2)
        self._fixes: list[_Fix] = []
        self._fruitless = 0
        self._xy = {int(i): m.position[:2] for i, m in store.places.items()}
        self.ms_retrieval: list[float] = []
        self.searches = 0

    # ----------------------------------------------------------------------------- candidates
    def candidates(self, t: float) -> list[int] | None:
        """Places to search: None (the whole map) before the first fix; around the dead-reckoned
        estimate when lost, the radius doubling every ``widen_every`` fruitless frames."""
        if not self.loc.has_estimate:
            return None
        cfg = self.config
        T = self.loc.estimate(t)
        P = self.loc.graph.covariance()
        sigma = float(np.sqrt(max(np.linalg.eigvalsh(P[3:5, 3:5]).max(), 0.0)))
        radius = (cfg["search_radius_m"] + 3.0 * sigma) * 2.0 ** (self._fruitless // max(1, int(cfg["widen_every"])))
        near = [i for i, xy in self._xy.items() if np.linalg.norm(xy - T[:2, 3]) <= radius]
        return None if len(near) == len(self._xy) else near

    # ---------------------------------------------------------------------------------- search
    def search(self, image, t: float, descriptor_image: np.ndarray | None = None) -> SearchResult:
        """Retrieve, verify and sequence-check one detector frame at time t.

        ``image`` is what the method's ``detect`` takes (the image or its ``prepare()`` result);
        ``descriptor_image`` the image itself when ``image`` is not one.
        """
        cfg = self.config
        self.searches += 1
        raw = descriptor_image if descriptor_image is not None else image
        t0 = time.perf_counter()
        cands = self.candidates(t)
        shortlist = self.retrieval.rank(raw, cands)[:max(1, int(cfg["shortlist"]))]
        ms_ret = 1e3 * (time.perf_counter() - t0)
        self.ms_retrieval.append(ms_ret)
        best: Measurement | None = None        # the most inliers: what the frame records when nothing is accepted
        best_place = shortlist[0] if shortlist else int(min(self.store.places))
        ms_det = ms_solve = 0.0
        verified: list[_Fix] = []
        d_now = self.loc.distance_at(t)
        for p in shortlist:
            Twp = self.store.places[p].T_world_place
            prior = MotionPrior(float(t), Twp, self._prior_cov, p, Twp, None, True, float("inf"),
                                cfg["verify_classifiers"])
            a = time.perf_counter()
            obs = self.method.detect(image, p, prior)
            b = time.perf_counter()
            m = Measurement.coerce(self.method.solve(obs, p, prior))
            c = time.perf_counter()
            ms_det += 1e3 * (b - a)
            ms_solve += 1e3 * (c - b)
            if best is None or m.inliers > best.inliers:
                best, best_place = m, p
            if m.constraint is not None and m.inliers >= cfg["verify_min_inliers"]:
                k = m.constraint
                verified.append(_Fix(float(t), p, k.T_world_vehicle, k.covariance, int(m.inliers), d_now, m))
        if best is None:
            best = Measurement(None, reason="no_candidate")
        accepted = False
        if verified:
            self._fruitless = 0
            for f in sorted(verified, key=lambda f: -f.inliers):
                if self._consistent_history(f):
                    self.loc.fix(f.t, f.T, f.cov)
                    self._fixes.clear()
                    best, best_place, accepted = f.measurement, f.place, True
                    break
            if not accepted:
                self._fixes.extend(verified)
                self._prune(d_now)
        else:
            self._fruitless += 1
            if not best.reason:
                best.reason = "not_verified"
        if not accepted and best.constraint is not None:
            best.reason = "awaiting_sequence" if verified else (best.reason or "too_few_inliers")
        return SearchResult(best, int(best_place), accepted, len(verified), len(shortlist), ms_ret, ms_det, ms_solve)

    def _prune(self, d_now: float) -> None:
        w = self.config["sequence_window_m"]
        self._fixes = [f for f in self._fixes if d_now - f.d <= w]

    def agree(self, a: _Fix, b: _Fix) -> bool:
        """Does fix ``a``, carried to ``b``'s time by the odometry, agree with ``b``?"""
        cfg = self.config
        T_pred = a.T @ self.loc.odometry_between(a.t, b.t)
        d = abs(b.d - a.d)
        dp = float(np.linalg.norm(T_pred[:2, 3] - b.T[:2, 3]))
        dyaw = abs(float(np.degrees(np.angle(np.exp(1j * (yaw_of(T_pred) - yaw_of(b.T)))))))
        return dp <= cfg["agree_m"] + cfg["agree_per_m"] * d and dyaw <= cfg["agree_deg"]

    def _consistent_history(self, f: _Fix) -> bool:
        """Enough earlier verified detections (distinct frames) agree with ``f`` through the odometry."""
        need = int(self.config["sequence_length"]) - 1
        if need <= 0:
            return True
        w = self.config["sequence_window_m"]
        times = {g.t for g in self._fixes if g.t < f.t and f.d - g.d <= w and self.agree(g, f)}
        return len(times) >= need
