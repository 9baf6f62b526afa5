"""A procedural synthetic place: one scene under many appearance conditions, with known alignment.

Used by the tests (a classifier mined on some conditions must fire at the right spot on a
held-out one) and as the image source of the speed benchmark when the survey simulator is not
installed.  The scene is a fixed random layout of "structures" -- filled rectangles (windows,
walls), vertical bars (trunks, poles), discs (canopies) and line segments -- over smooth
low-frequency shading; a *condition* re-renders it with a random global gamma, contrast, colour
cast, a shading ramp (sun direction), blur, sensor noise, and a small known shift of the camera.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["synthetic_scene", "synthetic_place"]


def synthetic_scene(width: int, height: int, seed: int = 0, n_structures: int | None = None):
    """Render the condition-free scene (BGR float32 in [0, 1]), larger than the view by a margin
    so that shifted views stay inside it.  Returns (scene, margin)."""
    rng = np.random.default_rng(seed)
    margin = max(16, int(0.1 * width))
    W, H = width + 2 * margin, height + 2 * margin
    base = rng.random((max(2, H // 32), max(2, W // 32), 3)).astype(np.float32)
    img = cv2.resize(base, (W, H), interpolation=cv2.INTER_CUBIC) * 0.4 + 0.3
    n = n_structures or max(12, (W * H) // 3000)
    for _ in range(n):
        col = tuple(float(c) for c in rng.random(3))
        kind = rng.integers(4)
        x, y = int(rng.integers(0, W)), int(rng.integers(0, H))
        if kind == 0:      # rectangle (window / wall patch)
            w, h = int(rng.integers(8, W // 6)), int(rng.integers(8, H // 5))
            cv2.rectangle(img, (x, y), (x + w, y + h), col, -1)
            if rng.random() < 0.5:
                cv2.rectangle(img, (x + 3, y + 3), (x + w - 3, y + h - 3),
                              tuple(1 - c for c in col), 2)
        elif kind == 1:    # vertical bar (trunk / pole)
            w = int(rng.integers(3, 14))
            cv2.rectangle(img, (x, y), (x + w, min(H, y + int(rng.integers(H // 4, H)))), col, -1)
        elif kind == 2:    # disc (canopy / sign)
            cv2.circle(img, (x, y), int(rng.integers(5, H // 6)), col, -1)
        else:              # line segment (edge / cable)
            x2, y2 = x + int(rng.integers(-W // 4, W // 4)), y + int(rng.integers(-H // 4, H // 4))
            cv2.line(img, (x, y), (x2, y2), col, int(rng.integers(1, 4)))
    # Fine texture so that flat regions are not perfectly flat.
    img += rng.normal(0, 0.02, img.shape).astype(np.float32)
    return np.clip(img, 0, 1), margin


def synthetic_place(n: int, width: int = 640, height: int = 480, seed: int = 0,
                    max_shift: float = 12.0, strength: float = 1.0):
    """Views of one synthetic place under ``n`` appearance conditions.

    Parameters
    ----------
    n : int
        Number of conditions (views).
    width, height : int
        View size in pixels.
    seed : int
        Scene and conditions seed (the scene depends on ``seed`` only, conditions on ``seed`` and
        the view index).
    max_shift : float
        Largest camera shift (pixels) of a view relative to view 0 (view 0 is unshifted).
    strength : float
        Scales the photometric changes (0: identical appearance).

    Returns
    -------
    images : list of ndarray
        BGR uint8 views.
    offsets : ndarray, shape (n, 2)
        A scene point at (x, y) in view 0 appears at (x + dx, y + dy) in view i.
    """
    scene, margin = synthetic_scene(width, height, seed)
    images, offsets = [], []
    for i in range(n):
        rng = np.random.default_rng([seed, i + 1])
        dx, dy = (0.0, 0.0) if i == 0 else tuple(rng.uniform(-max_shift, max_shift, 2))
        # View i shows the scene translated by (dx, dy): crop starting at margin - d.
        M = np.float32([[1, 0, dx - margin], [0, 1, dy - margin]])
        v = cv2.warpAffine(scene, M, (width, height), flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REFLECT)
        s = strength if i > 0 else 0.0
        ramp = np.linspace(-1, 1, width, dtype=np.float32)[None, :] * rng.uniform(-0.25, 0.25) * s
        v = v * (1 + ramp[:, :, None])
        v = v * (1 + s * rng.uniform(-0.2, 0.2, 3)[None, None, :])
        m = v.mean()
        v = m + (1 + s * rng.uniform(-0.4, 0.3)) * (v - m)
        v = np.clip(v, 0, 1) ** float(np.exp(s * rng.uniform(-0.5, 0.5)))
        if s > 0 and rng.random() < 0.5:
            v = cv2.GaussianBlur(v, (0, 0), 0.5 + s * rng.random())
        v = v + rng.normal(0, 0.02 * s, v.shape).astype(np.float32)
        images.append(np.clip(v * 255, 0, 255).astype(np.uint8))
        offsets.append((dx, dy))
    return images, np.asarray(offsets, dtype=float)
