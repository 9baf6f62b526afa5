"""Point-feature baselines for aerial scene matching: SIFT, ORB or XFeat, matching, RANSAC affine.

A competent set-up for a nadir image against a north-up map: rotation-invariant features (the
sensed image may be rotated; upright descriptors would not match beyond a few degrees), many
more features on the reference than on the sensed image (it covers about fifteen times the area),
2-NN matching with Lowe's ratio 0.8, and an affine transform fitted by RANSAC
(``cv2.estimateAffine2D``, 3-px reprojection threshold) -- the sensed centre mapped by it is the
estimate.  Extraction and descriptor matching are :mod:`scenesig.signatures.pointfeatures`'; the
reference's features are computed once per tile.  XFeat (Potje et al. 2024, :mod:`scenesig.signatures.xfeat`;
rotation-robust by training, no orientation step) is matched with its authors' matcher instead of the
ratio test: mutual nearest neighbours with cosine similarity above 0.82.
"""
from __future__ import annotations

import time

import numpy as np

from scenesig.aerial.affine import AffineEstimate, ransac_affine
from scenesig.aerial.trials import sensed_centre
from scenesig.signatures import pointfeatures as pf
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "PointMatcher"]

#: Point-feature settings.
default_config = {
    "kind": "sift",                 # "sift", "rootsift", "orb" or "xfeat"
    "xfeat": {},                    # overrides of signatures.xfeat.default_config (model file, tiling)
    "min_cossim": 0.82,             # XFeat's matcher threshold (upstream's default)
    "ratio": 0.8,                   # Lowe's ratio test
    "sensed_features": 1500,        # strongest keypoints kept in the sensed image
    "reference_features": 15000,    # ... and in the reference tile
    "ransac_px": 3.0,               # RANSAC reprojection threshold
    "ransac_iters": 2000,
    "min_inliers": 6,               # fewer: no estimate
    # match filter: None = the kind's own (XFeat's matcher, else Lowe's ratio); "dapc" (the M2Det scene-matching
    # paper's adaptive distance test, seed 002) or "gms" (grid-based motion statistics, seed 004), both on
    # mutual nearest neighbours as those seeds match
    "filter": None,
}


class PointMatcher:
    """SIFT / ORB + ratio test + RANSAC affine against one reference image (estimator API)."""

    def __init__(self, config: dict | None = None):
        self.config = merge_settings(default_config, config, "point-matcher", open=("xfeat",))

    def _extract(self, image, n):
        return pf.extract(image, self.config["kind"], n_features=int(n), upright=False,
                          config={"xfeat": self.config["xfeat"]} if self.config["kind"] == "xfeat" else None)

    def fit(self, reference: np.ndarray) -> "PointMatcher":
        """Extract the reference's features (once per tile)."""
        self.reference_ = self._extract(reference, self.config["reference_features"])
        return self

    def locate(self, sensed: np.ndarray) -> AffineEstimate:
        """Where the sensed image's centre lies on the reference."""
        t0, c0 = time.perf_counter(), time.process_time()
        cfg = self.config
        feats = self._extract(sensed, cfg["sensed_features"])
        c1 = time.process_time()
        if cfg["filter"] in ("dapc", "gms"):
            m = pf.match(feats, self.reference_, filter=cfg["filter"], mutual=True)
        elif cfg["filter"] is not None:
            raise ValueError(f"point-matcher filter must be None, 'dapc' or 'gms', got {cfg['filter']!r}")
        elif cfg["kind"] == "xfeat":
            m = pf.match(feats, self.reference_, filter="cossim", mutual=True, min_cossim=float(cfg["min_cossim"]))
        else:
            m = pf.match(feats, self.reference_, filter="ratio", ratio=float(cfg["ratio"]))
        c2 = time.process_time()
        est = ransac_affine(feats.xy[m.query], self.reference_.xy[m.train],
                            sensed_centre(sensed.shape), float(cfg["ransac_px"]),
                            int(cfg["min_inliers"]), int(cfg["ransac_iters"]))
        est.seconds = time.perf_counter() - t0
        # what the seeds' measures read (matched pairs, putative match ratio, RPR ... RT)
        est.matched_pairs, est.keypoints = len(m), len(feats)
        est.point_data = {"sensed_xy": feats.xy, "tile_xy": self.reference_.xy, "query": m.query, "train": m.train,
                          "detect_seconds": c1 - c0, "match_seconds": c2 - c1}
        return est
