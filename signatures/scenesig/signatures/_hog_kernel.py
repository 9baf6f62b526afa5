"""Compiled loops of :func:`scenesig.signatures.hog.fhog` (numba), bit for bit the numpy code's.

The numpy version (:func:`scenesig.signatures.hog._cell_histograms_numpy` and the block normalisation in
:func:`scenesig.signatures.hog.fhog`) makes about thirty passes over a level's pixels and cells -- scaling,
clipping, flooring, two weighted ``np.bincount``, the 1-3-3-1 spatial taps, four normalisations --
each a separate array and, for a tracking detector's small regions, a separate trip through the
interpreter.  Here one loop does the votes, one the taps and one the normalisation, with the same
arithmetic in the same order:

* the orientation vote in float32: ``b = min(ang * 18/360, 18 - 1e-3)``, ``b0 = floor(b)``,
  ``w1 = (b - b0) * mag`` to the upper bin and ``mag - w1`` to the lower one;
* the two ``np.bincount`` sums kept apart in float64, each accumulated in pixel order as
  ``np.bincount`` does, and added afterwards (``sub = lower + upper``), then bin 18 folded onto 0;
* the taps in float32, ``((0.25 a + 0.75 b) + 0.75 c) + 0.25 d``, each product and sum rounded as
  numpy rounds them (no fused multiply-add: numba leaves ``fastmath`` off);
* the normalisation in float32: the four block energies summed as numpy sums its shifted grids,
  the four clipped normalisations summed in order, the texture sums of 18 values in numpy's
  pairwise order.  The cells' squared norms stay ``np.einsum``'s (its float32 sum order is
  numpy's own, SIMD-dependent), computed by the caller.

So every feature, map and detection is unchanged (``tests/test_signatures_hog.py`` compares the two
on random, synthetic and rendered images, gray and colour).  Without numba, or with the environment
variable ``SCENESIG_NUMPY_HOG=1``, :mod:`scenesig.signatures.hog` runs the numpy code.
"""
from __future__ import annotations

import numpy as np

from scenesig.surveys.compiled import AVAILABLE, lazy_njit

__all__ = ["AVAILABLE", "cell_histograms", "normalise", "warm_up"]

_N_BINS = 18
_SCALE = np.float32(_N_BINS / 360.0)
_TOP = np.float32(_N_BINS - 1e-3)
_Q1 = np.float32(0.25)
_Q3 = np.float32(0.75)


