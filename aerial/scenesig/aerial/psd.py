"""Point-set-domain matching of a UAV image on a map tile (the seed "A Point-Set-Domain Image Object
Matching Method for Airborne Object Localization", §§4-5, Algorithm 1) as three aerial methods.

* **Point stage** (``psd-point``, §4.1).  The seed trains a CNN detector and descriptor toward an
  existing detector's response (KPop-net, eqs. 2-4) and matches by the inner product of descriptors
  (eq. 5).  No KPop-net weights are published; XFeat (Potje et al. 2024,
  :mod:`scenesig.signatures.xfeat`) stands in: a CNN whose keypoint head is the same 65-way softmax over an
  8 x 8 cell plus "no keypoint" as eq. 4, trained with a keypoint loss toward a detector's response
  (ALIKE's) -- the seed's recipe.  Matching is eq. 5's inner product of unit descriptors, mutual nearest
  neighbours above ``min_cossim``; a RANSAC affine (:func:`scenesig.aerial.affine.ransac_affine`)
  places the sensed centre.
* **Set stage** (``psd-kdm``, §4.2): the keypoint-constrained diffeomorphism
  (:mod:`scenesig.aerial.kdm`) fitted on the matches the affine gates, starting from the affine; the
  sensed -> tile map is ``A o phi``.  Matches are re-gated under that map and the fit repeated once.
* **Domain stage** (``psd-kdmm``, §4.3, Algorithm 1): the alignment hypotheses of the set stage --
  the best RANSAC model and ``hypotheses - 1`` more found by sequential RANSAC on the matches the
  previous models leave, plus the model of all mutual nearest neighbours without the similarity
  threshold, each refined by KDM -- are scored by the region dissimilarity of
  :mod:`scenesig.aerial.kdmm` (CI-stable watershed regions, colour map ``phi_c``, eq. 12), and the
  lowest dissimilarity decides and places the match.

Every estimate carries a ``score`` (higher = more likely the right tile; the inliers for the point
stage, the matches within ``ransac_px`` of the KDM map for the set stage, minus the dissimilarity for
the domain stage), what the localiser uses to pick a tile and the benchmark's ROC uses, and the
matching data the seed's point measures need (:mod:`scenesig.aerial.measures`).

XFeat features can be kept on disk (``cache``: a folder; keyed by the image's bytes, the model file's
sha256 and the settings): descriptors are stored as float16 and always used as such, so a run reads
what it would have computed.  An estimate read from the cache carries the extraction's CPU seconds in
``extra_seconds``, so timings do not depend on the cache.
"""
from __future__ import annotations

import hashlib
import json
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from scenesig.aerial import kdm as _kdm, kdmm as _kdmm
from scenesig.aerial.affine import AffineEstimate, apply_affine, ransac_affine, scale_rotation
from scenesig.aerial.trials import sensed_centre
from scenesig.surveys.io import atomic_path
from scenesig.surveys.settings import merge_settings

__all__ = ["STAGES", "default_config", "PSDEstimate", "PSDMatcher", "XFeatStore"]

STAGES = ("point", "kdm", "kdmm")

#: Settings (the ones the seed leaves open were chosen on seed-0 development trials, docs/aerial.md).
default_config = {
    "stage": "kdmm",                # "point", "kdm" or "kdmm"
    "xfeat": {},                    # overrides of signatures.xfeat.default_config (model file, ...)
    "sensed_features": 2048,        # XFeat top-k in the sensed image
    "reference_features": 16000,    # ... and in the tile (about 15 times the area)
    "min_cossim": 0.82,             # eq. 5's inner product: mutual nearest neighbours above this
    "ransac_px": 3.0,
    "ransac_iters": 2000,
    "min_inliers": 6,
    "kdm_gates_px": (8.0, 3.0),     # matches within these of the affine, then of the first KDM map, fit phi
    "hypotheses": 3,                # sequential-RANSAC models the domain stage scores
    "kdm": {},                      # overrides of aerial.kdm.default_config
    "kdmm": {},                     # overrides of aerial.kdmm.default_config
    "cache": None,                  # folder keeping XFeat features on disk (None: memory only)
}


@dataclass
class PSDEstimate(AffineEstimate):
    """An :class:`~scenesig.aerial.affine.AffineEstimate` with the point-set-domain extras.

    Attributes
    ----------
    stage : str
    score : float
        Higher = more likely right (module docstring); ``-inf`` without an estimate.
    dissimilarity : float
        Domain stage: the chosen alignment's region dissimilarity (``nan`` otherwise).
    kdm_rms : float
        Set stage: RMS residual of the KDM fit (px, in the affine's frame).
    extra_seconds : float
        CPU seconds of a feature extraction read from the cache (0 when computed here).
    """

    stage: str = "point"
    score: float = float("-inf")
    dissimilarity: float = float("nan")
    kdm_rms: float = float("nan")
    extra_seconds: float = 0.0
    to_tile: object = field(default=None, repr=False)

    def map(self, xy) -> np.ndarray:
        """Sensed pixels -> tile pixels under the estimate (NaN without one)."""
        xy = np.asarray(xy, float)
        if self.to_tile is None:
            return np.full(xy.shape, np.nan)
        return np.asarray(self.to_tile(xy), float)


