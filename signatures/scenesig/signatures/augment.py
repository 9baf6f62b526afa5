"""Synthetic appearance change: photometrically altered copies of an image.

Where a place has been seen under few conditions -- one summer image of a GRIEF ``sequence`` place,
or a map built from one to three survey runs -- mining gets more appearances to generalise over from
altered copies of the images it has (gamma, contrast, colour casts, blur, noise, desaturation and a
synthetic "snow"), each with a small known horizontal shift that stands in for a heading change.
:func:`synthesise` appends such copies to a place's real images (heading benchmark, webcam benchmark,
map builder); :func:`relight` imitates night, fog and snow more strongly, for the single-experience
settings that ask for it (:mod:`scenesig.signatures.experience`).
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["augment", "synthesise", "relight", "CONDITIONS"]

#: Synthetic conditions :func:`relight` imitates.
CONDITIONS = ("night", "fog", "snow")


def augment(image: np.ndarray, rng: np.random.Generator, max_shift: float = 24.0):
    """One photometrically (and slightly geometrically) altered copy of a BGR image.

    Returns the copy and its horizontal shift (a point at x appears at x + shift).  The changes
    imitate what separates seasons and times of day: global gamma / contrast / colour cast, blur,
    sensor noise, desaturation, and "snow" -- smooth, bright regions pushed towards white and dark
    regions lifted, as snow cover and overcast light do.  The shift mimics heading changes; the
    uncovered border is filled by edge replication.
    """
    img = image.astype(np.float32) / 255.0
    if img.ndim == 2:
        img = img[:, :, None].repeat(3, axis=2)
    # Colour cast and desaturation.
    gray = img.mean(axis=2, keepdims=True)
    sat = rng.uniform(0.2, 1.2)
    img = gray + sat * (img - gray)
    img *= rng.uniform(0.85, 1.15, size=3)[None, None, :]
    # Snow: whiten where the image is smooth (low local variance) and bright, lift shadows.
    if rng.random() < 0.5:
        g = cv2.cvtColor(np.clip(img, 0, 1), cv2.COLOR_BGR2GRAY)
        mu = cv2.GaussianBlur(g, (0, 0), 3)
        var = cv2.GaussianBlur(g * g, (0, 0), 3) - mu * mu
        smooth = np.exp(-var / (rng.uniform(0.002, 0.01)))
        amount = rng.uniform(0.3, 0.9) * smooth * np.clip(mu * 1.5, 0, 1)
        img = img + amount[:, :, None] * (1.0 - img)
        img = 0.15 * rng.random() + (1 - 0.15 * rng.random()) * img
    # Gamma and contrast.
    img = np.clip(img, 0, 1) ** rng.uniform(0.5, 2.0)
    m = img.mean()
    img = m + rng.uniform(0.6, 1.4) * (img - m)
    # Blur and noise.
    if rng.random() < 0.5:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 1.5))
    img = img + rng.normal(0, rng.uniform(0.0, 0.04), img.shape).astype(np.float32)
    out = np.clip(img * 255.0, 0, 255).astype(np.uint8)
    shift = float(rng.uniform(-max_shift, max_shift))
    if abs(shift) >= 0.5:
        M = np.float32([[1, 0, shift], [0, 1, 0]])
        out = cv2.warpAffine(out, M, (out.shape[1], out.shape[0]), borderMode=cv2.BORDER_REPLICATE)
    return out, shift


def _smooth_bright(img: np.ndarray, sigma: float = 3.0):
    """Local mean and variance of the gray image (float BGR in [0, 1])."""
    g = cv2.cvtColor(np.clip(img, 0, 1), cv2.COLOR_BGR2GRAY)
    mu = cv2.GaussianBlur(g, (0, 0), sigma)
    var = np.maximum(cv2.GaussianBlur(g * g, (0, 0), sigma) - mu * mu, 0.0)
    return g, mu, var


def _sky(img: np.ndarray) -> np.ndarray:
    """Soft sky mask: bright, smooth pixels, more likely higher up (float in [0, 1])."""
    h = img.shape[0]
    _, mu, var = _smooth_bright(img, 4.0)
    prior = np.clip(1.2 - 2.0 * np.arange(h, dtype=np.float32) / h, 0, 1)[:, None]
    return np.clip((mu - 0.45) / 0.3, 0, 1) * np.exp(-var / 0.02) * prior


def _night(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Night: little ambient light, a dark sky, a few warm light sources that light their
    surroundings, and the sensor noise of a long exposure."""
    h, w = img.shape[:2]
    lin = img ** 2.2
    ambient = rng.uniform(0.01, 0.06)
    lin = lin * ambient * np.array([1.15, 1.0, 0.85], np.float32)[None, None, :] \
        * (1.0 - 0.9 * _sky(img))[:, :, None]
    # street lamps: warm Gaussian pools, lighting the scene multiplicatively and glowing a little
    light = np.zeros((h, w), np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for _ in range(int(rng.integers(2, 7))):
        cx, cy = rng.uniform(0, w), rng.uniform(0.2 * h, h)
        s = rng.uniform(0.04, 0.15) * w
        light += rng.uniform(0.3, 1.5) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    warm = np.array([0.45, 0.75, 1.0], np.float32)[None, None, :]    # BGR: orange sodium light
    lin = lin + (img ** 2.2) * light[:, :, None] * warm * rng.uniform(0.2, 0.6) \
        + 0.05 * light[:, :, None] * warm
    out = np.clip(lin, 0, 1) ** (1 / 2.2) * rng.uniform(0.8, 1.3)
    out = out + rng.normal(0, rng.uniform(0.01, 0.04), out.shape).astype(np.float32)
    if rng.random() < 0.7:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.6, 1.4))
    return out


