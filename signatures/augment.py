"""Synthetic appearance change: photometrically altered copies of an image.

Where a place has been seen under few conditions -- one summer image of a GRIEF ``sequence`` place,
or a map built from one to three survey runs -- mining gets more appearances to generalise over from
altered copies of the images it has (gamma, contrast, colour casts, blur, noise, desaturation and a
synthetic "snow"), each with a small known horizontal shift that stands in for a heading change.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["augment"]


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