class XFeatStore:
    """XFeat features per image, in memory (a few hundred) and optionally on disk (module docstring)."""

    def __init__(self, xfeat_config: dict, folder=None, max_items: int = 64):
        from scenesig.signatures.xfeat import get_xfeat

        self.model = get_xfeat(xfeat_config)
        self.folder = None if folder is None else Path(folder).expanduser()
        self.max_items = int(max_items)
        self._mem: OrderedDict = OrderedDict()
        self._settings = json.dumps({k: v for k, v in self.model.describe().items() if k != "model"},
                                    sort_keys=True, default=repr)

    def get(self, image: np.ndarray, top_k: int):
        """``(xy, descriptors, cpu_seconds, from_cache)`` of the ``top_k`` best keypoints."""
        img = np.ascontiguousarray(image)
        h = hashlib.blake2b(img.data, digest_size=16)
        h.update(repr((img.shape, img.dtype.str, int(top_k), self._settings)).encode())
        key = h.hexdigest()
        if key in self._mem:
            self._mem.move_to_end(key)
            xy, desc, sec = self._mem[key]
            return xy, desc, sec, True
        path = None if self.folder is None else self.folder / f"{key}.npz"
        if path is not None and path.is_file():
            with np.load(path) as z:
                xy, desc, sec = z["xy"], z["desc"].astype(np.float32), float(z["seconds"])
            cached = True
        else:
            t0 = time.process_time()
            xy, _, desc = self.model.detect_and_compute(img, top_k=int(top_k))
            sec = time.process_time() - t0
            xy = np.asarray(xy, np.float32)
            desc16 = np.asarray(desc, np.float16)
            desc = desc16.astype(np.float32)            # always the stored precision (module docstring)
            cached = False
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_path(path) as tmp:
                    with open(tmp, "wb") as f:
                        np.savez(f, xy=xy, desc=desc16, seconds=np.float64(sec))
        self._mem[key] = (xy, desc, sec)
        while len(self._mem) > self.max_items:
            self._mem.popitem(last=False)
        return xy, desc, sec, cached


_STORES: dict = {}


def _store(xfeat_config: dict, folder) -> XFeatStore:
    key = (json.dumps(xfeat_config, sort_keys=True, default=repr), str(folder))
    if key not in _STORES:
        _STORES[key] = XFeatStore(xfeat_config, folder)
    return _STORES[key]


def _compose(A: np.ndarray, phi):
    """Sensed -> tile map ``A o phi`` (``phi`` None: the affine alone)."""
    if phi is None:
        return lambda xy: apply_affine(A, xy)
    return lambda xy: apply_affine(A, phi(xy))


