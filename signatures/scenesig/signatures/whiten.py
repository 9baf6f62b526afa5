"""Whitened HOG: discriminative decorrelation with a generic background (Hariharan, Malik & Ramanan,
"Discriminative decorrelation for clustering and classification", ECCV 2012).

HOG cells are far from independent: neighbouring cells share gradients through the spatial
interpolation and the block normalisation, and the 31 features of one cell are strongly correlated
(the 9 contrast-insensitive bins are sums of the 18 sensitive ones).  A linear filter trained on raw
HOG from few positives spends its weights on that generic structure -- the strong edges any image
has -- and fires on whatever has similar edges after a change of light.  Hariharan et al. estimate
the mean ``mu`` and the spatial auto-covariance ``Gamma(d) = E[(x(p) - mu)(x(p + d) - mu)^T]`` of HOG
cells **once**, from generic natural images, and either train LDA filters ``Sigma^-1 (mu_pos - mu)``
or, equivalently for a linear classifier, describe windows by whitened features
``Sigma^-1/2 (x - mu)``: what is left is what makes *this* patch unlike images in general.

Here the whitening is local and stationary: the whitened cell ``p`` is ``sum_d H(d) (x(p + d) - mu)``
over ``|d| <= radius`` cells (``H``: the central cell's block row of ``Sigma^-1/2`` of a
``(2 radius + 1)``-square patch whose covariance is assembled from ``Gamma`` plus a ridge
``reg * mean variance``).  Mining runs on whitened pyramid levels (:func:`whiten_pyramid`); a
whitened filter ``w`` (fh x fw cells) is then **folded** into an ordinary filter on raw HOG of
``(fh + 2 radius) x (fw + 2 radius)`` cells, centred where ``w`` was, and a bias
(:func:`fold_filter`), so banks, maps and the detector are unchanged.

The background statistics (``data/hog_background.npz``, a few hundred kB) were estimated from the
KITTI raw snippet's two colour cameras (``../shared/data/kitti``; none of the benchmark data sets)
by::

    python -m scenesig.signatures.whiten ../shared/data/kitti/2011_09_26_snippet --out signatures/scenesig/signatures/data/hog_background.npz
"""
from __future__ import annotations

import argparse
import functools
from pathlib import Path

import numpy as np

from scenesig.signatures import hog as hogmod
from scenesig.surveys.settings import merge_settings

__all__ = ["BACKGROUND_FILE", "estimate_background", "load_background", "whitening_kernel",
           "whiten_level", "whiten_pyramid", "fold_filter", "main"]

#: The packaged background statistics.
BACKGROUND_FILE = Path(__file__).with_name("data") / "hog_background.npz"

#: Largest cell offset whose covariance the statistics file holds (whitening radius <= half of it).
MAX_OFFSET = 4

D = hogmod.FEATURE_DIM


# ---------------------------------------------------------------------------------- statistics


def estimate_background(images, levels=range(0, 9), hog_config: dict | None = None,
                        max_offset: int = MAX_OFFSET) -> dict:
    """Mean and spatial auto-covariance of HOG cells over ``images`` (all pyramid ``levels``).

    Returns
    -------
    dict
        ``mean`` (31,), ``gamma`` (2 m + 1, 2 m + 1, 31, 31) with ``gamma[m + dy, m + dx] =
        E[(x(r, c) - mu)(x(r + dy, c + dx) - mu)^T]``, ``cells`` (number of cells averaged) and the
        HOG parameters.
    """
    cfg = merge_settings(hogmod.default_config, hog_config, "HOG")
    m = int(max_offset)
    feats = []
    for img in images:
        pyr = hogmod.build_pyramid(img, cfg, levels=list(levels))
        feats += [f.astype(np.float64) for f in pyr.levels.values() if min(f.shape[:2]) > 2 * m + 2]
    if not feats:
        raise ValueError("no image gave a HOG level larger than the covariance support")
    n = sum(f.shape[0] * f.shape[1] for f in feats)
    mu = sum(f.sum(axis=(0, 1)) for f in feats) / n
    gamma = np.zeros((2 * m + 1, 2 * m + 1, D, D))
    count = np.zeros((2 * m + 1, 2 * m + 1))
    for f in feats:
        z = f - mu
        h, w = z.shape[:2]
        for dy in range(-m, m + 1):
            for dx in range(-m, m + 1):
                a = z[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)].reshape(-1, D)
                b = z[max(0, dy):h + min(0, dy), max(0, dx):w + min(0, dx)].reshape(-1, D)
                gamma[m + dy, m + dx] += a.T @ b
                count[m + dy, m + dx] += len(a)
    gamma /= count[:, :, None, None]
    # Stationarity: Gamma(-d) = Gamma(d)^T exactly (the estimates differ only by border cells).
    gamma = 0.5 * (gamma + np.transpose(gamma[::-1, ::-1], (0, 1, 3, 2)))
    return {"mean": mu.astype(np.float32), "gamma": gamma.astype(np.float32), "cells": int(n),
            "hog_cell": int(cfg["cell"]), "hog_clip": float(cfg["clip"]),
            "hog_color": bool(cfg["color"])}


