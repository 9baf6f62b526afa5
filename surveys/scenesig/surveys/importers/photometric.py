"""Photometric transforms of day images: a night-like replay of a real run, and two milder looks.

``night`` is **not** real night: a day image has no street lamps, headlight cone, lit windows or
black sky, so the scene's structure and shadows stay the day's. What it changes is what a camera does
in the dark, the part that hurts point features: an exposure ~2.7 stops short (``gain``), a tone
curve that crushes shadows (``gamma`` applied to the darkened linear intensity), a cold cast (``tint``,
B G R gains), long-exposure blur (``blur_px``) and the sensor noise of a high gain (``noise`` DN,
Gaussian, per pixel and channel), then 8-bit quantisation. ``dusk`` (1.3 stops short) and ``haze``
(lifted shadows, soft, low contrast) use the same operations with other settings. Deterministic:
frame ``i`` uses a generator seeded by ``(seed, i)``.
"""
from __future__ import annotations

import numpy as np

__all__ = ["NIGHT", "DUSK", "HAZE", "PRESETS", "darken", "photometric_transform"]

NIGHT = {"gain": 0.15, "gamma": 1.4, "tint": (1.0, 0.85, 0.7), "blur_px": 0.8, "noise": 3.0, "seed": 0}
DUSK = {"gain": 0.4, "gamma": 1.2, "tint": (1.0, 0.95, 0.9), "blur_px": 0.5, "noise": 2.0, "seed": 7}
HAZE = {"gain": 1.0, "gamma": 0.7, "tint": (0.95, 1.0, 1.0), "blur_px": 1.2, "noise": 1.5, "seed": 11}
PRESETS = {"night": NIGHT, "dusk": DUSK, "haze": HAZE}


def darken(image: np.ndarray, index: int = 0, config: dict | None = None) -> np.ndarray:
    """The darkened uint8 copy of ``image`` (BGR or grey; see the module docstring; ``config`` overrides
    :data:`NIGHT`)."""
    import cv2

    from ..settings import merge_settings

    c = merge_settings(NIGHT, config, "photometric")
    # the tone change is pointwise per channel: one 256-entry table per channel instead of pow() per pixel
    x = np.arange(256, dtype=np.float64) / 255.0
    lin = x[None, :] ** 2.2 * float(c["gain"]) * np.asarray(c["tint"], float)[:, None]  # linear light, darkened
    lut = (np.clip(lin, 0, 1) ** (float(c["gamma"]) / 2.2) * 255.0).astype(np.float32)  # steeper curve
    img = image if image.ndim == 3 else image[:, :, None]
    out = np.stack([lut[k % 3][img[:, :, k]] for k in range(img.shape[2])], axis=2)
    if c["blur_px"] > 0:
        out = cv2.GaussianBlur(out, (0, 0), float(c["blur_px"])).reshape(out.shape)
    rng = np.random.default_rng([int(c["seed"]), int(index)])
    out += rng.standard_normal(out.shape, dtype=np.float32) * np.float32(c["noise"])
    out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return out if image.ndim == 3 else out[:, :, 0]


def photometric_transform(spec: str | dict = "night"):
    """``(f(index, image) -> image, description)`` for a preset name (:data:`PRESETS`) or a dict over :data:`NIGHT`."""
    if isinstance(spec, str):
        if spec not in PRESETS:
            raise ValueError(f"unknown photometric transform {spec!r} ({', '.join(PRESETS)})")
        c, label = dict(PRESETS[spec]), spec
    else:
        from ..settings import merge_settings

        c, label = merge_settings(NIGHT, spec, "photometric"), "custom"

    def f(index: int, image: np.ndarray) -> np.ndarray:
        return darken(image, index, c)

    desc = (f"photometric {label} (day image darkened: gain {c['gain']}, gamma {c['gamma']}, BGR tint "
            f"{tuple(c['tint'])}, blur {c['blur_px']} px, noise {c['noise']} DN, seed {c['seed']}; not real night)")
    return f, desc
