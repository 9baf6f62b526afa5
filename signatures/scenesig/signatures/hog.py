"""HOG feature pyramid: FHOG-style 31-d cells, computed once per image and shared by a whole bank.

Every classifier of a place (and the mining of all 296 candidate shapes) reads from the same
pyramid, so the pyramid is the only per-image cost that scales with resolution; it is written for
speed: gradients with OpenCV, orientation and spatial binning and block normalisation in compiled
loops (:mod:`scenesig.signatures._hog_kernel`, numba), which give bit for bit the features of the numpy
code kept beside them (two weighted ``np.bincount`` passes, normalisation vectorised over the
cell grid; used without numba).

Features per 8x8-pixel cell (Felzenszwalb et al., PAMI 2010, "FHOG"):

* 18 contrast-sensitive orientation bins (0..360 deg),
* 9 contrast-insensitive bins (0..180 deg),
* 4 texture features (gradient energy under each of the four 2x2-block normalisations),

each orientation vote split linearly between its two nearest bins and spatially (bilinearly) between
the four nearest cells, then normalised by the four 2x2 blocks the cell belongs to and clipped at
0.2.  Cell ``(r, c)`` covers pixels ``[8r, 8r + 8) x [8c, 8c + 8)`` of its level (no border is
dropped; blocks at the edge reuse the edge cell's energy).

Other cell descriptors (the ``features`` setting; :func:`describe_cells`): XFeat's learned dense
descriptors, whose 1/8-resolution map gives one 64-d descriptor per 8-pixel cell, alone or stacked after
FHOG.  Everything downstream -- pyramid, shapes, filters, detection -- reads cells of any length
(``docs/learned_cells.md``).

Pyramid levels are indexed by an integer ``k`` with scale ``2 ** (-k / scales_per_octave)``: ``k = 0``
is the input resolution, ``k = scales_per_octave`` half of it.  A classifier stores its nominal
``k`` and searches ``k - 1 .. k + 1``, so levels are exact and shared by all classifiers.

A detector that only searches windows needs a fraction of each level: :func:`build_pyramid` with
``regions`` resizes (:func:`resize_area_region`, OpenCV's area decimation restricted to the region)
and describes only a cell box per level plus :data:`REGION_MARGIN_CELLS`, and those cells are bit for
bit the whole level's.  Levels are independent: :func:`build_pyramid` (and the bank's detection)
can compute them on several threads (:func:`thread_map`) with the same result.

``scenesig bench hog [IMAGE]`` times one level and a pyramid.
"""
from __future__ import annotations

import contextlib
import contextvars
import os
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from scenesig.signatures import _hog_kernel
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "FEATURE_DIM", "FEATURE_KINDS", "feature_dim", "learned", "describe_cells", "fhog",
           "HogPyramid", "build_pyramid", "level_scale",
           "level_size", "window_cell", "resize_area_region", "to_gray_float", "REGION_MARGIN_CELLS",
           "level_plan", "build_level", "assemble_pyramid", "thread_map", "set_parallel_section", "ScaledImages", "load_compiled"]

#: HOG parameters.  Every classifier stores the values it was trained with; detection refuses a
#: pyramid built with different ones.
default_config = {
    "cell": 8,                 # pixels per cell side
    "scales_per_octave": 4,    # pyramid density: neighbouring levels differ by 2**(1/4) = 19 %
    "clip": 0.2,               # FHOG truncation of normalised bin values
    "color": False,            # True: per pixel, gradient of the colour channel with the largest
                               # magnitude (FHOG); False: gradient of the gray image (2x faster)
    # What describes a cell (see describe_cells): "hog" (FHOG, the paper's), "xfeat" (XFeat's
    # dense 64-d descriptors, unit length per cell) or "hog+xfeat" (both, stacked).  Mining's
    # ``features`` setting sets it; every classifier stores it, so detection describes alike.
    "features": "hog",
    "xfeat_weight": 1.0,       # hog+xfeat: length of the XFeat part of a cell (the HOG part as FHOG)
}

#: The cell descriptors :func:`describe_cells` knows.
FEATURE_KINDS = ("hog", "xfeat", "hog+xfeat")

#: Length of an XFeat dense descriptor (the network's 64-channel map at 1/8 resolution).
XFEAT_DIM = 64

#: Length of a cell's feature vector.
FEATURE_DIM = 31

_N_BINS = 18
# SCENESIG_NUMPY_HOG=1: the numpy HOG loops even where numba is installed (the same features).
_NUMPY_ONLY = bool(os.environ.get("SCENESIG_NUMPY_HOG"))
# cv2.resize INTER_AREA is the right anti-aliasing filter for downscaling by non-integer factors.
_INTERP = cv2.INTER_AREA
_EPS = 1e-4
# A level region covering more than this share of the level is described whole (one resize is cheaper).
_FULL_FRACTION = 0.8




