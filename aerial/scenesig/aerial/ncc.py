"""Normalised cross-correlation (NCC) against a reference image: global search by FFT, local by
direct correlation, both with sub-pixel peaks.

Jin et al. 2016 (§3.3, §4.3) register each landmark region, and SISM the whole sensed image, by NCC
(Zhao et al. 2006).  Searching a whole 1469 x 1274 tile with a template is the expensive part, so
the reference keeps what does not depend on the template:

* the spectrum of the (mean-removed) reference, so each template costs one forward and one inverse
  real FFT of the reference's size -- the cross-correlation ``sum_u t0(u) I(x + u)`` of a zero-mean
  template ``t0`` is ``irfft2(F_I * conj(F_t0))``;
* per template size, the windowed sums of ``I`` and ``I^2`` (integral images), which give every
  window's ``sum (I - mean_I)^2`` and hence the NCC denominator.

Windows of (nearly) constant reference -- where NCC is undefined -- score 0.
"""
from __future__ import annotations

import cv2
import numpy as np
import scipy.fft as sfft

__all__ = ["to_gray", "ReferenceNCC", "local_match", "subpixel_peak"]


def to_gray(image: np.ndarray) -> np.ndarray:
    """float32 luminance of a BGR or gray uint8 image."""
    a = np.asarray(image)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    return a.astype(np.float32)


def subpixel_peak(m: np.ndarray, r: int, c: int) -> tuple[float, float]:
    """Offset (dy, dx) of a parabola's vertex through the 3-point neighbourhoods of ``m[r, c]``."""
    def one(a, b, d):
        den = a - 2 * b + d
        return 0.0 if den >= 0 else float(np.clip(0.5 * (a - d) / den, -0.5, 0.5))
    dy = one(m[r - 1, c], m[r, c], m[r + 1, c]) if 0 < r < m.shape[0] - 1 else 0.0
    dx = one(m[r, c - 1], m[r, c], m[r, c + 1]) if 0 < c < m.shape[1] - 1 else 0.0
    return dy, dx


