"""Compact whole-image descriptors for coarse place retrieval (global localisation).

The localiser needs to find, among all places of a map, the few a live image may show before it
knows where it is.  Scene signatures are searched per place, so running every place's bank over an
image would cost ``places x`` a detection; instead every place stores a compact descriptor of its
training images (one per training run, so night and snow are represented as well as day) and the
live image is compared with all of them at once -- a dot product per stored descriptor.

Two descriptors are provided (``kind``):

``"hog"`` (default)
    FHOG (:func:`scenesig.signatures.hog.fhog`, the features the banks themselves use) of the gray image
    area-resized to ``width`` pixels, at ``cell`` pixels per cell; the cells' 31-vectors are
    flattened, the mean removed and the result L2-normalised.  Gradient orientation survives
    illumination changes better than intensity.
``"thumbnail"``
    SeqSLAM's patch-normalised thumbnail (Milford & Wyeth 2012): the image area-resized to
    ``width`` pixels, every ``patch`` x ``patch`` block normalised to zero mean and unit variance,
    then L2-normalised.

Chosen by measurement (``benchmarks/places.py``; see ``docs/global_localisation.md``).  Stored as
int8 (a descriptor is unit-norm; 127 levels keep cosine similarities to ~1e-3), so a place with six
training runs costs 6 x 1.5 kB.
"""
from __future__ import annotations

import base64

import cv2
import numpy as np

from scenesig.surveys.settings import merge_settings

from .hog import fhog

__all__ = ["default_config", "describe", "quantise", "dequantise", "encode", "decode", "similarity"]

default_config = {
    "kind": "hog",
    "width": 64,          # image width after area resizing (pixels); height keeps the aspect ratio
    "cell": 8,            # FHOG cell ("hog")
    "patch": 8,           # normalisation block ("thumbnail")
}


def _resize(image: np.ndarray, width: int) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ValueError(f"expected a gray or BGR image, got shape {img.shape}")
    h, w = img.shape
    height = max(2, int(round(h * width / w)))
    return cv2.resize(img, (int(width), height), interpolation=cv2.INTER_AREA)


def describe(image: np.ndarray, config: dict | None = None) -> np.ndarray:
    """The unit-norm float32 descriptor of one gray or BGR image."""
    cfg = merge_settings(default_config, config, "descriptor")
    small = _resize(image, cfg["width"])
    if cfg["kind"] == "hog":
        v = fhog(small, cell=int(cfg["cell"])).ravel().astype(np.float32)
    elif cfg["kind"] == "thumbnail":
        p = int(cfg["patch"])
        h, w = (small.shape[0] // p) * p, (small.shape[1] // p) * p
        blocks = small[:h, :w].astype(np.float32).reshape(h // p, p, w // p, p).transpose(0, 2, 1, 3)
        blocks = blocks.reshape(h // p, w // p, p * p)
        blocks = (blocks - blocks.mean(axis=2, keepdims=True)) / (blocks.std(axis=2, keepdims=True) + 1e-3)
        v = blocks.ravel()
    else:
        raise ValueError(f"unknown descriptor kind {cfg['kind']!r}; choose 'hog' or 'thumbnail'")
    v = v - v.mean()
    n = float(np.linalg.norm(v))
    return (v / n if n > 0 else v).astype(np.float32)


def quantise(d: np.ndarray) -> np.ndarray:
    """Unit-norm descriptor(s) -> int8 (the scale is irrelevant to cosine similarity)."""
    d = np.asarray(d, np.float32)
    m = float(np.abs(d).max()) if d.size else 0.0
    return np.round(d / m * 127.0).astype(np.int8) if m > 0 else np.zeros(d.shape, np.int8)


def dequantise(q: np.ndarray) -> np.ndarray:
    """int8 descriptor(s) (rows) -> unit-norm float32 rows."""
    d = np.asarray(q, np.float32).reshape(len(q), -1) if np.ndim(q) > 1 else np.asarray(q, np.float32)[None]
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(n > 0, n, 1.0)


def encode(descriptors: np.ndarray) -> dict:
    """JSON-ready form of a place's (k, d) descriptors: int8 bytes in base64 plus the shape."""
    q = np.stack([quantise(d) for d in np.atleast_2d(descriptors)])
    return {"shape": list(q.shape), "int8": base64.b64encode(q.tobytes()).decode("ascii")}


def decode(entry: dict) -> np.ndarray:
    """(k, d) unit-norm float32 descriptors from :func:`encode`'s output."""
    shape = tuple(int(s) for s in entry["shape"])
    raw = np.frombuffer(base64.b64decode(entry["int8"]), dtype=np.int8)
    if raw.size != int(np.prod(shape)):
        raise ValueError(f"descriptor has {raw.size} values, its shape {list(shape)} needs {int(np.prod(shape))}")
    return dequantise(raw.reshape(shape))


def similarity(query: np.ndarray, stored: np.ndarray, owner: np.ndarray, n_owners: int) -> np.ndarray:
    """Cosine similarity of a query to each owner: the best over that owner's stored descriptors.

    ``stored`` (m, d) unit rows, ``owner`` (m,) their owner index in ``0..n_owners-1``; owners without
    a descriptor get -inf.
    """
    s = stored @ np.asarray(query, np.float32)
    out = np.full(n_owners, -np.inf, np.float32)
    np.maximum.at(out, owner, s)
    return out