def _cell_histograms(mag, ang, hc, wc, cell):
    half = cell // 2
    h, w = hc * cell, wc * cell
    H2, W2 = 2 * hc, 2 * wc
    slots = _N_BINS + 1
    # acc[slot, 0]: the lower-bin votes, acc[slot, 1]: the upper-bin votes (np.bincount's two sums).
    acc = np.zeros((H2 * W2 * slots, 2), np.float64)
    col = np.empty(w, np.intp)
    for c in range(w):
        col[c] = (c // half) * slots
    for r in range(h):
        rp = (r // half) * (W2 * slots)
        for c in range(w):
            b = ang[r, c] * _SCALE
            if b > _TOP:
                b = _TOP
            b0 = int(b)
            m = mag[r, c]
            w1 = (b - np.float32(b0)) * m
            m = m - w1
            i = rp + col[c] + b0
            acc[i, 0] += np.float64(m)
            acc[i + 1, 1] += np.float64(w1)
    # sub = lower + upper, bin 18 folded onto 0, then float32 -- padded with a zero row above and below.
    pad = np.zeros((H2 + 2, W2, _N_BINS), np.float32)
    for y in range(H2):
        for x in range(W2):
            base = (y * W2 + x) * slots
            s18 = acc[base + _N_BINS, 0] + acc[base + _N_BINS, 1]
            pad[y + 1, x, 0] = np.float32((acc[base, 0] + acc[base, 1]) + s18)
            for k in range(1, _N_BINS):
                pad[y + 1, x, k] = np.float32(acc[base + k, 0] + acc[base + k, 1])
    # Rows: cell row i takes half-cell rows 2i-1 .. 2i+2 (pad rows 2i .. 2i+3).
    pad2 = np.zeros((hc, W2 + 2, _N_BINS), np.float32)
    for i in range(hc):
        for x in range(W2):
            for k in range(_N_BINS):
                v = pad[2 * i, x, k] * _Q1
                v = v + pad[2 * i + 1, x, k] * _Q3
                v = v + pad[2 * i + 2, x, k] * _Q3
                v = v + pad[2 * i + 3, x, k] * _Q1
                pad2[i, x + 1, k] = v
    out = np.empty((hc, wc, _N_BINS), np.float32)
    for i in range(hc):
        for j in range(wc):
            for k in range(_N_BINS):
                v = pad2[i, 2 * j, k] * _Q1
                v = v + pad2[i, 2 * j + 1, k] * _Q3
                v = v + pad2[i, 2 * j + 2, k] * _Q3
                v = v + pad2[i, 2 * j + 3, k] * _Q1
                out[i, j, k] = v
    return out


def _normalise(hist, insens, energy, clip, eps):
    hc, wc = energy.shape
    out = np.empty((hc, wc, 31), np.float32)
    half = np.float32(0.5)
    tex = np.float32(0.2357)
    inv = np.empty(4, np.float32)
    for i in range(hc):
        i0, i1, i2 = max(i - 1, 0), i, min(i + 1, hc - 1)
        for j in range(wc):
            j0, j1, j2 = max(j - 1, 0), j, min(j + 1, wc - 1)
            # The four 2x2 blocks around the cell (top-left, top-right, bottom-left, bottom-right),
            # each summed as numpy sums its shifted grids, ((a + b) + c) + d.
            inv[0] = energy[i0, j0] + energy[i1, j0] + energy[i0, j1] + energy[i1, j1]
            inv[1] = energy[i0, j1] + energy[i1, j1] + energy[i0, j2] + energy[i1, j2]
            inv[2] = energy[i1, j0] + energy[i2, j0] + energy[i1, j1] + energy[i2, j1]
            inv[3] = energy[i1, j1] + energy[i2, j1] + energy[i1, j2] + energy[i2, j2]
            for a in range(4):
                inv[a] = np.float32(1.0) / np.sqrt(inv[a] + eps)
            for k in range(_N_BINS):
                v = hist[i, j, k]
                s = min(v * inv[0], clip)
                s = s + min(v * inv[1], clip)
                s = s + min(v * inv[2], clip)
                s = s + min(v * inv[3], clip)
                out[i, j, k] = s * half
            for k in range(9):
                v = insens[i, j, k]
                s = min(v * inv[0], clip)
                s = s + min(v * inv[1], clip)
                s = s + min(v * inv[2], clip)
                s = s + min(v * inv[3], clip)
                out[i, j, 18 + k] = s * half
            # Texture: the 18 clipped sensitive values under each block, summed in numpy's
            # pairwise order for 18 terms (eight running sums of two, a tree, then the last two).
            for a in range(4):
                g = inv[a]
                r0 = min(hist[i, j, 0] * g, clip) + min(hist[i, j, 8] * g, clip)
                r1 = min(hist[i, j, 1] * g, clip) + min(hist[i, j, 9] * g, clip)
                r2 = min(hist[i, j, 2] * g, clip) + min(hist[i, j, 10] * g, clip)
                r3 = min(hist[i, j, 3] * g, clip) + min(hist[i, j, 11] * g, clip)
                r4 = min(hist[i, j, 4] * g, clip) + min(hist[i, j, 12] * g, clip)
                r5 = min(hist[i, j, 5] * g, clip) + min(hist[i, j, 13] * g, clip)
                r6 = min(hist[i, j, 6] * g, clip) + min(hist[i, j, 14] * g, clip)
                r7 = min(hist[i, j, 7] * g, clip) + min(hist[i, j, 15] * g, clip)
                s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
                s = s + min(hist[i, j, 16] * g, clip)
                s = s + min(hist[i, j, 17] * g, clip)
                out[i, j, 27 + a] = s * tex
    return out


_CELL_HISTOGRAMS = lazy_njit(_cell_histograms)
_NORMALISE = lazy_njit(_normalise)


def normalise(hist: np.ndarray, insens: np.ndarray, energy: np.ndarray, clip: float, eps: float) -> np.ndarray:
    """(hc, wc, 31) FHOG features from the (hc, wc, 18) histograms, their (hc, wc, 9) contrast-insensitive
    sums and those sums' squared norms ``energy`` (computed by the caller with ``np.einsum``, whose
    float32 sum order is numpy's own): the block normalisation of :func:`scenesig.signatures.hog.fhog`, in the
    same float32 operations and order."""
    return _NORMALISE(np.ascontiguousarray(hist, np.float32), np.ascontiguousarray(insens, np.float32),
                      np.ascontiguousarray(energy, np.float32), np.float32(clip), np.float32(eps))


def cell_histograms(mag: np.ndarray, ang: np.ndarray, hc: int, wc: int, cell: int) -> np.ndarray:
    """(hc, wc, 18) float32 histograms from float32 gradient magnitude and angle (degrees) of an
    (hc*cell, wc*cell) image -- the compiled loops (numba required: check :data:`AVAILABLE`)."""
    return _CELL_HISTOGRAMS(np.ascontiguousarray(mag, np.float32), np.ascontiguousarray(ang, np.float32),
                            int(hc), int(wc), int(cell))


def warm_up() -> None:
    """Load the compiled loops now (about half a second from numba's cache, several seconds the
    first time): a replay calls it before its clock starts, as it opens the map."""
    if AVAILABLE:
        z = np.zeros((8, 8), np.float32)
        h = cell_histograms(z, z, 1, 1, 8)
        normalise(h, h[:, :, :9], np.zeros((1, 1), np.float32), 0.2, 1e-4)
