"""Monte-Carlo sensed images cut from geo-referenced tiles (Jin et al. 2016, §4.3).

Each trial is a ``400 x 300`` sensed image whose centre lies at a random point of a random tile,
scaled by ``s ~ U[0.9, 1.1]`` (objects appear ``s`` times their size on the tile) and rotated by
``theta ~ U[-10 deg, 10 deg]`` about its centre, then given a random photometric change.  The
exact sensed -> tile affine is known, so is the truth of the centre.

Photometric change (:data:`PHOTOMETRIC`; every trial gets all of them, each with a random strength
drawn uniformly from its range; the ranges that include the identity make some trials milder):

* colour cast -- per-channel gain ``U[0.75, 1.25]`` and offset ``U[-20, 20]`` gray levels;
* gamma ``U[0.6, 1.7]``;
* contrast -- about the image mean, factor ``U[0.7, 1.3]``;
* haze -- ``I t + A (1 - t)`` with transmission ``t ~ U[0.65, 1.0]`` and a bluish-white airlight
  ``A ~ U[170, 240]`` (blue +10);
* shadow pattern -- smooth random blobs (a Gaussian-blurred random field, sigma 25-60 px, over about
  a third of the image, soft-edged) darkened by a factor ``1 - depth``, ``depth ~ U[0.0, 0.4]``;
* sensor noise -- Gaussian, sigma ``U[0, 4]`` gray levels.

Trial k of seed S draws from ``numpy.random.default_rng([S, k])``, so a trial does not depend on
how many came before it or which methods run.
"""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from scenesig.surveys.io import atomic_path, atomic_write_text
from scenesig.surveys.settings import merge_settings

__all__ = ["PHOTOMETRIC", "GEOMETRY", "Trial", "make_trial", "make_trials", "photometric_change",
           "sensed_centre", "cut_sensed", "write_sequence"]

#: Geometry of a sensed image (Jin et al. 2016's protocol).
GEOMETRY = {"size": (400, 300), "scale": (0.9, 1.1), "rotation_deg": (-10.0, 10.0)}

#: Ranges of the photometric change (see module docstring).
PHOTOMETRIC = {
    "gain": (0.75, 1.25),
    "offset": (-20.0, 20.0),
    "gamma": (0.6, 1.7),
    "contrast": (0.7, 1.3),
    "haze_transmission": (0.65, 1.0),
    "haze_airlight": (170.0, 240.0),
    "shadow_depth": (0.0, 0.4),
    "shadow_sigma_px": (25.0, 60.0),
    "shadow_cover": 0.35,
    "noise_sigma": (0.0, 4.0),
}


def sensed_centre(shape) -> np.ndarray:
    """Centre (x, y) of an image of shape (H, W, ...) in pixel coordinates: ((W-1)/2, (H-1)/2)."""
    return np.array([(shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0])


@dataclass
class Trial:
    """One Monte-Carlo trial.

    Attributes
    ----------
    index : int
    tile : int
        Index of the tile in the tile set.
    image : ndarray (H, W, 3) uint8
        The sensed image.
    affine : ndarray (2, 3)
        Exact sensed -> tile pixel transform.
    centre : ndarray (2,)
        Truth: where the sensed centre lies on the tile (pixels).
    scale, rotation_deg : float
    photometric : dict
        The drawn photometric parameters (empty when none were applied).
    """

    index: int
    tile: int
    image: np.ndarray
    affine: np.ndarray
    centre: np.ndarray
    scale: float
    rotation_deg: float
    photometric: dict = field(default_factory=dict)


def _affine(centre, scale: float, rotation_deg: float, size) -> np.ndarray:
    """Sensed -> tile affine: tile = centre + (1/scale) R(theta) (x - sensed centre)."""
    th = math.radians(rotation_deg)
    L = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]) / scale
    c = sensed_centre((size[1], size[0]))
    return np.hstack([L, (np.asarray(centre, float) - L @ c)[:, None]])


