"""A photometric transform that darkens a day image towards night (for a night-like replay of a real run).

It is **not** real night: a day image has no street lamps, headlight cone, lit windows or black sky,
so the scene's structure and shadows stay the day's. What it changes is what a camera does in the
dark, the part that breaks point features: an exposure ~2.7 stops short (``gain``), a tone curve that
crushes shadows (``gamma`` on the darkened linear intensity), a cold cast (``tint``, B G R gains as
a tungsten-balanced sensor shows moonlight and sodium-free LED light), long-exposure blur
(``blur_px``) and the sensor noise of a high gain (``noise`` DN, Gaussian, per pixel and channel),
then 8-bit quantisation. Deterministic: frame ``i`` uses a generator seeded by ``(seed, i)``.
"""
from __future__ import annotations

import numpy as np

__all__ = ["NIGHT", "darken", "night_transform"]

NIGHT = {"gain": 0.15, "gamma": 1.4, "tint": (1.0, 0.85, 0.7), "blur_px": 0.8, "noise": 3.0, "seed": 0}


def darken(image: np.ndarray, index: int = 0, conf: dict | None = None) -> np.ndarray:
    """The darkened BGR uint8 copy of ``image`` (see the module docstring; ``conf`` overrides :data:`NIGHT`)."""
    import cv2

    c = {**NIGHT, **(conf or {})}
    x = image.astype(np.float32) / 255.0
    lin = np.power(x, 2.2)                                      # sRGB-ish to linear light
    lin *= np.float32(c["gain"]) * np.asarray(c["tint"], np.float32)
    out = np.power(np.clip(lin, 0, 1), np.float32(c["gamma"] / 2.2)) * 255.0  # steeper tone curve: crushed shadows
    if c["blur_px"] > 0:
        out = cv2.GaussianBlur(out, (0, 0), float(c["blur_px"]))
    rng = np.random.default_rng([int(c["seed"]), int(index)])
    out += rng.normal(0.0, float(c["noise"]), out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def night_transform(conf: dict | None = None):
    """``f(index, image) -> image`` for the importers' ``transform`` conf key, and its description."""
    c = {**NIGHT, **(conf or {})}

    def f(index: int, image: np.ndarray) -> np.ndarray:
        return darken(image, index, c)

    desc = ("photometric night (day image darkened: gain {gain}, gamma {gamma}, BGR tint {tint}, blur {blur_px} px, "
            "noise {noise} DN, seed {seed}; not real night)").format(**c)
    return f, desc
