"""Scene signatures as an aerial matcher: a bank of HOG-patch classifiers mined from one tile.

McManus et al. 2015 (§3.2) mine place-dependent classifiers from many images of a place under
different appearance.  A satellite tile comes in one appearance only, so -- as the scene-signature
heading method does for a single map image (:func:`scenesig.signatures.heading.augment`) -- the bank is
mined from augmented copies of the tile: colour casts, gamma, contrast, snow-like whitening, blur,
noise and small known shifts.  Candidate shapes are squares of about ``square_px`` on a dense grid
over the tile (the sensed image covers a ninth of a tile, so the place-sized default template would
give shapes larger than it).

Matching: the bank is detected over the whole sensed image (at ``scale``); each classifier's best
detection above ``min_prob`` pairs its position in the sensed image with its nominal position on
the tile, and an affine transform fitted to those pairs by RANSAC maps the sensed centre onto the
tile.  Mined banks can be cached (``cache_dir``): mining is offline map building, not
localisation.
"""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import cv2
import numpy as np

from scenesig.aerial.affine import AffineEstimate, ransac_affine
from scenesig.aerial.trials import sensed_centre
from scenesig.signatures import mining
from scenesig.signatures.bank import Bank
from scenesig.signatures.heading import augment
from scenesig.surveys.io import atomic_path
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "SignatureMatcher"]

#: Scene-signature matcher settings.
default_config = {
    "scale": 0.5,                  # mining and detection resolution
    "augment_copies": 8,           # augmented copies of the tile (plus the tile itself)
    "augment_shift_px": 16.0,      # max shift of a copy (full-resolution px)
    "square_px": 96.0,             # candidate square side (full-resolution px)
    "grid_px": 80.0,               # spacing of the candidate squares (full-resolution px)
    "mining": {"search_radius_px": 16.0, "max_classifiers": 150},
    "min_prob": 0.3,               # a classifier's detection must reach this probability
    "ransac_px": 8.0,              # RANSAC reprojection threshold (full-resolution px)
    "min_inliers": 4,
    "seed": 0,
}


class SignatureMatcher:
    """Scene-signature bank of one tile, matched by detections + RANSAC affine (estimator API)."""

    def __init__(self, config: dict | None = None, cache_dir=None):
        self.config = merge_settings(default_config, config, "signature-matcher", open=("mining",))
        self.cache_dir = None if cache_dir is None else Path(cache_dir)

    def _shapes(self, w: int, h: int) -> dict:
        f = float(self.config["scale"])
        side = float(self.config["square_px"]) * f
        step = float(self.config["grid_px"]) * f
        return {"kinds": [{"name": "square", "size": side / np.sqrt(w * h), "aspect": 1.0,
                           "nx": max(2, int((w - side) / step) + 1),
                           "ny": max(2, int((h - side) / step) + 1)}]}

    def _key(self, tile: np.ndarray) -> str:
        h = hashlib.sha256(np.ascontiguousarray(tile[::4, ::4]).tobytes())
        # only what decides the bank (detection settings such as min_prob do not re-mine)
        mine = {k: v for k, v in self.config.items() if k not in ("min_prob", "ransac_px", "min_inliers")}
        h.update(json.dumps(mine, sort_keys=True, default=str).encode())
        return h.hexdigest()[:20]

    def fit(self, tile: np.ndarray) -> "SignatureMatcher":
        """Mine (or load from the cache) the tile's bank."""
        t0 = time.perf_counter()
        cfg = self.config
        f = float(cfg["scale"])
        cache = None
        if self.cache_dir is not None:
            cache = self.cache_dir / f"bank_{self._key(tile)}.npz"
            if cache.is_file():
                with np.load(cache, allow_pickle=False) as z:
                    self.bank_ = Bank.from_arrays(dict(z))
                self.mining_seconds_ = 0.0
                return self
        base = cv2.resize(tile, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
        rng = np.random.default_rng(int(cfg["seed"]))
        images, offsets = [base], [(0.0, 0.0)]
        for _ in range(int(cfg["augment_copies"])):
            im, sh = augment(base, rng, float(cfg["augment_shift_px"]) * f)
            images.append(im)
            offsets.append((sh, 0.0))
        mcfg = {**cfg["mining"], "shapes": self._shapes(base.shape[1], base.shape[0])}
        self.bank_, self.stats_ = mining.mine_place(images, np.array(offsets), config=mcfg,
                                                    n_jobs=1, rng=int(cfg["seed"]))
        self.mining_seconds_ = time.perf_counter() - t0
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(cache) as tmp:
                np.savez(tmp, **self.bank_.to_arrays())
        return self

    def locate(self, sensed: np.ndarray) -> AffineEstimate:
        """Where the sensed image's centre lies on the tile."""
        t0 = time.perf_counter()
        cfg = self.config
        f = float(cfg["scale"])
        src = dst = np.zeros((0, 2))
        if len(self.bank_):
            small = cv2.resize(sensed, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
            det = self.bank_.detect(small, top_n=1)
            x, y, p = det.x[:, 0], det.y[:, 0], det.prob[:, 0]
            use = np.isfinite(x) & np.isfinite(y) & (np.nan_to_num(p) >= float(cfg["min_prob"]))
            # Detection centres and nominal positions -> full-resolution pixels (INTER_AREA by 1/f).
            src = (np.stack([x[use], y[use]], axis=1) + 0.5) / f - 0.5
            nom = np.array([c.nominal_xy for c in self.bank_.classifiers])[use]
            dst = (nom + 0.5) / f - 0.5
        est = ransac_affine(src, dst, sensed_centre(sensed.shape), float(cfg["ransac_px"]),
                            int(cfg["min_inliers"]))
        est.seconds = time.perf_counter() - t0
        return est
