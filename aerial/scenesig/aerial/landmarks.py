"""Landmark regions from colour-histogram statistics (Jin et al. 2016, §3.2, eqs. 3-6).

For each landmark type B (the paper: roads, sports fields, buildings, rivers) a colour histogram
``p_B`` of its pixels and a histogram ``pbar_B`` of their neighbourhood mean colours (eq. 4: the
mean over the neighbourhood without the pixel itself) are learnt from a training library cut from
the geo-referenced images.  A sensed pixel's landmark likelihood is ``p_B(I) * pbar_B(I_r)``
(eq. 6); sub-regions whose mean likelihood passes a threshold are the landmark regions, and
overlapping regions of different types are combined into one, centred at the mean of their
centres.

The paper picks its training library by hand.  Here it is picked by one colour rule per type on the
reference tiles (:data:`default_config` ``"types"``; HSV in OpenCV units, H 0-179, S and V 0-255),
which selects the same kind of pixels without hand labelling: unsaturated grey-to-bright pixels for
roads and tracks, very bright or red-roof pixels for buildings, light yellow-green open ground for
fields, blue for rivers.  A type with too few training pixels is dropped.  Likelihoods are divided
by the type's mean likelihood over its own training pixels, so one threshold serves every type.

Two practical additions, both because NCC must be able to register the region: a region must lie
wholly on valid sensed pixels, and its gray-level standard deviation must reach
``min_region_std`` (a region of uniform field has no NCC peak).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "LandmarkModel", "Region"]

log = logging.getLogger(__name__)

#: Landmark parameters.
default_config = {
    "bins": 16,                    # histogram bins per colour channel (16^3 colours)
    "neighbourhood": 5,            # eq. 4: side of the neighbourhood N_ij
    "types": {                     # training-pixel rule per landmark type (HSV, OpenCV units)
        "roads": {"s": (0, 40), "v": (110, 245)},
        "buildings": {"any": [{"s": (0, 60), "v": (200, 256)},
                              {"h": (0, 10), "s": (80, 256), "v": (80, 256)},
                              {"h": (165, 180), "s": (80, 256), "v": (80, 256)}]},
        "fields": {"h": (18, 40), "s": (50, 180), "v": (110, 256)},
        "rivers": {"h": (90, 130), "s": (40, 256), "v": (40, 256)},
    },
    "min_training_pixels": 2000,   # a type with fewer training pixels is dropped
    "training_stride": 2,          # use every n-th pixel of the library (rows and columns)
    "region_size": 64,             # sub-region side (paper: 64 x 64)
    "threshold": 0.2,              # mean normalised likelihood a landmark region must reach
    "regions_per_type": 8,         # at most this many regions per type (the paper shows 3-10)
    "region_spacing": 40,          # same-type regions: centres at least this far apart (px)
    "merge_distance": 32,          # regions of different types closer than this are combined
    "min_region_std": 12.0,        # gray-level standard deviation a region needs (NCC)
    "stride": 8,                   # candidate region centres are on this grid (px)
}


@dataclass
class Region:
    """A landmark region: centre (x, y) in sensed pixels, score, and the types it combines."""

    x: float
    y: float
    score: float
    types: tuple


def _rule_mask(hsv: np.ndarray, rule: dict) -> np.ndarray:
    if "any" in rule:
        m = np.zeros(hsv.shape[:2], bool)
        for r in rule["any"]:
            m |= _rule_mask(hsv, r)
        return m
    m = np.ones(hsv.shape[:2], bool)
    for ch, key in enumerate("hsv"):
        if key in rule:
            lo, hi = rule[key]
            m &= (hsv[..., ch] >= lo) & (hsv[..., ch] < hi)
    return m


def _neighbour_mean(image: np.ndarray, k: int) -> np.ndarray:
    """Eq. 4: mean colour of the k x k neighbourhood without the centre pixel."""
    f = image.astype(np.float32)
    s = cv2.boxFilter(f, -1, (k, k), normalize=False, borderType=cv2.BORDER_REFLECT)
    return np.clip((s - f) / (k * k - 1), 0, 255).astype(np.uint8)


class LandmarkModel:
    """Colour-histogram landmark detector (estimator API: :meth:`fit`, then :meth:`regions`).

    Parameters
    ----------
    config : dict, optional
        Overrides of :data:`default_config`.

    Attributes
    ----------
    types_ : list of str
        Landmark types kept after fitting.
    p_, pbar_ : ndarray (T, bins^3)
        Normalised colour / neighbourhood-colour histograms per type.
    """

    def __init__(self, config: dict | None = None):
        # A caller's "types" replaces the whole set of landmark types.
        self.config = merge_settings(default_config, config, "landmark", open=("types",))
        if config and "types" in config:
            self.config["types"] = dict(config["types"])

    def _index(self, image: np.ndarray) -> np.ndarray:
        b = int(self.config["bins"])
        q = (image.astype(np.int32) * b) >> 8
        return (q[..., 0] * b + q[..., 1]) * b + q[..., 2]

    def fit(self, images) -> "LandmarkModel":
        """Learn ``p_B`` and ``pbar_B`` of every type from the library images (BGR uint8)."""
        cfg = self.config
        b3 = int(cfg["bins"]) ** 3
        st = int(cfg["training_stride"])
        k = int(cfg["neighbourhood"])
        counts = {t: (np.zeros(b3), np.zeros(b3)) for t in cfg["types"]}
        for img in images:
            hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)[::st, ::st]
            idx = self._index(img)[::st, ::st]
            idx_r = self._index(_neighbour_mean(img, k))[::st, ::st]
            for t, rule in cfg["types"].items():
                m = _rule_mask(hsv, rule)
                counts[t][0][:] += np.bincount(idx[m], minlength=b3)
                counts[t][1][:] += np.bincount(idx_r[m], minlength=b3)
        self.types_, p, pbar, ref = [], [], [], []
        for t, (c, cr) in counts.items():
            n = c.sum()
            if n < int(cfg["min_training_pixels"]):
                log.info("landmark type %s dropped: %d training pixels", t, int(n))
                continue
            pt, prt = c / n, cr / cr.sum()
            # Normaliser: the mean likelihood of the type's own training pixels.
            joint_mean = float((c * pt).sum() / n) * float((cr * prt).sum() / n)
            self.types_.append(t)
            p.append(pt)
            pbar.append(prt)
            ref.append(max(joint_mean, 1e-30))
        if not self.types_:
            raise ValueError("no landmark type has enough training pixels in the library")
        self.p_ = np.array(p, np.float32)
        self.pbar_ = np.array(pbar, np.float32)
        self.ref_ = np.array(ref, np.float32)
        return self

    def likelihood(self, image: np.ndarray) -> np.ndarray:
        """Normalised eq.-6 likelihood maps, (T, H, W) float32."""
        idx = self._index(image)
        idx_r = self._index(_neighbour_mean(image, int(self.config["neighbourhood"])))
        return (self.p_[:, idx] * self.pbar_[:, idx_r]) / self.ref_[:, None, None]

    def regions(self, image: np.ndarray, valid: np.ndarray | None = None) -> list[Region]:
        """Landmark regions of a BGR image (region centres in its pixels).

        Parameters
        ----------
        image : ndarray (H, W, 3) uint8
        valid : ndarray of bool (H, W), optional
            Pixels that carry image content (regions must lie wholly on them).
        """
        cfg = self.config
        s, st = int(cfg["region_size"]), int(cfg["stride"])
        H, W = image.shape[:2]
        if H < s or W < s:
            return []
        lik = self.likelihood(image)
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float64)
        ys = np.arange(0, H - s + 1, st)
        xs = np.arange(0, W - s + 1, st)

        def box_means(a):
            ii = cv2.integral(a.astype(np.float64))
            y0, x0 = ys[:, None], xs[None, :]
            return (ii[y0 + s, x0 + s] - ii[y0, x0 + s] - ii[y0 + s, x0] + ii[y0, x0]) / (s * s)

        mean_g, mean_g2 = box_means(gray), box_means(gray * gray)
        ok = np.sqrt(np.maximum(mean_g2 - mean_g ** 2, 0)) >= float(cfg["min_region_std"])
        if valid is not None:
            ok &= box_means(~np.asarray(valid, bool)) == 0
        found = []      # (x, y, score, type)
        r2 = float(cfg["region_spacing"]) ** 2
        for t, name in enumerate(self.types_):
            score = np.where(ok, box_means(lik[t]), -np.inf)
            order = np.argsort(-score, axis=None)
            chosen = []
            for flat in order:
                v = score.flat[flat]
                if v < float(cfg["threshold"]) or len(chosen) >= int(cfg["regions_per_type"]):
                    break
                cy = ys[flat // len(xs)] + (s - 1) / 2
                cx = xs[flat % len(xs)] + (s - 1) / 2
                if all((cx - a) ** 2 + (cy - b) ** 2 >= r2 for a, b, _ in chosen):
                    chosen.append((cx, cy, float(v)))
            found += [(a, b, v, name) for a, b, v in chosen]
        return _combine(found, float(cfg["merge_distance"]))


def _combine(found, dist: float) -> list[Region]:
    """Combine regions of different types that overlap (centre at the mean of their centres)."""
    groups: list[list] = []
    for f in sorted(found, key=lambda f: -f[2]):
        for g in groups:
            if f[3] not in {m[3] for m in g} and all(
                    np.hypot(f[0] - m[0], f[1] - m[1]) < dist for m in g):
                g.append(f)
                break
        else:
            groups.append([f])
    return [Region(float(np.mean([m[0] for m in g])), float(np.mean([m[1] for m in g])),
                   float(max(m[2] for m in g)), tuple(m[3] for m in g)) for g in groups]