def cut_sensed(tile_image: np.ndarray, centre, scale: float, rotation_deg: float,
               size=GEOMETRY["size"]) -> tuple[np.ndarray, np.ndarray]:
    """The sensed view of a tile (no photometric change) and its sensed -> tile affine."""
    A = _affine(centre, scale, rotation_deg, size)
    img = cv2.warpAffine(tile_image, A, tuple(int(v) for v in size),
                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REFLECT)
    return img, A


def _footprint_margin(size, scale: float, rotation_deg: float) -> tuple[float, float]:
    """Half extent (x, y) on the tile of a rotated, scaled sensed image."""
    w, h = size
    th = math.radians(rotation_deg)
    c, s = abs(math.cos(th)), abs(math.sin(th))
    return (w * c + h * s) / (2 * scale), (w * s + h * c) / (2 * scale)


def photometric_change(image: np.ndarray, rng: np.random.Generator,
                       ranges: dict | None = None) -> tuple[np.ndarray, dict]:
    """Apply a random colour cast, gamma, contrast, haze, shadow pattern and noise.

    Returns the changed image and the drawn parameters.
    """
    r = merge_settings(PHOTOMETRIC, ranges, "photometric")
    h, w = image.shape[:2]
    p = {"gain": rng.uniform(*r["gain"], size=3), "offset": rng.uniform(*r["offset"], size=3),
         "gamma": rng.uniform(*r["gamma"]), "contrast": rng.uniform(*r["contrast"]),
         "haze_t": rng.uniform(*r["haze_transmission"]),
         "airlight": rng.uniform(*r["haze_airlight"]),
         "shadow_depth": rng.uniform(*r["shadow_depth"]),
         "shadow_sigma": rng.uniform(*r["shadow_sigma_px"]),
         "noise": rng.uniform(*r["noise_sigma"])}
    img = image.astype(np.float32)
    img = img * p["gain"][None, None, :].astype(np.float32) + p["offset"][None, None, :]
    img = 255.0 * (np.clip(img, 0, 255) / 255.0) ** p["gamma"]
    m = img.mean()
    img = m + p["contrast"] * (img - m)
    air = np.array([p["airlight"], p["airlight"], p["airlight"]], np.float32)
    air[0] += 10.0                                                   # BGR: bluish haze
    img = img * p["haze_t"] + air[None, None, :] * (1 - p["haze_t"])
    field_ = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0),
                              p["shadow_sigma"])
    field_ /= max(float(field_.std()), 1e-6)
    cut = float(np.quantile(field_, 1 - r["shadow_cover"]))
    shade = np.clip(field_ - cut, 0, 1)                               # soft-edged blobs
    img = img * (1 - p["shadow_depth"] * shade)[:, :, None]
    img = img + rng.normal(0, p["noise"], img.shape).astype(np.float32)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return out, {k: (v.tolist() if isinstance(v, np.ndarray) else float(v)) for k, v in p.items()}


def make_trial(tile_images, index: int, seed: int, photometric: bool = True,
               size=GEOMETRY["size"], scale_range=GEOMETRY["scale"],
               rotation_range=GEOMETRY["rotation_deg"], ranges: dict | None = None) -> Trial:
    """Trial ``index`` of seed ``seed`` over the given tile images (BGR uint8 list).

    ``ranges`` overrides entries of :data:`PHOTOMETRIC`.
    """
    rng = np.random.default_rng([int(seed), int(index)])
    t = int(rng.integers(len(tile_images)))
    tile = tile_images[t]
    scale = float(rng.uniform(*scale_range))
    rot = float(rng.uniform(*rotation_range))
    mx, my = _footprint_margin(size, scale, rot)
    H, W = tile.shape[:2]
    if W - 1 < 2 * mx + 2 or H - 1 < 2 * my + 2:
        raise ValueError(f"tile {t} ({W}x{H}) is too small for a {size[0]}x{size[1]} sensed image")
    centre = np.array([rng.uniform(mx + 1, W - 2 - mx), rng.uniform(my + 1, H - 2 - my)])
    img, A = cut_sensed(tile, centre, scale, rot, size)
    params = {}
    if photometric:
        img, params = photometric_change(img, rng, ranges)
    return Trial(int(index), t, img, A, centre, scale, rot, params)


