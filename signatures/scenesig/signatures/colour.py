"""Colour constancy by exact histogram matching (EHM), globally or on local windows.

Exact histogram matching (Morovic, Shaw and Sun, "A fast, non-iterative and exact histogram
matching algorithm", Pattern Recognition Letters 23, 2002) gives an image *exactly* a target
histogram: the pixels are put in a strict order and the k-th pixel gets the k-th value of the
sorted target population.  Per channel, that is the look-up-table construction Jin et al. describe
("A multi-region scene matching based localisation system for UAVs", J. Navigation 2016, §3.1):
walking both histograms in ascending bin order and moving ``min(N_rem, N_req)`` pixels from
source bin m to target bin n.  Pixels that share a source value must still be split between
target bins when the target needs it; which ones move is decided here by the 3x3 local mean of the
channel (Coltuc et al.'s strict-ordering idea), so smooth regions stay smooth and the result is
deterministic.

Jin et al. apply EHM *locally*: the sensed image is cut into a 5 x 5 grid of non-overlapping
windows, each window's reference is the matching sub-image of the geo-referenced image (found with
the current estimate of position, scale and rotation), and each window's histogram -- per R, G, B
channel -- is transferred exactly to its reference window's, rescaled to the window's pixel count
(their eq. 2).  The aerial localiser (:mod:`scenesig.aerial.mrsmcc`) iterates this with its pose estimate;
the scene-signature side can use the same functions for single-image robustness.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["target_counts", "channel_histograms", "match_histograms", "exact_histogram_match",
           "local_exact_histogram_match", "grid_edges"]


def target_counts(hist: np.ndarray, n: int) -> np.ndarray:
    """A histogram rescaled to ``n`` pixels in whole counts (Jin et al. 2016, eq. 2).

    ``H_N = H * n / sum(H)``, made integral by rounding the *cumulative* histogram, so the counts
    sum to ``n`` exactly and no bin is off by more than one pixel.

    Parameters
    ----------
    hist : ndarray, shape (..., bins)
        Non-negative counts (or weights) per bin; the last axis is the histogram.
    n : int or ndarray broadcastable to ``hist.shape[:-1] + (1,)``
        Pixel count(s) the result must total.

    Returns
    -------
    ndarray of int64, same shape as ``hist``
    """
    h = np.asarray(hist, dtype=np.float64)
    total = h.sum(axis=-1, keepdims=True)
    if np.any(total <= 0):
        raise ValueError("a target histogram is empty")
    n = np.broadcast_to(np.asarray(n, dtype=np.int64), total.shape)
    cum = np.rint(np.cumsum(h, axis=-1) * (n / total)).astype(np.int64)
    cum[..., -1] = n[..., 0]
    return np.diff(cum, axis=-1, prepend=0)


def _channels(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"exact histogram matching needs uint8 images, got {a.dtype}")
    if a.ndim == 2:
        return a[:, :, None]
    if a.ndim != 3:
        raise ValueError(f"expected a gray or colour image, got shape {a.shape}")
    return a


def _order_keys(img: np.ndarray) -> np.ndarray:
    """Strict-order keys per channel: the value, ties broken by the 3x3 local mean.

    uint16 keys (value * 256 + rounded local mean) let numpy's stable argsort use a radix sort.
    """
    local = cv2.blur(img, (3, 3), borderType=cv2.BORDER_REFLECT)
    if local.ndim == 2:
        local = local[:, :, None]
    return (img.astype(np.uint16) << 8) | local.astype(np.uint16)


def _match_windows(src: np.ndarray, window: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Give every window of ``src`` its target counts exactly.

    src : (H, W, C) uint8; window : (H, W) uint8 window index of each pixel; counts : (C, n, 256)
    integer target counts, each window's summing to its pixel count.  Pixels are ordered by
    (window, key) with two stable radix sorts (16-bit key, then 8-bit window), and the sorted
    population of the targets -- window by window, value by value -- is laid onto them.
    """
    h, w, c = src.shape
    keys = _order_keys(src).reshape(-1, c)
    wid = window.ravel()
    n = counts.shape[1]
    values = np.tile(np.arange(256, dtype=np.uint8), n)
    out = np.empty((h * w, c), np.uint8)
    for ch in range(c):
        o = np.argsort(keys[:, ch], kind="stable")
        o = o[np.argsort(wid[o], kind="stable")]
        out[o, ch] = np.repeat(values, counts[ch].ravel())
    return out.reshape(h, w, c)