def load_compiled() -> None:
    """Load the compiled HOG loops (:mod:`scenesig.signatures._hog_kernel`) now rather than at the first
    image: about half a second from numba's cache, a few seconds the very first time."""
    if _hog_kernel.AVAILABLE and not _NUMPY_ONLY:
        _hog_kernel.warm_up()


def level_scale(k: int | np.ndarray, scales_per_octave: int) -> float | np.ndarray:
    """Scale of pyramid level ``k`` relative to the input image."""
    return 2.0 ** (-np.asarray(k, dtype=float) / scales_per_octave)


def window_cell(x: float, y: float, scale_xy, cell: int, fh: int, fw: int) -> tuple[float, float]:
    """Fractional top-left cell (row, col) of a window of fh x fw cells centred at input pixel (x, y),
    on a level of scale ``scale_xy`` (sx, sy) -- also before the level exists (:meth:`Bank.pyramid`
    sizes the regions it needs with it).  Every argument may also be an array (elementwise)."""
    sx, sy = scale_xy
    return (y + 0.5) * sy / cell - 0.5 * fh, (x + 0.5) * sx / cell - 0.5 * fw


def level_size(image_size: tuple[int, int], k: int, scales_per_octave: int) -> tuple[int, int]:
    """(width, height) in pixels of pyramid level ``k`` of an image of ``image_size`` (width, height)."""
    s = float(level_scale(k, scales_per_octave))
    return int(round(image_size[0] * s)), int(round(image_size[1] * s))


def to_gray_float(image: np.ndarray, color: bool = False) -> np.ndarray:
    """Validate an image and return float32 (gray, or BGR when ``color``) for gradient computation.

    Raises
    ------
    ValueError
        If the array is not a 2-D gray or 3-channel image.
    """
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return image.astype(np.float32, copy=False)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"expected a gray (H, W) or colour (H, W, 3) image, got shape {image.shape}")
    if image.shape[2] == 4:
        image = image[:, :, :3]
    if color:
        return image.astype(np.float32, copy=False)
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY).astype(np.float32)


class ScaledImages:
    """An image ready for HOG (:func:`to_gray_float`), its pyramid levels' resizes, and the whole
    levels described so far.

    The resizes depend on the image alone -- not on which levels or cells a detector will search --
    so a replay makes them for the next frame on a worker thread while the current frame is solved
    (:meth:`scenesig.localiser.pipeline.SignatureLocaliser.prepare`).  :func:`build_level` then takes a
    level's region from here, with the values it would have computed bit for bit:

    * resizes: :func:`resize_area_region` equals the crop of OpenCV's resize for integer-valued
      images, which :func:`to_gray_float` of a uint8 image always is;
    * features: a level described whole once (a whole-image search) is kept, and later searches in
      the same image -- the relocaliser tries several places' banks on one frame -- take it or a
      region of it: the cells a region keeps (:data:`REGION_MARGIN_CELLS` inside its crop) are
      exactly the whole level's, the same invariance that lets a detector describe only its windows.

    (Describing the whole pyramid ahead on the worker thread was measured slower: its many short
    steps wait for Python's interpreter lock about as long as they save the detector.)

    Parameters
    ----------
    image : gray or BGR image (uint8 expected).
    config : HOG parameters (:data:`default_config` overrides).
    sizes : (width, height) of the levels to resize now (others are never made here: a region of
        them is resized on its own, which is cheaper when only part of the level is needed).
    """

    def __init__(self, image: np.ndarray, config: dict | None = None, sizes=()):
        cfg = merge_settings(default_config, config, "HOG")
        self.config = cfg
        self.color = bool(cfg["color"])
        self.image = to_gray_float(image, self.color)
        own = self.image.shape[1::-1]
        self._levels = {tuple(map(int, s)): cv2.resize(self.image, tuple(map(int, s)), interpolation=_INTERP)
                        for s in sizes if tuple(map(int, s)) != own}
        self._features: dict = {}

    @property
    def shape(self) -> tuple:
        return self.image.shape

    def resized(self, size) -> np.ndarray | None:
        """The whole level of ``size`` (width, height) if it was made (or is the image), else None."""
        size = (int(size[0]), int(size[1]))
        if size == self.image.shape[1::-1]:
            return self.image
        return self._levels.get(size)

    def _same_hog(self, cfg: dict) -> bool:
        return all(self.config.get(key) == cfg.get(key)
                   for key in ("cell", "clip", "color", "features", "xfeat_weight"))

    def features(self, size, cfg: dict) -> np.ndarray | None:
        """The whole level's features if it was described with the HOG parameters ``cfg``, else None."""
        return self._features.get((int(size[0]), int(size[1]))) if self._same_hog(cfg) else None

    def keep(self, size, cfg: dict, feat: np.ndarray) -> None:
        """Remember a whole level's features (described with ``cfg``; read-only from now on, since
        every later search of this image shares them)."""
        if self._same_hog(cfg):
            feat.flags.writeable = False
            self._features[(int(size[0]), int(size[1]))] = feat

    @classmethod
    def for_pyramid(cls, image: np.ndarray, config: dict | None = None, levels=None) -> "ScaledImages":
        """``image`` with the resizes of pyramid ``levels`` (default those of :func:`build_pyramid`)."""
        cfg = merge_settings(default_config, config, "HOG")
        h, w = np.asarray(image).shape[:2]
        plan = level_plan((w, h), cfg, levels)
        return cls(image, cfg, [size for _, size, _ in plan])


