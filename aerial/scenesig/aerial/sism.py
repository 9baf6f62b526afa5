"""SISM -- single-image scene matching: the whole sensed image registered on the reference by NCC
(the baseline of Jin et al. 2016, §4.3), and the prepared reference image MRSM-CC shares.

SISM has no colour constancy and no rotation or scale compensation: the sensed image (gray) is
matched at ``coarse_scale`` over the whole reference by FFT NCC and the peak refined at full
resolution; the estimate is the reference position of the sensed image's centre.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from scenesig.aerial.ncc import ReferenceNCC, local_match, to_gray
from scenesig.aerial.trials import sensed_centre
from scenesig.signatures.colour import channel_histograms
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "ReferenceImage", "SISM", "SismResult"]

#: SISM settings.
default_config = {
    # whole-reference search resolution; quarter: chosen by ``scenesig aerial bench --choose-defaults`` on all
    # shared tiles (docs/aerial.md; 60 % against 55 % at half resolution)
    "coarse_scale": 0.25,
    "refine_radius_px": 3,      # full-resolution refinement around the coarse peak
}


class ReferenceImage:
    """A reference (BGR uint8) prepared for matching: gray at full, coarse and attitude-search
    resolution with FFT NCC on the two reduced ones, and its colour histogram (for EHM)."""

    def __init__(self, image: np.ndarray, coarse_scale: float, attitude_scale: float | None = None,
                 highpass_sigma: float = 0.0):
        self.image = image
        self.highpass_sigma = float(highpass_sigma)
        self.gray = self.to_gray(image)
        self.coarse_scale = float(coarse_scale)
        self.coarse = cv2.resize(self.gray, None, fx=coarse_scale, fy=coarse_scale,
                                 interpolation=cv2.INTER_AREA)
        self.ncc = ReferenceNCC(self.coarse)
        self.hist = channel_histograms(image)[:, 0]
        if attitude_scale is not None:
            self.attitude_scale = float(attitude_scale)
            self.small = cv2.resize(self.gray, None, fx=attitude_scale, fy=attitude_scale,
                                    interpolation=cv2.INTER_AREA)
            self.small_ncc = ReferenceNCC(self.small)

    def to_gray(self, image: np.ndarray) -> np.ndarray:
        """Gray image as matched: luminance, minus its Gaussian blur when ``highpass_sigma`` > 0."""
        g = to_gray(image)
        if self.highpass_sigma > 0:
            g = g - cv2.GaussianBlur(g, (0, 0), self.highpass_sigma)
        return g

    def prior_ncc(self, prior, tshape):
        """A ReferenceNCC on the coarse window around a rough prior ((x, y), radius) in full-res
        px, and the window's offset (coarse px)."""
        (px, py), r = prior
        f = self.coarse_scale
        H, W = self.coarse.shape
        x0 = int(np.clip((px - r) * f - tshape[1], 0, W - tshape[1]))
        y0 = int(np.clip((py - r) * f - tshape[0], 0, H - tshape[0]))
        x1 = int(np.clip((px + r) * f + tshape[1], x0 + tshape[1], W))
        y1 = int(np.clip((py + r) * f + tshape[0], y0 + tshape[0], H))
        return ReferenceNCC(self.coarse[y0:y1, x0:x1]), np.array([x0, y0], float)

    def sism(self, gray: np.ndarray, prior=None, refine_radius: int = 3) -> tuple[np.ndarray, float]:
        """Whole-image NCC: reference position of the image centre, and the peak NCC."""
        k = int(round(1 / self.coarse_scale))
        h, w = gray.shape
        hs, ws = h // k, w // k
        small = cv2.resize(gray[:hs * k, :ws * k], (ws, hs), interpolation=cv2.INTER_AREA)
        ncc, off = self.ncc, np.zeros(2)
        if prior is not None:
            ncc, off = self.prior_ncc(prior, small.shape)
        if small.shape[0] > ncc.shape[0] or small.shape[1] > ncc.shape[1]:
            return np.full(2, np.nan), -np.inf
        coarse = ncc.best(small)
        x, y, sc = local_match(self.gray, gray, (coarse[:2] + off) * k, int(refine_radius))
        return np.array([x, y]) + sensed_centre(gray.shape), sc


@dataclass
class SismResult:
    """SISM estimate: centre on the reference, peak NCC, seconds."""

    centre: np.ndarray
    score: float
    seconds: float


class SISM:
    """Single-image scene matching against one reference image (estimator API)."""

    def __init__(self, config: dict | None = None):
        self.config = merge_settings(default_config, config, "SISM")

    def fit(self, reference: np.ndarray) -> "SISM":
        self.reference_ = ReferenceImage(np.asarray(reference), float(self.config["coarse_scale"]))
        return self

    def locate(self, sensed: np.ndarray, prior=None) -> SismResult:
        """Centre of ``sensed`` (BGR or gray uint8) on the reference; ``prior`` = ((x, y), radius)."""
        t0 = time.perf_counter()
        centre, sc = self.reference_.sism(to_gray(sensed), prior,
                                          int(self.config["refine_radius_px"]))
        return SismResult(centre, sc, time.perf_counter() - t0)