def _fog(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Fog (Koschmieder): ``I = J t + A (1 - t)``, transmission falling with a depth proxy that
    grows towards the top of the image and in the sky."""
    h = img.shape[0]
    depth = np.clip(1.0 - np.arange(h, dtype=np.float32) / h, 0, 1)[:, None] ** rng.uniform(0.5, 1.5)
    depth = np.maximum(depth, _sky(img))
    t = np.exp(-rng.uniform(1.0, 3.5) * depth) * rng.uniform(0.6, 1.0)
    airlight = rng.uniform(0.6, 0.9) * np.array(rng.uniform(0.95, 1.05, 3), np.float32)
    out = img * t[:, :, None] + airlight[None, None, :] * (1.0 - t[:, :, None])
    return cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 2.0))


def _snow(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Snow cover: texture on the ground and on smooth or bright surfaces flattened to white, the
    rest (trunks, walls under eaves) kept and darkened by contrast with the snow; optional falling
    flakes."""
    h, w = img.shape[:2]
    g, mu, var = _smooth_bright(img, 2.0)
    ground = np.clip((np.arange(h, dtype=np.float32) / h - rng.uniform(0.3, 0.6)) / 0.2, 0, 1)[:, None]
    flat = np.exp(-var / rng.uniform(0.003, 0.02))
    cover = np.clip(rng.uniform(0.5, 1.0) * np.maximum(ground * (0.4 + 0.6 * flat), flat * mu * 1.5), 0, 1)
    white = rng.uniform(0.8, 1.0)
    out = img * (1 - cover[:, :, None]) + white * cover[:, :, None]
    out = out * rng.uniform(0.7, 1.0)
    if rng.random() < 0.4:
        flakes = (rng.random((h, w)) < rng.uniform(0.002, 0.01)).astype(np.float32)
        flakes = cv2.GaussianBlur(flakes, (0, 0), rng.uniform(0.6, 1.5)) * 4.0
        out = out + np.clip(flakes, 0, 1)[:, :, None]
    return out


def relight(image: np.ndarray, condition: str, rng: np.random.Generator) -> np.ndarray:
    """A copy of a BGR daytime image as if seen at night, in fog or under snow (uint8 BGR).

    Crude physical models, not renderings: what matters for mining is that gradients that do not
    survive the condition (sky edges at night, distant texture in fog, ground texture under snow)
    are missing in some training copies, so the filters that converge rely on what does survive.
    """
    if condition not in CONDITIONS:
        raise ValueError(f"unknown condition {condition!r}; choose from {', '.join(CONDITIONS)}")
    img = image.astype(np.float32) / 255.0
    if img.ndim == 2:
        img = img[:, :, None].repeat(3, axis=2)
    out = {"night": _night, "fog": _fog, "snow": _snow}[condition](img, rng)
    return np.clip(out * 255.0, 0, 255).astype(np.uint8)


def synthesise(images, offsets, n_copies: int, rng: np.random.Generator, max_shift: float = 24.0,
               conditions=()):
    """The images with ``n_copies`` altered copies appended (:func:`augment`, the images in turn).

    Parameters
    ----------
    images : list of ndarray
        The real images of a place (BGR or gray).
    offsets : sequence of (dx, dy)
        Their alignment offsets; a copy's offset is its source's plus its known shift.
    n_copies : int
    rng : numpy Generator
    max_shift : float
        Largest horizontal shift of a copy (pixels of ``images``).
    conditions : sequence of str
        :func:`relight` conditions; copy k is relit to ``conditions[k % (len + 1)]`` before the
        generic alterations, and one copy in ``len + 1`` is only altered (empty: none relit).

    Returns
    -------
    images, offsets : list
        Real images first, in their order, then the copies.
    """
    images, offsets = list(images), [list(map(float, o)) for o in offsets]
    n = len(images)
    if n == 0:
        raise ValueError("nothing to synthesise from: no image")
    cycle = [None, *conditions]
    for k in range(int(n_copies)):
        src = images[k % n]
        cond = cycle[k % len(cycle)]
        if cond is not None:
            gray = src.ndim == 2
            src = relight(src, cond, rng)
            if gray:
                src = cv2.cvtColor(src, cv2.COLOR_BGR2GRAY)
        copy, shift = augment(src, rng, max_shift)
        images.append(copy)
        offsets.append([offsets[k % n][0] + shift, offsets[k % n][1]])
    return images, offsets