def as_hog_input(image, color: bool) -> "np.ndarray | ScaledImages":
    """:func:`to_gray_float` of an image; a :class:`ScaledImages` is returned as it is (checked for ``color``)."""
    if isinstance(image, ScaledImages):
        if image.color != bool(color):
            raise ValueError(f"images prepared with color={image.color} for HOG with color={bool(color)}")
        return image
    return to_gray_float(image, color)


def _subcell_offsets(h: int, w: int, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row and per column, the part of a pixel's histogram slot that its half-cell decides.

    A pixel's half-cell (``cell // 2`` px square) owns 19 slots; the index of its first slot is
    ``row_part[r] + col_part[c]``.  The linear orientation vote of a pixel in bin 17 goes to slots
    17 and 18, and slot 18 is folded back onto bin 0 afterwards, which avoids a modulo over every
    pixel.  (Adding the two parts in place costs less than building, or caching, the (h, w) index
    of every pixel: detection regions come in many sizes.)
    """
    half = cell // 2
    row_part = (np.arange(h) // half) * ((w // half) * (_N_BINS + 1))
    col_part = (np.arange(w) // half) * (_N_BINS + 1)
    return row_part.astype(np.intp), col_part.astype(np.intp)


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centred-difference gradient magnitude and angle (degrees, [0, 360))."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE)
    if img.ndim == 3:
        # FHOG: keep, per pixel, the channel with the strongest gradient.
        mag2 = gx * gx + gy * gy
        best = np.argmax(mag2, axis=2)[..., None]
        gx = np.take_along_axis(gx, best, axis=2)[..., 0]
        gy = np.take_along_axis(gy, best, axis=2)[..., 0]
    return cv2.cartToPolar(gx, gy, angleInDegrees=True)


def _cell_histograms(img: np.ndarray, cell: int) -> np.ndarray:
    """(Hc, Wc, 18) orientation histograms with linear orientation and bilinear spatial votes."""
    h, w = img.shape[:2]
    hc, wc = h // cell, w // cell
    mag, ang = _gradients(img[:hc * cell, :wc * cell])
    if _hog_kernel.AVAILABLE and not _NUMPY_ONLY:
        return _hog_kernel.cell_histograms(mag, ang, hc, wc, cell)
    return _cell_histograms_numpy(mag, ang, hc, wc, cell)


def _cell_histograms_numpy(mag: np.ndarray, ang: np.ndarray, hc: int, wc: int, cell: int) -> np.ndarray:
    """:func:`_cell_histograms` from the gradients in numpy (the reference of :mod:`scenesig.signatures._hog_kernel`,
    and the code path without numba)."""
    h, w = hc * cell, wc * cell
    # Linear vote between the two nearest of 18 bins centred at 0, 20, .. 340 degrees.
    b = ang.ravel()
    b *= np.float32(_N_BINS / 360.0)
    np.minimum(b, np.float32(_N_BINS - 1e-3), out=b)    # cartToPolar may return 360.0
    b0 = b.astype(np.intp)                               # floor, since b >= 0
    m = mag.ravel()
    w1 = b - b0.astype(np.float32)
    w1 *= m                                              # vote to the upper bin
    m -= w1                                              # vote to the lower bin
    idx = b0                                             # fresh array: reuse it in place
    row_part, col_part = _subcell_offsets(h, w, cell)
    idx2 = idx.reshape(h, w)
    idx2 += row_part[:, None]
    idx2 += col_part[None, :]
    n = (2 * hc) * (2 * wc) * (_N_BINS + 1)
    sub = np.bincount(idx, m, minlength=n)
    idx += 1
    sub += np.bincount(idx, w1, minlength=n)
    sub = sub.reshape(2 * hc, 2 * wc, _N_BINS + 1)
    sub[:, :, 0] += sub[:, :, _N_BINS]
    # Bilinear spatial interpolation at half-cell resolution: a cell's triangular weight over the
    # four half-cells at distance 0.5 and 1.5 half-cells from its centre is (0.25, 0.75, 0.75, 0.25).
    # (Zero padding written into preallocated arrays: np.pad costs more than the arithmetic here.
    # The rows pass writes straight into the zero-padded input of the columns pass.)
    pad = np.zeros((2 * hc + 2, 2 * wc, _N_BINS), np.float32)
    pad[1:-1] = sub[:, :, :_N_BINS]
    pad2 = np.zeros((hc, 2 * wc + 2, _N_BINS), np.float32)
    _taps_1331(pad[0:2 * hc:2], pad[1:2 * hc + 1:2], pad[2:2 * hc + 2:2], pad[3:2 * hc + 3:2], pad2[:, 1:-1])
    out = np.empty((hc, wc, _N_BINS), np.float32)
    return _taps_1331(pad2[:, 0:2 * wc:2], pad2[:, 1:2 * wc + 1:2], pad2[:, 2:2 * wc + 2:2],
                      pad2[:, 3:2 * wc + 3:2], out)


def _taps_1331(a, b, c, d, out):
    """``out = 0.25 a + 0.75 b + 0.75 c + 0.25 d``, summed left to right, without temporaries."""
    tmp = np.empty(out.shape, out.dtype)
    np.multiply(a, 0.25, out=out)
    np.multiply(b, 0.75, out=tmp)
    out += tmp
    np.multiply(c, 0.75, out=tmp)
    out += tmp
    np.multiply(d, 0.25, out=tmp)
    out += tmp
    return out


def fhog(image: np.ndarray, cell: int = 8, clip: float = 0.2, color: bool = False) -> np.ndarray:
    """FHOG features of one image (one pyramid level).

    Parameters
    ----------
    image : ndarray
        Gray (H, W) or BGR (H, W, 3), any numeric dtype (uint8 expected).
    cell : int
        Cell side in pixels (even).
    clip : float
        Truncation of normalised histogram values.
    color : bool
        Use the strongest colour channel's gradient (FHOG) instead of the gray gradient.

    Returns
    -------
    ndarray, shape (H // cell, W // cell, 31), float32
        Columns 0-17 contrast-sensitive, 18-26 contrast-insensitive, 27-30 texture.
    """
    if cell < 2 or cell % 2:
        raise ValueError(f"cell must be an even number of pixels >= 2, got {cell}")
    img = to_gray_float(image, color)
    hc, wc = img.shape[0] // cell, img.shape[1] // cell
    if hc < 1 or wc < 1:
        raise ValueError(f"image {img.shape[:2]} is smaller than one {cell}-px cell")
    hist = _cell_histograms(img, cell)                       # (hc, wc, 18)
    insens = hist[:, :, :9] + hist[:, :, 9:]                 # (hc, wc, 9)
    energy = np.einsum("ijk,ijk->ij", insens, insens)        # squared norm per cell
    if _hog_kernel.AVAILABLE and not _NUMPY_ONLY:
        return _hog_kernel.normalise(hist, insens, energy, clip, _EPS)
    # Energy of the 2x2 blocks with corners between cells (edge-replicated): block (i, j) covers
    # cells (i-1..i, j-1..j) of the padded grid; blk has shape (hc + 1, wc + 1).
    e = np.empty((hc + 2, wc + 2), energy.dtype)         # np.pad(energy, 1, mode="edge"), faster
    e[1:-1, 1:-1] = energy
    e[0, 1:-1], e[-1, 1:-1] = energy[0], energy[-1]
    e[:, 0], e[:, -1] = e[:, 1], e[:, -2]
    blk = e[:-1, :-1] + e[1:, :-1] + e[:-1, 1:] + e[1:, 1:]
    # The four blocks containing cell (i, j): top-left, top-right, bottom-left, bottom-right.
    norms = np.stack([blk[:-1, :-1], blk[:-1, 1:], blk[1:, :-1], blk[1:, 1:]])
    inv = 1.0 / np.sqrt(norms + _EPS)                        # (4, hc, wc)
    out = np.empty((hc, wc, FEATURE_DIM), np.float32)
    # All four normalisations at once (sums over them in the order k = 0..3, as a loop would).
    # (In-place where possible: the same float32 operations without temporaries.)
    inv = inv[:, :, :, None]
    hs = np.multiply(hist[None], inv)                        # (4, hc, wc, 18)
    np.minimum(hs, clip, out=hs)
    np.multiply(hs.sum(axis=0), 0.5, out=out[:, :, :18])
    hi = np.multiply(insens[None], inv)
    np.minimum(hi, clip, out=hi)
    np.multiply(hi.sum(axis=0), 0.5, out=out[:, :, 18:27])
    # Texture: summed clipped sensitive energy under each normalisation (FHOG's 0.2357 = 1/sqrt(18)).
    np.multiply(np.moveaxis(hs.sum(axis=3), 0, 2), 0.2357, out=out[:, :, 27:])
    return out


#: Length of each part a cell descriptor can stack.
_PART_DIM = {"hog": FEATURE_DIM, "xfeat": XFEAT_DIM}


def _parts(config: dict | None) -> list[str]:
    """The stacked parts of ``config``'s cell descriptor, in order (``["hog", "xfeat"]`` for hog+xfeat)."""
    kind = str((config or {}).get("features", "hog"))
    if kind not in FEATURE_KINDS:
        raise ValueError(f"unknown cell features {kind!r}: expected one of {', '.join(FEATURE_KINDS)}")
    return kind.split("+")


def feature_dim(config: dict | None = None) -> int:
    """Length of a cell's descriptor under ``config`` (HOG parameters): 31, 64 or 95."""
    return sum(_PART_DIM[p] for p in _parts(config))


def learned(config: dict | None) -> bool:
    """True when cells are (partly) described by a network, whose descriptor of a cell depends on
    the whole image: such levels are always described whole (no regions)."""
    return "xfeat" in _parts(config)


def describe_cells(level: np.ndarray, cfg: dict) -> np.ndarray:
    """The cell descriptors of one pyramid level (an image resized to the level), shape
    ``(H // cell, W // cell, feature_dim(cfg))``, float32.

    ``features`` "hog" is :func:`fhog`.  "xfeat" is XFeat's dense descriptor map (Potje et al.,
    CVPR 2024), whose 1/8 resolution makes one descriptor per 8-pixel cell, each scaled to unit
    length as XFeat's own descriptors are (:meth:`scenesig.signatures.xfeat.XFeat.cells`); the network
    runs on each level, as FHOG does, so a level holds what the network sees at that scale.
    "hog+xfeat" stacks both, FHOG first (so its texture columns stay 27-30), the XFeat part scaled to
    length ``xfeat_weight``.
    """
    names = _parts(cfg)
    cell = int(cfg["cell"])
    parts = []
    if "hog" in names:
        parts.append(fhog(level, cell, float(cfg["clip"]), bool(cfg["color"])))
    if "xfeat" in names:
        from scenesig.signatures.xfeat import get_xfeat

        x = get_xfeat().cells(level, cell)
        if len(names) > 1:
            x *= np.float32(cfg.get("xfeat_weight", 1.0))
        parts.append(x)
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=2)


# ------------------------------------------------------------------------------ regions of a level
#: Cells computed around a requested region of a level: a cell's features depend on the gradients
#: of the half-cells bordering it (bilinear votes) and on its neighbours' energies (block
#: normalisation), so two extra cells on each side make the requested cells exactly the same as
#: in the whole level's features.
REGION_MARGIN_CELLS = 2

# Area-decimation tables per (source length, destination length): they depend only on the sizes.
_AREA_TABS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}