@functools.lru_cache(maxsize=4)
def load_background(path: str | None = None) -> dict:
    """The background statistics (default: the packaged :data:`BACKGROUND_FILE`)."""
    from scenesig.surveys.errors import DataError

    p = Path(path) if path else BACKGROUND_FILE
    try:
        with np.load(p) as z:
            out = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise DataError(p, f"cannot read the HOG background statistics: {exc}") from None
    if out.get("mean", np.zeros(0)).shape != (D,) or out["gamma"].shape[2:] != (D, D):
        raise DataError(p, "not HOG background statistics (mean (31,), gamma (., ., 31, 31))")
    return out


@functools.lru_cache(maxsize=8)
def whitening_kernel(radius: int = 1, reg: float = 0.1, path: str | None = None) -> np.ndarray:
    """Whitening kernel ``H`` (2 radius + 1, 2 radius + 1, 31, 31): whitened cell p =
    ``sum_d H[radius + dy, radius + dx] @ (x(p + d) - mu)``.

    ``H`` is the central cell's block row of ``(Sigma + reg * mean(diag Sigma) I)^-1/2``, with
    ``Sigma`` the covariance of a (2 radius + 1)-square patch assembled from the background's
    ``Gamma``.
    """
    bg = load_background(path)
    gamma = bg["gamma"].astype(np.float64)
    m = gamma.shape[0] // 2
    r = int(radius)
    if r < 0 or 2 * r > m:
        # the patch's covariance needs Gamma up to offsets of 2 * radius
        raise ValueError(f"whitening radius must be in 0..{m // 2}, got {radius}")
    s = 2 * r + 1
    idx = [(y, x) for y in range(s) for x in range(s)]
    sigma = np.empty((s * s * D, s * s * D))
    for a, (ya, xa) in enumerate(idx):
        for b, (yb, xb) in enumerate(idx):
            sigma[a * D:(a + 1) * D, b * D:(b + 1) * D] = gamma[m + yb - ya, m + xb - xa]
    sigma = 0.5 * (sigma + sigma.T)
    sigma += float(reg) * np.mean(np.diag(sigma)) * np.eye(len(sigma))
    vals, vecs = np.linalg.eigh(sigma)
    inv_sqrt = (vecs / np.sqrt(np.maximum(vals, 1e-12))) @ vecs.T
    centre = (s * s) // 2
    row = inv_sqrt[centre * D:(centre + 1) * D]            # (31, s*s*31)
    # Keep the raw features' overall scale (mean variance), so the SVM's C means what it did.
    row *= np.sqrt(np.mean(np.diag(gamma[m, m])))
    H = row.reshape(D, s, s, D).transpose(1, 2, 0, 3)      # (s, s, out, in)
    return np.ascontiguousarray(H, dtype=np.float32)


# ---------------------------------------------------------------------------------- applying