def channel_histograms(image: np.ndarray, mask: np.ndarray | None = None,
                       window: np.ndarray | None = None, n_windows: int = 1) -> np.ndarray:
    """Per-channel 256-bin histograms, (C, n_windows, 256), of the (masked) pixels of each window.

    Computing a large reference's histogram once and passing it to :func:`match_histograms` saves
    the cost on every call.
    """
    a = _channels(image)
    c = a.shape[2]
    pix = a.reshape(-1, c).astype(np.int64)
    wid = np.zeros(len(pix), np.int64) if window is None else np.asarray(window).ravel().astype(np.int64)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != a.shape[:2]:
            raise ValueError(f"mask is {m.shape}, image {a.shape[:2]}")
        pix, wid = pix[m.ravel()], wid[m.ravel()]
    return np.stack([np.bincount(wid * 256 + pix[:, ch], minlength=n_windows * 256)
                     .reshape(n_windows, 256) for ch in range(c)])


def match_histograms(source: np.ndarray, hist: np.ndarray) -> np.ndarray:
    """Give ``source`` the per-channel histograms ``hist`` (C, 256) exactly (rescaled by eq. 2)."""
    src = _channels(source)
    hist = np.asarray(hist).reshape(src.shape[2], 1, -1)
    if hist.shape[2] != 256:
        raise ValueError(f"expected 256-bin histograms, got shape {hist.shape}")
    n = src.shape[0] * src.shape[1]
    out = _match_windows(src, np.zeros(src.shape[:2], np.uint8), target_counts(hist, n))
    return out.reshape(np.asarray(source).shape)


def exact_histogram_match(source: np.ndarray, reference: np.ndarray,
                          reference_mask: np.ndarray | None = None) -> np.ndarray:
    """Give ``source`` the histogram of ``reference``, exactly, per channel.

    Parameters
    ----------
    source : ndarray, (H, W) or (H, W, C) uint8
        Image whose colours are changed.
    reference : ndarray, (H', W') or (H', W', C) uint8
        Image whose histogram is the target (any size; its histogram is rescaled to the source's
        pixel count by eq. 2, so with equal sizes the result's histogram *is* the reference's).
    reference_mask : ndarray of bool, (H', W'), optional
        Only these reference pixels count (e.g. the part of a warped reference inside the map).

    Returns
    -------
    ndarray, same shape and dtype as ``source``
    """
    src, ref = _channels(source), _channels(reference)
    if src.shape[2] != ref.shape[2]:
        raise ValueError(f"source has {src.shape[2]} channels, reference {ref.shape[2]}")
    return match_histograms(source, channel_histograms(ref, reference_mask)[:, 0])


def grid_edges(length: int, parts: int) -> np.ndarray:
    """Edges of ``parts`` near-equal, non-overlapping intervals covering ``range(length)``."""
    if parts < 1 or parts > length:
        raise ValueError(f"cannot split {length} pixels into {parts} windows")
    return np.rint(np.linspace(0, length, parts + 1)).astype(int)


def local_exact_histogram_match(source: np.ndarray, reference: np.ndarray,
                                grid: tuple[int, int] = (5, 5),
                                reference_mask: np.ndarray | None = None,
                                min_reference_fraction: float = 0.25) -> np.ndarray:
    """Local EHM: each window of a ``grid`` gets the histogram of the same window of ``reference``.

    This is the colour-constancy step of Jin et al. 2016, §3.1: ``reference`` is the reference
    sub-image already brought into the source's frame (shift, scale and rotation compensated), so
    window i of the source and window i of the reference show the same ground.

    Parameters
    ----------
    source : ndarray, (H, W) or (H, W, C) uint8
    reference : ndarray, same height and width as ``source``
    grid : (rows, cols)
        Windows per side (the paper: 5 x 5; at most 255 windows).
    reference_mask : ndarray of bool, (H, W), optional
        Valid reference pixels (a warped reference may leave the map).  A window whose reference
        has fewer than ``min_reference_fraction`` valid pixels keeps its colours.
    min_reference_fraction : float

    Returns
    -------
    ndarray, same shape and dtype as ``source``
    """
    src, ref = _channels(source), _channels(reference)
    if src.shape != ref.shape:
        raise ValueError(f"local EHM needs the reference in the source's frame: source "
                         f"{src.shape}, reference {ref.shape}")
    gy, gx = int(grid[0]), int(grid[1])
    if gy * gx > 255:
        raise ValueError(f"at most 255 windows, got a {gy} x {gx} grid")
    ys, xs = grid_edges(src.shape[0], gy), grid_edges(src.shape[1], gx)
    row = np.searchsorted(ys, np.arange(src.shape[0]), side="right") - 1
    col = np.searchsorted(xs, np.arange(src.shape[1]), side="right") - 1
    window = (row[:, None] * gx + col[None, :]).astype(np.uint8)
    n = gy * gx
    size = np.bincount(window.ravel(), minlength=n)
    hist = channel_histograms(ref, reference_mask, window, n).astype(np.float64)
    own = channel_histograms(src, None, window, n)
    # Windows with too little valid reference keep their own histogram (i.e. their colours).
    keep = hist[0].sum(axis=1) < min_reference_fraction * size
    hist[:, keep] = own[:, keep]
    counts = target_counts(hist, size[None, :, None])
    return _match_windows(src, window, counts).reshape(np.asarray(source).shape)