def _area_taps(ssize: int, dsize: int) -> tuple[np.ndarray, np.ndarray]:
    """Source indices (dsize, T) and weights (dsize, T) of OpenCV's INTER_AREA decimation along one axis.

    The same table as OpenCV's ``computeResizeAreaTab`` (a destination pixel averages the source
    pixels it covers, the partly covered ones weighted by their covered share), padded with zero
    weights to a fixed number of taps T.
    """
    key = (int(ssize), int(dsize))
    tab = _AREA_TABS.get(key)
    if tab is not None:
        return tab
    scale = 1.0 / (dsize / ssize)          # OpenCV: scale_x = 1. / inv_scale_x
    rows: list[list[tuple[int, np.float32]]] = []
    for dx in range(dsize):
        fsx1 = dx * scale
        fsx2 = fsx1 + scale
        cell = min(scale, ssize - fsx1)
        sx1, sx2 = int(np.ceil(fsx1)), int(np.floor(fsx2))
        sx2 = min(sx2, ssize - 1)
        sx1 = min(sx1, sx2)
        taps = []
        if sx1 - fsx1 > 1e-3:
            taps.append((sx1 - 1, np.float32((sx1 - fsx1) / cell)))
        for sx in range(sx1, sx2):
            taps.append((sx, np.float32(1.0 / cell)))
        if fsx2 - sx2 > 1e-3:
            taps.append((sx2, np.float32(min(min(fsx2 - sx2, 1.0), cell) / cell)))
        rows.append(taps)
    T = max(len(t) for t in rows)
    idx = np.zeros((dsize, T), np.intp)
    wts = np.zeros((dsize, T), np.float32)
    for d, taps in enumerate(rows):
        for t, (si, a) in enumerate(taps):
            idx[d, t], wts[d, t] = si, a
        idx[d, len(taps):] = taps[0][0]     # padding taps: weight 0 on a pixel already used
    if len(_AREA_TABS) > 256:
        _AREA_TABS.clear()
    _AREA_TABS[key] = (idx, wts)
    return idx, wts