def whiten_level(feat: np.ndarray, radius: int = 1, reg: float = 0.1, path: str | None = None,
                 valid=None) -> tuple[np.ndarray, tuple | None]:
    """Whitened features of one HOG level (Hc, Wc, 31).

    Outside the level the features count as the background mean (they whiten to zero).  With
    ``valid`` (the cell box ``(r0, r1, c0, c1)`` where a partly computed level is exact) the result
    is exact in that box shrunk by ``radius`` (except where it touches the level's border), which is
    returned as the new valid box.
    """
    H = whitening_kernel(radius, reg, path)
    mu = load_background(path)["mean"]
    r = int(radius)
    s = 2 * r + 1
    hc, wc = feat.shape[:2]
    z = np.zeros((hc + 2 * r, wc + 2 * r, D), np.float32)
    z[r:r + hc, r:r + wc] = feat - mu
    t0, t1, t2 = z.strides
    patches = np.lib.stride_tricks.as_strided(z, (hc, wc, s, s, D), (t0, t1, t0, t1, t2))
    out = np.tensordot(patches, H, axes=([2, 3, 4], [0, 1, 3])).astype(np.float32)
    if valid is not None:
        r0, r1, c0, c1 = valid
        valid = (r0 + r if r0 > 0 else 0, r1 - r if r1 < hc else hc,
                 c0 + r if c0 > 0 else 0, c1 - r if c1 < wc else wc)
    return out, valid


def whiten_pyramid(pyr: hogmod.HogPyramid, radius: int = 1, reg: float = 0.1,
                   path: str | None = None) -> hogmod.HogPyramid:
    """A copy of ``pyr`` with every level whitened (:func:`whiten_level`)."""
    if pyr.config.get("features", "hog") != "hog":
        raise ValueError(f"the background statistics are of HOG cells; this pyramid holds "
                         f"{pyr.config['features']} cells")
    levels, regions = {}, {}
    for k, f in pyr.levels.items():
        levels[k], v = whiten_level(f, radius, reg, path, pyr.regions.get(k))
        if v is not None:
            regions[k] = v
    return hogmod.HogPyramid(levels, pyr.image_size, dict(pyr.config), dict(pyr.sizes), regions)


def fold_filter(weights: np.ndarray, bias: float, radius: int = 1, reg: float = 0.1,
                path: str | None = None) -> tuple[np.ndarray, float]:
    """An equivalent raw-HOG filter of a filter trained on whitened features.

    ``w . whiten(x)`` over a fh x fw window equals ``W . x + (bias shift)`` over the window grown by
    ``radius`` cells on every side, ``W(q) = sum_d H(d)^T w(q - d)``: the returned ``(W, b)`` score a
    raw window exactly as ``(weights, bias)`` score the whitened one (away from the level border, where
    whitening pads with the mean).  The grown window has the same centre.
    """
    H = whitening_kernel(radius, reg, path)
    mu = load_background(path)["mean"].astype(np.float64)
    r = int(radius)
    fh, fw = weights.shape[:2]
    W = np.zeros((fh + 2 * r, fw + 2 * r, D))
    w = weights.astype(np.float64)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            # cell (a, b) of w reads x at (a + dy, b + dx): grown-window cell (a + dy + r, b + dx + r)
            W[r + dy:r + dy + fh, r + dx:r + dx + fw] += w @ H[r + dy, r + dx].astype(np.float64)
    b = float(bias) - float(np.tensordot(W, mu, axes=([2], [0])).sum())
    return W.astype(np.float32), b


# ---------------------------------------------------------------------------------- command


def main(argv=None) -> int:
    """``python -m scenesig.signatures.whiten KITTI_DRIVE --out FILE``: re-estimate the background statistics."""
    import cv2

    from scenesig.surveys.io import atomic_path

    ap = argparse.ArgumentParser(prog="python -m scenesig.signatures.whiten", description=main.__doc__)
    ap.add_argument("drive", help="a KITTI raw drive folder (image_02/data, image_03/data)")
    ap.add_argument("--out", default=str(BACKGROUND_FILE))
    ap.add_argument("--every", type=int, default=3, help="every N-th frame of each camera")
    args = ap.parse_args(argv)
    files = []
    for cam in ("image_02", "image_03"):
        files += sorted((Path(args.drive) / cam / "data").glob("*.*"))[::max(1, args.every)]
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    images = [im for im in images if im is not None]
    if not images:
        raise SystemExit(f"no image under {args.drive}/image_0[23]/data")
    stats = estimate_background(images)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, images=np.array(len(images)), **stats)
    print(f"{out}: {len(images)} images, {stats['cells']} cells")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