def make_trials(tile_images, n: int, seed: int, photometric: bool = True,
                ranges: dict | None = None):
    """Trials 0..n-1 of ``seed`` (a generator: each trial's image is made when it is needed)."""
    for k in range(int(n)):
        yield make_trial(tile_images, k, seed, photometric, ranges=ranges)


def write_sequence(tiles, out_dir, n: int = 20, seed: int = 0, step_m: float = 8.0,
                   photometric: bool = True) -> list[dict]:
    """Write a synthetic UAV sequence: ``n`` sensed images along a flight of straight legs, and
    ``truth.csv`` (image, lat, lon, tile, x, y, scale, rotation_deg).

    The flight starts at a random point and heading; consecutive images are ``step_m`` apart.  Each
    image is cut, as in the Monte-Carlo protocol, from the tile that holds its whole footprint; when
    the next footprint fits no single tile the flight turns to a random new heading at the last
    image (and starts afresh elsewhere if no heading works).

    Parameters
    ----------
    tiles : aerial.geo.TileSet
    out_dir : path
    n : int
    seed : int
    step_m : float
    photometric : bool

    Returns
    -------
    list of dict
        The rows of ``truth.csv``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([int(seed), 7])
    lat = [v for t in tiles for v in (t.top_left[0], t.bottom_right[0])]
    lon = [v for t in tiles for v in (t.top_left[1], t.bottom_right[1])]
    lo = tiles.latlon_to_local([min(lat), min(lon)])
    hi = tiles.latlon_to_local([max(lat), max(lon)])
    size = GEOMETRY["size"]
    rows, pos, heading, tries, last, misses = [], None, 0.0, 0, None, 0
    while len(rows) < n:
        tries += 1
        if tries > 200 * n:
            raise ValueError(f"could not place {n} sensed images on the tiles of {tiles.root}")
        if pos is None:
            pos = rng.uniform(lo, hi)
            heading = rng.uniform(0, 2 * np.pi)
        ll = tiles.local_to_latlon(pos)
        scale = float(rng.uniform(*GEOMETRY["scale"]))
        rot = float(rng.uniform(*GEOMETRY["rotation_deg"]))
        mx, my = _footprint_margin(size, scale, rot)
        placed = False
        for ti, t in enumerate(tiles):
            if not bool(t.contains(ll)):
                continue
            img = t.image()
            x, y = t.latlon_to_pixel(ll)
            if mx + 1 <= x <= img.shape[1] - 2 - mx and my + 1 <= y <= img.shape[0] - 2 - my:
                sensed, _ = cut_sensed(img, (x, y), scale, rot, size)
                if photometric:
                    sensed, _ = photometric_change(sensed, rng)
                name = f"{len(rows):04d}.png"
                with atomic_path(out / name) as tmp:
                    cv2.imwrite(str(tmp), sensed)
                rows.append({"image": name, "lat": float(ll[0]), "lon": float(ll[1]),
                             "tile": t.name, "x": float(x), "y": float(y), "scale": scale,
                             "rotation_deg": rot})
                placed = True
                break
        if placed:
            last, misses = pos, 0
        elif rows and misses < 20:
            # The footprint left the tiles: turn at the last image and fly on from there.
            pos, heading, misses = last, rng.uniform(0, 2 * np.pi), misses + 1
        else:
            pos, misses = None, 0                        # start a new line elsewhere
            continue
        pos = pos + step_m * np.array([np.cos(heading), np.sin(heading)])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(out / "truth.csv", buf.getvalue())
    return rows