def resize_area_region(img: np.ndarray, size: tuple[int, int], rows: tuple[int, int],
                       cols: tuple[int, int]) -> np.ndarray:
    """Rows ``[y0, y1)`` and columns ``[x0, x1)`` of ``cv2.resize(img, size, interpolation=INTER_AREA)``.

    Only the source rows those destination pixels cover are read: OpenCV decimates them along x
    (its own x table), and the y pass repeats OpenCV's arithmetic (float32 products accumulated tap
    by tap) on the needed columns only.  For a float32 image with integer values (a converted uint8
    image, as the pyramid's input always is) the result equals the crop of the full resize bit for
    bit; for other values it agrees to float32 rounding.  Only downscaling (``size`` <= the image
    size) is supported.

    Parameters
    ----------
    img : (H, W) or (H, W, C) float32 image.
    size : (width, height) of the whole resized image.
    rows, cols : destination row and column ranges (end exclusive).
    """
    h, w = img.shape[:2]
    dw, dh = int(size[0]), int(size[1])
    if dw > w or dh > h:
        raise ValueError(f"resize_area_region only downscales; {w}x{h} -> {dw}x{dh}")
    y0, y1 = int(rows[0]), int(rows[1])
    x0, x1 = int(cols[0]), int(cols[1])
    if not (0 <= y0 < y1 <= dh and 0 <= x0 < x1 <= dw):
        raise ValueError(f"region rows {rows} cols {cols} outside the {dw}x{dh} resized image")
    yi, yw = _area_taps(h, dh)
    yi, yw = yi[y0:y1], yw[y0:y1]
    sy0, sy1 = int(yi[0, 0]), int(yi.max()) + 1        # taps are sorted: the first is the smallest
    yi = yi - sy0
    extra = (None,) * (img.ndim - 1)          # broadcast a tap's weights over a row (and channels)
    rows_src = img[sy0:sy1]
    if dw < w:
        # The horizontal pass is OpenCV's own: resizing the needed source rows in x only runs the
        # same x table (and a y table of weight 1, which changes nothing) -- much faster than
        # gathering columns in numpy.
        buf = cv2.resize(np.ascontiguousarray(rows_src), (dw, sy1 - sy0), interpolation=_INTERP)[:, x0:x1]
    else:
        buf = rows_src[:, x0:x1]
    # (Row gathers by indexing: np.take along axis 0 of this strided view is up to 20x slower.)
    out = yw[(slice(None), 0) + extra] * buf[yi[:, 0]]
    for t in range(1, yi.shape[1]):
        out += yw[(slice(None), t) + extra] * buf[yi[:, t]]
    return out


