"""A bank of scene-signature classifiers for one place: the data model and its storage.

A :class:`Classifier` is a linear filter over a window of FHOG cells (McManus et al. 2015, §3.2: one SVM per
scene signature) with the shape it was mined from, its nominal position and scale, and the
score-to-probability calibration lambda of eq. (5).  A :class:`Bank` holds the classifiers of a
place and stores to and from plain arrays (the map store writes that dict).

Detecting a bank in an image (:meth:`Bank.detect`, :meth:`Bank.pyramid`) is the detection engine,
:mod:`scenesig.signatures.detection` (McManus et al. 2015, §3.3.1): the methods call it.  Its names --
:class:`~scenesig.signatures.detection.Detections`, :data:`~scenesig.signatures.detection.default_config`,
:func:`~scenesig.signatures.detection.limit_blas_threads`,
:func:`~scenesig.signatures.detection.score_maps_bruteforce` -- are importable from here too (the same
objects); patch the engine's functions in :mod:`scenesig.signatures.detection`, where they are called.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scenesig.signatures import detection
from scenesig.signatures.classifier import sigmoid
from scenesig.signatures.detection import Detections, default_config, limit_blas_threads, score_maps_bruteforce
from scenesig.signatures.hog import HogPyramid, default_config as hog_default, feature_dim, level_scale

__all__ = ["Classifier", "Bank", "Detections", "default_config", "score_maps_bruteforce", "limit_blas_threads"]


@dataclass
class Classifier:
    """One scene-signature classifier (a linear SVM over a window of HOG cells).

    Attributes
    ----------
    weights : ndarray, shape (fh, fw, D), float32
        (D: 31 for HOG cells, :func:`scenesig.signatures.hog.feature_dim` of ``hog``)
        Filter; the score of a window is ``sum(weights * window) + bias``.
    bias : float
    level : int
        Nominal pyramid level ``k`` (scale ``2 ** (-k / scales_per_octave)``) the filter was trained at.
    box : tuple of float
        The candidate shape ``(x, y, w, h)`` in pixels of the reference image.
    nominal_xy : tuple of float
        Where the signature lies in the reference image (centre, pixels): the median over its
        training firings of the firing position shifted back by the image's alignment offset.
    nominal_scale : float
        Median scale (level scale) of the training firings.
    calibration : tuple of float
        ``(a, b)``: detection probability ``lambda = 1 / (1 + exp(-(a * score + b)))`` (Platt scaling
        fitted on held-out partitions during mining).
    hog : dict
        HOG parameters the filter expects (see :data:`scenesig.signatures.hog.default_config`).
    shape_index : int
        Index of the shape in the candidate template (-1 if unknown).
    kind : str
        Shape kind name.
    quality : float
        Held-out separability from mining (higher is better; NaN if unknown).
    spread : tuple of float
        ``(sx, sy)``: RMS deviation (pixels, per axis) of the training firings, moved into the
        reference image by their alignment offsets, from ``nominal_xy``.  Small for signatures that
        move with the alignment (distant structure), large for near ones (parallax) or unstable
        ones.  NaN if unknown.
    """

    weights: np.ndarray
    bias: float
    level: int
    box: tuple
    nominal_xy: tuple
    nominal_scale: float
    calibration: tuple = (1.0, 0.0)
    hog: dict = field(default_factory=lambda: dict(hog_default))
    shape_index: int = -1
    kind: str = ""
    quality: float = float("nan")
    spread: tuple = (float("nan"), float("nan"))

    def __post_init__(self):
        w = np.asarray(self.weights, dtype=np.float32)
        d = feature_dim(self.hog)
        if w.ndim != 3 or w.shape[2] != d or w.shape[0] < 1 or w.shape[1] < 1:
            raise ValueError(f"classifier weights must have shape (fh, fw, {d}) for "
                             f"{self.hog.get('features', 'hog')} cells, got {w.shape}")
        self.weights = w

    @property
    def filter_shape(self) -> tuple[int, int]:
        """(fh, fw) in cells."""
        return self.weights.shape[0], self.weights.shape[1]

    @property
    def scale(self) -> float:
        """Scale of the nominal level."""
        return float(level_scale(self.level, int(self.hog["scales_per_octave"])))

    def probability(self, score):
        """Calibrated detection probability (lambda) of raw SVM scores."""
        a, b = self.calibration
        return sigmoid(a * np.asarray(score, dtype=float) + b)



class Bank:
    """The scene-signature classifiers of one place.

    Parameters
    ----------
    classifiers : list of Classifier
        All must share the same HOG parameters.
    image_size : tuple of int, optional
        (width, height) of the images the bank was trained on; detection checks it.
    meta : dict, optional
        Free-form numeric/str metadata kept through :meth:`to_arrays`.
    """

    def __init__(self, classifiers, image_size=None, meta=None):
        self.classifiers = list(classifiers)
        self.image_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
        self.meta = dict(meta or {})
        hogs = {tuple(sorted(c.hog.items())) for c in self.classifiers}
        if len(hogs) > 1:
            raise ValueError("classifiers of one bank must share HOG parameters "
                             f"(found {len(hogs)} different sets)")
        self.hog = dict(self.classifiers[0].hog) if self.classifiers else dict(hog_default)

    # ------------------------------------------------------------------ container
    def __len__(self) -> int:
        return len(self.classifiers)

    def __getitem__(self, i):
        if isinstance(i, (int, np.integer)):
            return self.classifiers[int(i)]
        return self.select(i)

    def __iter__(self):
        return iter(self.classifiers)

    def __repr__(self) -> str:
        return f"Bank({len(self)} classifiers, image_size={self.image_size})"

    def select(self, indices) -> "Bank":
        """A bank with the classifiers at ``indices`` (int array, slice or boolean mask)."""
        idx = np.arange(len(self))[indices]
        sub = Bank.__new__(Bank)      # the classifiers share this bank's HOG parameters: no re-check
        sub.classifiers = [self.classifiers[i] for i in np.atleast_1d(idx)]
        sub.image_size, sub.meta, sub.hog = self.image_size, dict(self.meta), dict(self.hog)
        return sub

    def best(self, n: int) -> "Bank":
        """The ``n`` classifiers of highest mining quality (NaN quality last)."""
        q = np.array([c.quality for c in self.classifiers], dtype=float)
        order = np.argsort(-np.nan_to_num(q, nan=-np.inf), kind="stable")
        return self.select(np.sort(order[:n]))

    # ------------------------------------------------------------------ storage
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for storage (no pickles; float16 only where the round trip is exact)."""
        n = len(self)
        cs = self.classifiers
        flat = (np.concatenate([c.weights.ravel() for c in cs]) if n
                else np.zeros(0, np.float32))
        kinds = sorted({c.kind for c in cs})
        out = {
            "weights": _compact(flat.astype(np.float32)),
            "filter_shape": np.array([c.filter_shape for c in cs], dtype=np.int32).reshape(n, 2),
            "bias": np.array([c.bias for c in cs], dtype=np.float64),
            "level": np.array([c.level for c in cs], dtype=np.int32),
            "box": _compact(np.array([c.box for c in cs], dtype=np.float64).reshape(n, 4)),
            "nominal_xy": np.array([c.nominal_xy for c in cs], dtype=np.float64).reshape(n, 2),
            "nominal_scale": np.array([c.nominal_scale for c in cs], dtype=np.float64),
            "calibration": np.array([c.calibration for c in cs], dtype=np.float64).reshape(n, 2),
            "shape_index": np.array([c.shape_index for c in cs], dtype=np.int32),
            "kind": np.array([kinds.index(c.kind) for c in cs], dtype=np.int32),
            "kind_names": np.array(kinds, dtype=str),
            "quality": np.array([c.quality for c in cs], dtype=np.float64),
            "spread": np.array([c.spread for c in cs], dtype=np.float64).reshape(n, 2),
            "hog_cell": np.array(int(self.hog["cell"])),
            "hog_scales_per_octave": np.array(int(self.hog["scales_per_octave"])),
            "hog_clip": np.array(float(self.hog["clip"])),
            "hog_color": np.array(bool(self.hog["color"])),
            "image_size": np.array(self.image_size if self.image_size else (-1, -1), dtype=np.int32),
        }
        if self.hog.get("features", "hog") != "hog":
            # only learned cells write these: a HOG bank's file stays as it always was
            out["hog_features"] = np.array(str(self.hog["features"]))
            out["hog_xfeat_weight"] = np.array(float(self.hog.get("xfeat_weight", 1.0)))
        for k, v in self.meta.items():
            out[f"meta_{k}"] = np.asarray(v)
        return out

    @classmethod
    def from_arrays(cls, d: dict) -> "Bank":
        """Inverse of :meth:`to_arrays`.

        Raises
        ------
        ValueError
            If a required array is missing or the sizes disagree.
        """
        need = ("weights", "filter_shape", "bias", "level", "box", "nominal_xy", "nominal_scale",
                "calibration", "hog_cell", "hog_scales_per_octave", "hog_clip", "hog_color")
        missing = [k for k in need if k not in d]
        if missing:
            raise ValueError(f"bank arrays lack {', '.join(missing)}")
        # banks stored before the cell descriptor was a setting hold HOG cells
        hog = {"cell": int(d["hog_cell"]), "scales_per_octave": int(d["hog_scales_per_octave"]),
               "clip": float(d["hog_clip"]), "color": bool(d["hog_color"]),
               "features": str(d.get("hog_features", hog_default["features"])),
               "xfeat_weight": float(d.get("hog_xfeat_weight", hog_default["xfeat_weight"]))}
        dim = feature_dim(hog)
        fs = np.asarray(d["filter_shape"], dtype=int).reshape(-1, 2)
        n = len(fs)
        sizes = fs[:, 0] * fs[:, 1] * dim
        flat = np.asarray(d["weights"], dtype=np.float32)
        if flat.size != sizes.sum():
            raise ValueError(f"bank weights hold {flat.size} values but the filter shapes need "
                             f"{int(sizes.sum())}")
        for key in ("bias", "level", "box", "nominal_xy", "nominal_scale", "calibration"):
            a = np.asarray(d[key])
            if (a.shape[0] if a.ndim else 1) != n:
                raise ValueError(f"bank array {key!r} does not have {n} rows")
        kind_names = [str(s) for s in np.asarray(d.get("kind_names", np.array([], dtype=str)))]
        kind = np.asarray(d.get("kind", np.full(n, -1)), dtype=int)
        sidx = np.asarray(d.get("shape_index", np.full(n, -1)), dtype=int)
        qual = np.asarray(d.get("quality", np.full(n, np.nan)), dtype=float)
        spread = np.asarray(d.get("spread", np.full((n, 2), np.nan)), dtype=float).reshape(n, 2)
        offs = np.concatenate([[0], np.cumsum(sizes)])
        cs = []
        for i in range(n):
            cs.append(Classifier(
                weights=flat[offs[i]:offs[i + 1]].reshape(fs[i, 0], fs[i, 1], dim),
                bias=float(np.asarray(d["bias"])[i]), level=int(np.asarray(d["level"])[i]),
                box=tuple(float(v) for v in np.asarray(d["box"], dtype=float).reshape(n, 4)[i]),
                nominal_xy=tuple(float(v) for v in np.asarray(d["nominal_xy"]).reshape(n, 2)[i]),
                nominal_scale=float(np.asarray(d["nominal_scale"])[i]),
                calibration=tuple(float(v) for v in np.asarray(d["calibration"]).reshape(n, 2)[i]),
                hog=dict(hog), shape_index=int(sidx[i]),
                kind=kind_names[kind[i]] if 0 <= kind[i] < len(kind_names) else "",
                quality=float(qual[i]), spread=(float(spread[i, 0]), float(spread[i, 1]))))
        size = tuple(int(v) for v in np.asarray(d.get("image_size", (-1, -1))))
        meta = {k[5:]: (v.item() if np.ndim(v) == 0 else v) for k, v in d.items()
                if k.startswith("meta_")}
        bank = cls(cs, None if size[0] < 0 else size, meta)
        bank.hog = hog
        return bank

    # ------------------------------------------------------------------ detection
    def levels(self, scale_search: int = 1) -> list[int]:
        """Pyramid levels detection needs (nominal +- scale_search, never below 0)."""
        ks = set()
        for c in self.classifiers:
            ks.update(range(max(0, c.level - scale_search), c.level + scale_search + 1))
        return sorted(ks)


    def pyramid(self, image: np.ndarray, scale_search: int = 1, levels=None, windows=None,
                threads: int = 1) -> HogPyramid:
        """The HOG pyramid of ``image`` with exactly what this bank searches.

        Parameters
        ----------
        image : gray or BGR image.
        scale_search : levels nominal +- this (when ``levels`` is not given).
        levels : per-classifier levels to search (as in :meth:`detect`).
        windows : per-classifier search windows (as in :meth:`detect`).  With windows only the
            cells the windows' detections can touch are computed at each level (and levels no
            window reaches are skipped); those cells are exactly the whole level's.
        threads : levels computed at once (the features are the same for any count).
        """
        return detection.pyramid(self, image, scale_search, levels, windows, threads)

    def detect(self, image, windows=None, top_n: int = 1, config: dict | None = None,
               levels=None) -> "Detections":
        """Detect every classifier of the bank in one image.

        Parameters
        ----------
        image : ndarray, ScaledImages or HogPyramid
            The image (gray or BGR), the image with its levels' resizes
            (:class:`scenesig.signatures.hog.ScaledImages`, the same detections), or its pyramid (built with
            this bank's HOG parameters and the needed levels, e.g. by :meth:`pyramid`).
        windows : ndarray, shape (n, 4), optional
            Per-classifier search window ``x_min, y_min, x_max, y_max`` (input pixels) for the
            detection *centre*; a row of NaN means the whole image.
        top_n : int
            Number of detections per classifier (after non-maximum suppression).
        config : dict, optional
            Overrides of :data:`scenesig.signatures.detection.default_config`.
        levels : sequence of sequence of int, optional
            Per-classifier pyramid levels to search (default nominal +- ``scale_search``).

        Returns
        -------
        Detections
        """
        return detection.detect(self, image, windows, top_n, config, levels)


def _compact(a: np.ndarray) -> np.ndarray:
    """float16 copy of ``a`` if that round trip is exact, else ``a`` unchanged."""
    a16 = a.astype(np.float16)
    with np.errstate(over="ignore", invalid="ignore"):
        if np.array_equal(a16.astype(a.dtype), a, equal_nan=True):
            return a16
    return a