class PSDMatcher:
    """Point-set-domain matching against one tile (estimator API: ``fit(tile)``, ``locate(image)``)."""

    def __init__(self, config: dict | None = None):
        self.config = merge_settings(default_config, config, "point-set-domain", open=("xfeat", "kdm", "kdmm"))
        if self.config["stage"] not in STAGES:
            raise ValueError(f"unknown point-set-domain stage {self.config['stage']!r}; choose from {STAGES}")
        self.kdm_config = merge_settings(_kdm.default_config, self.config["kdm"], "KDM")
        self.kdmm_config = merge_settings(_kdmm.default_config, self.config["kdmm"], "KDMM")

    def fit(self, reference: np.ndarray) -> "PSDMatcher":
        """Extract the tile's features (once per tile; cached) and, for the domain stage, its low-passed copy."""
        self.store_ = _store(self.config["xfeat"], self.config["cache"])
        xy, desc, _, _ = self.store_.get(reference, int(self.config["reference_features"]))
        self.ref_xy_, self.ref_desc_ = xy, desc
        self.reference_ = reference
        s = float(self.kdmm_config["work_scale"])
        self.ref_blur_ = cv2.GaussianBlur(reference, (0, 0), 0.5 / s) if s < 1 else reference
        return self

    # ---------------------------------------------------------------- stages
    def _matches(self, desc, min_cossim):
        """Eq. 5: mutual nearest neighbours by inner product; ``(ia, ib, similarity)`` of all mutual pairs
        (one similarity matrix serves every threshold) and the mask of those above ``min_cossim``."""
        from scenesig.signatures.xfeat import match_mnn

        ia, ib, s = match_mnn(desc, self.ref_desc_, -2.0)
        return ia, ib, s > float(min_cossim)

    def _ransac(self, src, dst, centre):
        cfg = self.config
        return ransac_affine(src, dst, centre, float(cfg["ransac_px"]), int(cfg["min_inliers"]),
                             int(cfg["ransac_iters"]))

    def _kdm(self, A, src, dst):
        """KDM on the matches gated by ``A`` (set stage); returns ``(phi, rms, inliers of A o phi)``."""
        Ainv = cv2.invertAffineTransform(np.asarray(A, np.float64))
        z = apply_affine(Ainv, dst)                      # targets in the affine's (sensed) frame
        phi, rms = None, float("nan")
        for gate in self.config["kdm_gates_px"]:
            pred = apply_affine(A, src if phi is None else phi(src))
            sel = np.linalg.norm(pred - dst, axis=1) <= float(gate)
            if sel.sum() < max(3, int(self.config["min_inliers"])):
                break
            phi = _kdm.fit_kdm(src[sel], z[sel], self.kdm_config)
            rms = phi.rms
        pred = apply_affine(A, src if phi is None else phi(src))
        inl = int((np.linalg.norm(pred - dst, axis=1) <= float(self.config["ransac_px"])).sum())
        return phi, rms, inl

    def _hypotheses(self, src, dst, src_all, dst_all, centre):
        """Affine models: sequential RANSAC on the thresholded matches, then one on all mutual pairs."""
        out, left = [], np.ones(len(src), bool)
        for _ in range(int(self.config["hypotheses"])):
            est = self._ransac(src[left], dst[left], centre)
            if est.transform is None:
                break
            out.append(est)
            res = np.linalg.norm(apply_affine(est.transform, src) - dst, axis=1)
            left &= res > 2 * float(self.config["ransac_px"])
        est = self._ransac(src_all, dst_all, centre)
        if est.transform is not None and all(np.linalg.norm(est.centre - o.centre) > 5.0 for o in out):
            out.append(est)
        return out

    def locate(self, sensed: np.ndarray) -> PSDEstimate:
        """Where the sensed image's centre lies on the tile (see the module docstring for the stages)."""
        t0 = time.process_time()
        cfg = self.config
        xy, desc, det_s, cached = self.store_.get(sensed, int(cfg["sensed_features"]))
        t1 = time.process_time()
        ja, jb, keep = self._matches(desc, cfg["min_cossim"])
        ia, ib = ja[keep], jb[keep]
        match_s = time.process_time() - t1
        c = sensed_centre(sensed.shape)
        src, dst = xy[ia].astype(float), self.ref_xy_[ib].astype(float)
        nan = np.full(2, np.nan)
        base = dict(stage=cfg["stage"], matched_pairs=int(len(ia)), keypoints=int(len(xy)),
                    point_data={"sensed_xy": xy, "tile_xy": self.ref_xy_, "query": ia, "train": ib,
                                "detect_seconds": det_s, "match_seconds": match_s},
                    extra_seconds=det_s if cached else 0.0)
        if cfg["stage"] != "kdmm":
            est = self._ransac(src, dst, c)
            if est.transform is None:
                return PSDEstimate(nan, None, est.inliers, len(src), **base)
            if cfg["stage"] == "point":
                return PSDEstimate(est.centre, est.transform, est.inliers, len(src), est.scale, est.rotation_deg,
                                   score=float(est.inliers), to_tile=_compose(est.transform, None), **base)
            phi, rms, inl = self._kdm(est.transform, src, dst)
            f = _compose(est.transform, phi)
            return PSDEstimate(f(c[None])[0], est.transform, inl, len(src), est.scale, est.rotation_deg,
                               score=float(inl), kdm_rms=rms, to_tile=f, **base)
        # domain stage: every hypothesis refined by KDM, scored by the region dissimilarity
        hyps = self._hypotheses(src, dst, xy[ja].astype(float), self.ref_xy_[jb].astype(float), c)
        kc = self.kdmm_config
        s = float(kc["work_scale"])
        small = cv2.resize(sensed, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s != 1 else sensed
        labels = _kdmm.ci_regions(small, kc) if hyps else None
        best = None
        for h in hyps:
            phi, rms, inl = self._kdm(h.transform, src, dst)
            f = _compose(h.transform, phi)
            ref, valid = _kdmm.warp_reference(self.ref_blur_, f, small.shape[:2], s)
            d = _kdmm.domain_dissimilarity(small, ref, valid, labels, kc)
            if best is None or d < best[0]:
                best = (d, h, f, rms, inl)
        if best is None or not np.isfinite(best[0]):
            n_in = hyps[0].inliers if hyps else 0
            return PSDEstimate(nan, None, n_in, len(src), dissimilarity=best[0] if best else float("nan"), **base)
        d, h, f, rms, inl = best
        sc, rot = scale_rotation(h.transform)
        est = PSDEstimate(f(c[None])[0], h.transform, inl, len(src), sc, rot, score=-d, dissimilarity=d,
                          kdm_rms=rms, to_tile=f, **base)
        est.seconds = time.process_time() - t0
        return est