def _level_pixels(img, size: tuple[int, int]):
    """``(image, level)``: the float image of ``img`` (an image or :class:`ScaledImages`) and the whole
    level of ``size`` where it is at hand (the image itself at its own size, or a prepared resize),
    else None."""
    if isinstance(img, ScaledImages):
        return img.image, img.resized(size)
    return img, (img if tuple(size) == img.shape[1::-1] else None)


def _whole_level(img, size: tuple[int, int], cfg: dict) -> np.ndarray:
    """FHOG features of the whole level of ``size`` (width, height) of an image or :class:`ScaledImages`
    (which keeps them for later searches of the same image)."""
    scaled = isinstance(img, ScaledImages)
    feat = img.features(size, cfg) if scaled else None
    if feat is None:
        base, lvl = _level_pixels(img, size)
        if lvl is None:
            lvl = cv2.resize(base, tuple(size), interpolation=_INTERP)
        feat = describe_cells(lvl, cfg)
        if scaled:
            img.keep(size, cfg, feat)
    return feat


def _region_extent(image_size, size: tuple[int, int], box, cell: int, full_fraction: float):
    """Where :func:`_level_region` computes: None for the whole level, else the described cell box
    ``(a0, a1, b0, b1)`` (the requested box with its margin) and the exact cell box ``(e0, e1, g0, g1)``
    it returns as ``valid`` (end exclusive)."""
    lw, lh = size
    hc, wc = lh // cell, lw // cell
    r0, r1 = max(0, int(box[0])), min(hc, int(box[1]))
    c0, c1 = max(0, int(box[2])), min(wc, int(box[3]))
    m = REGION_MARGIN_CELLS
    a0, a1 = max(0, r0 - m), min(hc, r1 + m)
    b0, b1 = max(0, c0 - m), min(wc, c1 + m)
    w, h = image_size
    upscale = lw > w or lh > h
    if r1 <= r0 or c1 <= c0 or upscale or (a1 - a0) * (b1 - b0) > full_fraction * hc * wc:
        return None
    # Cells next to the crop's edges miss neighbours the whole level has: keep only exact ones
    # (at the level's own border the crop has the same border as the level).
    e0, e1 = (a0 + m if a0 > 0 else 0), (a1 - m if a1 < hc else hc)
    g0, g1 = (b0 + m if b0 > 0 else 0), (b1 - m if b1 < wc else wc)
    return (a0, a1, b0, b1), (e0, e1, g0, g1)