class ReferenceNCC:
    """A gray reference image prepared for FFT NCC search with many templates.

    Parameters
    ----------
    gray : ndarray, (H, W) float32
    min_std : float
        Reference windows whose standard deviation is below this (gray levels) score 0.
    """

    def __init__(self, gray: np.ndarray, min_std: float = 2.0):
        g = np.asarray(gray, dtype=np.float32)
        if g.ndim != 2:
            raise ValueError(f"reference must be a gray image, got shape {g.shape}")
        self.shape = g.shape
        self.min_std = float(min_std)
        self.fshape = (sfft.next_fast_len(g.shape[0], real=True),
                       sfft.next_fast_len(g.shape[1], real=True))
        self._g = g - np.float32(g.mean())
        self._spec = sfft.rfft2(self._g, s=self.fshape, workers=1)
        self._ii = cv2.integral2(self._g.astype(np.float64))
        self._den: dict = {}

    def _window_norm(self, th: int, tw: int) -> np.ndarray:
        """1 / sqrt(sum (I - mean)^2) of every th x tw window (valid positions); 0 where too flat."""
        key = (th, tw)
        if key not in self._den:
            s, sq = self._ii
            H, W = self.shape
            def box(ii):
                return ii[th:H + 1, tw:W + 1] - ii[:H - th + 1, tw:W + 1] \
                    - ii[th:H + 1, :W - tw + 1] + ii[:H - th + 1, :W - tw + 1]
            n = th * tw
            var = np.maximum(box(sq) - box(s) ** 2 / n, 0.0)
            flat = var < n * self.min_std ** 2
            inv = 1.0 / np.sqrt(np.where(flat, 1.0, var))
            inv[flat] = 0.0
            self._den[key] = inv.astype(np.float32)
        return self._den[key]

    def search(self, templates: np.ndarray) -> np.ndarray:
        """NCC maps of templates over every position where they fit.

        Parameters
        ----------
        templates : ndarray, (K, th, tw) or (th, tw)

        Returns
        -------
        ndarray, (K, H - th + 1, W - tw + 1) float32
            ``maps[k, y, x]`` is the NCC of template k with the window whose top-left is (x, y).
        """
        t = np.asarray(templates, dtype=np.float32)
        single = t.ndim == 2
        if single:
            t = t[None]
        K, th, tw = t.shape
        H, W = self.shape
        if th > H or tw > W:
            raise ValueError(f"template {tw}x{th} larger than the reference {W}x{H}")
        t0 = t - t.mean(axis=(1, 2), keepdims=True)
        tn = np.sqrt((t0.astype(np.float64) ** 2).sum(axis=(1, 2))).astype(np.float32)
        ft = sfft.rfft2(t0, s=self.fshape, axes=(1, 2), workers=1)
        corr = sfft.irfft2(self._spec[None] * np.conj(ft), s=self.fshape, axes=(1, 2), workers=1)
        out = corr[:, :H - th + 1, :W - tw + 1]
        out *= self._window_norm(th, tw)[None]
        scale = np.where(tn < np.sqrt(th * tw) * self.min_std, 0.0, 1.0 / np.maximum(tn, 1e-6))
        out *= scale.astype(np.float32)[:, None, None]
        return out[0] if single else out

    def best(self, templates: np.ndarray, top: int = 1, separation: int = 4) -> np.ndarray:
        """Sub-pixel top-left (x, y) and score of each template's NCC maxima.

        Returns (K, 3) for ``top == 1``, else (K, top, 3): the ``top`` highest peaks, each at least
        ``separation`` px from the higher ones (score -inf where there are fewer); without the
        leading K for a single 2-D template.
        """
        single = np.asarray(templates).ndim == 2
        maps = self.search(templates)
        if single:
            maps = maps[None]
        out = np.full((len(maps), top, 3), -np.inf)
        for k, m in enumerate(maps):
            work = m if top == 1 else m.copy()
            for j in range(top):
                r, c = np.unravel_index(int(np.argmax(work)), work.shape)
                if not np.isfinite(work[r, c]):
                    break
                dy, dx = subpixel_peak(m, r, c)
                out[k, j] = (c + dx, r + dy, m[r, c])
                if top > 1:
                    work[max(0, r - separation):r + separation + 1,
                         max(0, c - separation):c + separation + 1] = -np.inf
        out = out[:, 0] if top == 1 else out
        return out[0] if single else out


def local_match(reference: np.ndarray, template: np.ndarray, top_left_xy, radius: int):
    """Refine a template's position in ``reference`` within ``radius`` px of ``top_left_xy``.

    Parameters
    ----------
    reference : ndarray, (H, W) float32 gray
    template : ndarray, (th, tw) float32 gray
    top_left_xy : (x, y)
        Predicted top-left of the template in the reference.
    radius : int

    Returns
    -------
    (x, y, score)
        Sub-pixel top-left and NCC; score is ``-inf`` when the search window leaves the reference.
    """
    th, tw = template.shape
    H, W = reference.shape
    x0 = int(round(top_left_xy[0])) - radius
    y0 = int(round(top_left_xy[1])) - radius
    x1, y1 = x0 + tw + 2 * radius, y0 + th + 2 * radius
    x0c, y0c, x1c, y1c = max(0, x0), max(0, y0), min(W, x1), min(H, y1)
    if x1c - x0c < tw or y1c - y0c < th:
        return float("nan"), float("nan"), -np.inf
    m = cv2.matchTemplate(reference[y0c:y1c, x0c:x1c], template, cv2.TM_CCOEFF_NORMED)
    m = np.nan_to_num(m, nan=-1.0, posinf=-1.0, neginf=-1.0)
    r, c = np.unravel_index(int(np.argmax(m)), m.shape)
    dy, dx = subpixel_peak(m, r, c)
    return x0c + c + dx, y0c + r + dy, float(m[r, c])