def _level_region(img, size: tuple[int, int], box, cfg: dict, full_fraction: float):
    """FHOG features of one level computed only around a cell box.

    Returns ``(features, valid)``: features of the whole level's shape, zero outside ``valid``, the
    cell box ``(r0, r1, c0, c1)`` (end exclusive, containing ``box``) where they are exact.  When the
    box with its margin covers more than ``full_fraction`` of the level the whole level is computed
    (one OpenCV resize is cheaper then) and ``valid`` is None.
    """
    cell, clip, color = int(cfg["cell"]), float(cfg["clip"]), bool(cfg["color"])
    extent = None if learned(cfg) else _region_extent(img.shape[1::-1], size, box, cell, full_fraction)
    if extent is None:
        return _whole_level(img, size, cfg), None
    (a0, a1, b0, b1), (e0, e1, g0, g1) = extent
    lw, lh = size
    out = np.zeros((lh // cell, lw // cell, FEATURE_DIM), np.float32)
    whole = img.features(size, cfg) if isinstance(img, ScaledImages) else None
    if whole is not None:               # described whole before: the kept cells are the whole level's
        out[e0:e1, g0:g1] = whole[e0:e1, g0:g1]
        return out, (e0, e1, g0, g1)
    rows, cols = (a0 * cell, a1 * cell), (b0 * cell, b1 * cell)
    base, whole = _level_pixels(img, size)
    if whole is not None:
        lvl = whole[rows[0]:rows[1], cols[0]:cols[1]]
    else:
        lvl = resize_area_region(base, (lw, lh), rows, cols)
    f = fhog(lvl, cell, clip, color)
    out[e0:e1, g0:g1] = f[e0 - a0:e1 - a0, g0 - b0:g1 - b0]
    return out, (e0, e1, g0, g1)


@dataclass
class HogPyramid:
    """HOG features of one image at several scales.

    Attributes
    ----------
    levels : dict[int, ndarray]
        Level index ``k`` -> features (Hc, Wc, D) float32 (D = :func:`feature_dim` of ``config``: 31
        for HOG) of the image resized by
        ``2 ** (-k / scales_per_octave)``.
    image_size : tuple of int
        (width, height) of the input image in pixels.
    config : dict
        HOG parameters used (cell, scales_per_octave, clip, color).
    sizes : dict[int, tuple]
        Level -> (width, height) in pixels of the resized image.
    regions : dict[int, tuple]
        Levels computed only in part (:func:`build_pyramid`'s ``regions``): level -> cell box
        ``(r0, r1, c0, c1)``, end exclusive, where the features are exact; zero elsewhere.  Levels
        not listed are complete.
    """

    levels: dict[int, np.ndarray]
    image_size: tuple[int, int]
    config: dict
    sizes: dict[int, tuple[int, int]] = field(default_factory=dict)
    regions: dict[int, tuple[int, int, int, int]] = field(default_factory=dict)

    def valid_region(self, k: int) -> tuple[int, int, int, int]:
        """Cell box ``(r0, r1, c0, c1)`` (end exclusive) of level k where the features were computed."""
        box = self.regions.get(k)
        if box is None:
            hc, wc = self.levels[k].shape[:2]
            return 0, hc, 0, wc
        return box

    @property
    def cell(self) -> int:
        return int(self.config["cell"])

    @property
    def scales_per_octave(self) -> int:
        return int(self.config["scales_per_octave"])

    def scale(self, k: int) -> float:
        """Actual scale of level ``k`` (resized width / input width, per axis)."""
        w, h = self.sizes[k]
        return 0.5 * (w / self.image_size[0] + h / self.image_size[1])

    def scale_xy(self, k: int) -> tuple[float, float]:
        w, h = self.sizes[k]
        return w / self.image_size[0], h / self.image_size[1]

    def window_centre(self, k: int, row: float, col: float, fh: int, fw: int) -> tuple[float, float]:
        """Centre, in input-image pixels, of the fh x fw cell window with top-left cell (row, col).

        Accepts fractional (sub-cell refined) row and col.
        """
        sx, sy = self.scale_xy(k)
        c = self.cell
        # Level pixel edges -> input pixel edges: u_in = u_level / s (pixel-edge coordinates).
        x = (c * (col + 0.5 * fw)) / sx - 0.5
        y = (c * (row + 0.5 * fh)) / sy - 0.5
        return x, y

    def cell_at(self, k: int, x: float, y: float, fh: int, fw: int) -> tuple[float, float]:
        """Inverse of :meth:`window_centre`: fractional top-left cell (row, col) of a window of
        fh x fw cells centred at input pixel (x, y)."""
        return window_cell(x, y, self.scale_xy(k), self.cell, fh, fw)

    def matches(self, config: dict) -> bool:
        """True if this pyramid was built with the HOG parameters in ``config`` (a missing cell
        descriptor setting is the default's, as in banks stored before it existed)."""
        return all(self.config.get(key, default_config[key]) == config.get(key, default_config[key])
                   for key in default_config)


def build_pyramid(image: np.ndarray, config: dict | None = None, levels=None, regions: dict | None = None,
                  full_fraction: float = _FULL_FRACTION, threads: int = 1) -> HogPyramid:
    """HOG pyramid of one image.

    Parameters
    ----------
    image : ndarray
        Gray or BGR image.
    config : dict, optional
        Overrides of :data:`default_config`.
    levels : iterable of int, optional
        Level indices to compute (default ``0 .. 2 * scales_per_octave``, i.e. two octaves).
        Levels too small to hold one cell are skipped.
    regions : dict, optional
        Level -> cell box ``(r0, r1, c0, c1)`` (end exclusive) that is needed: only that box (plus
        :data:`REGION_MARGIN_CELLS`) is resized and described, and the features in it are exactly
        those of the whole level (a tracking detector searches small windows, so most of each
        level is never looked at).  Levels without an entry are computed whole.
    full_fraction : float
        A region covering more than this share of its level is computed whole (cheaper).
    threads : int
        Levels computed at once (:func:`thread_map`).  Levels are independent, so the features are
        the same for any count.

    Returns
    -------
    HogPyramid
        With ``regions`` recording the partly computed levels.
    """
    cfg = merge_settings(default_config, config, "HOG")
    img = as_hog_input(image, bool(cfg["color"]))
    plan = level_plan(img.shape[1::-1], cfg, levels, regions)
    feats = thread_map(lambda p: build_level(img, p[1], p[2], cfg, full_fraction), plan, threads,
                       cost=[p[1][0] * p[1][1] for p in plan])
    return assemble_pyramid(img.shape[1::-1], cfg, plan, feats)


def level_plan(image_size: tuple[int, int], cfg: dict, levels=None, regions: dict | None = None) -> list:
    """``[(k, (width, height), box or None), ...]``: the levels of :func:`build_pyramid` (those that
    hold at least one cell), each with its size and its region (None: the whole level)."""
    spo, cell = int(cfg["scales_per_octave"]), int(cfg["cell"])
    ks = range(0, 2 * spo + 1) if levels is None else sorted({int(k) for k in levels})
    plan = []
    for k in ks:
        lw, lh = level_size(image_size, k, spo)
        if lw >= cell and lh >= cell:
            plan.append((k, (lw, lh), None if regions is None else regions.get(k)))
    return plan


def build_level(img, size: tuple[int, int], box, cfg: dict, full_fraction: float = _FULL_FRACTION):
    """``(features, valid)`` of one level of ``size`` of the float image ``img`` (:func:`to_gray_float`,
    or a :class:`ScaledImages`, whose resizes are used): the whole level (``valid`` None) or only
    around the cell ``box`` (see :func:`build_pyramid`)."""
    if box is None:
        return _whole_level(img, size, cfg), None
    return _level_region(img, size, box, cfg, full_fraction)


def assemble_pyramid(image_size, cfg: dict, plan: list, feats: list) -> HogPyramid:
    """The :class:`HogPyramid` of :func:`level_plan`'s levels and :func:`build_level`'s results."""
    out, sizes, valid = {}, {}, {}
    for (k, size, _), (f, part) in zip(plan, feats):
        out[k], sizes[k] = f, size
        if part is not None:
            valid[k] = part
    return HogPyramid(out, tuple(image_size), cfg, sizes, valid)


# ------------------------------------------------------------------------------------ threads
# What thread_map's threaded section runs inside: nothing by default -- the library never changes
# process-wide state.  The runtime layer (scenesig.runtime.configure) installs OpenCV-on-one-thread.
_PARALLEL_SECTION = contextlib.nullcontext


def set_parallel_section(factory) -> None:
    """Make :func:`thread_map` run its threads inside ``factory()`` (a context manager factory; None:
    nothing).  The command line's runtime layer (:mod:`scenesig.runtime`) sets OpenCV's own thread pool
    to one thread there, as the threads already keep the cores busy."""
    global _PARALLEL_SECTION
    _PARALLEL_SECTION = factory or contextlib.nullcontext


def _usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:
        return os.cpu_count() or 1


def thread_map(fn, items, threads: int = 1, cost=None) -> list:
    """``[fn(x) for x in items]`` on ``threads`` threads: the calling one and ``threads - 1`` helper
    threads of this call (no pool outlives it) take the items one at a time, the costliest first (``cost``, one number per
    item).  The results come back in the order of ``items`` and each is computed exactly as a
    serial loop would, so threads change the time, never the result.

    Pyramid levels are the natural unit: OpenCV and numpy's large array operations release the
    GIL, so two levels run on two cores (about 1.5x, not 2x, on two idle cores: numpy's many
    small operations hold it).  The threads run inside the section :func:`set_parallel_section`
    installs (the command line: OpenCV on one thread).  The first exception raised by ``fn`` is re-raised.
    """
    items = list(items)
    threads = max(1, min(int(threads), len(items), _usable_cpus()))
    if threads == 1:
        return [fn(x) for x in items]
    order = list(range(len(items))) if cost is None else sorted(range(len(items)), key=lambda j: -cost[j])
    out = [None] * len(items)
    pending = iter(order)
    lock = threading.Lock()
    failed: list[BaseException] = []

    def work():
        while not failed:
            with lock:
                j = next(pending, None)
            if j is None:
                return
            try:
                out[j] = fn(items[j])
            except BaseException as exc:  # noqa: BLE001 - re-raised in the calling thread
                failed.append(exc)

    with _PARALLEL_SECTION():
        # each helper runs in a copy of the caller's context, so context variables the caller set
        # (the XFeat model of signatures.xfeat.using_model) hold in the helpers too
        helpers = [threading.Thread(target=contextvars.copy_context().run, args=(work,), name=f"hog-{k}", daemon=True)
                   for k in range(threads - 1)]
        for h in helpers:
            h.start()
        work()
        for h in helpers:
            h.join()
    if failed:
        raise failed[0]
    return out
