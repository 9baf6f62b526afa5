"""Deformed and recoloured Monte-Carlo trials (issue 38, point 2): what the point-set-domain stages
(:mod:`scenesig.aerial.psd`) are for.

The default trials (:func:`scenesig.aerial.trials.make_trial`) are exact similarity warps of a tile, so a
diffeomorphism has nothing to fit and no ground cover changes.  :func:`make_trial_variant` draws the
same tile, scale, rotation, centre and photometric change as the default trial of that index and seed
(the same generator, consumed in the same order), then adds

* ``deform`` -- the sensed image of a camera tilted by ``tau ~ U[0, 15] deg`` about a random axis in
  the image plane (focal length ``focal_px``; a homography between the ground and the sensed image),
  plus a smooth displacement field: ``bumps`` Gaussian bumps (width ``U[40, 100]`` px, random
  directions, largest displacement ``U[2, 10]`` px) standing in for relief and lens distortion.  A
  sensed pixel ``x`` lies on the tile at ``A(g(x + d(x)) - g(0))`` (``d`` the field, ``g`` the tilt
  homography about the image centre, ``A`` the trial's similarity), which is exact truth for every
  pixel (:attr:`VariantTrial.to_tile`);
* ``recolour`` -- region-wise ground-cover change before the photometric change: the sensed view is
  split into colour clusters (k-means, ``clusters``) and whole clusters, until ``U[0.2, 0.5]`` of the
  image is covered, are given one new cover -- snow (bright, bluish, texture damped), fresh grass
  (green) or bare soil (brown) -- with soft edges.

The variant's own draws come from ``default_rng([seed, index, 38])``, so they never shift the draws
of the default protocol.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from scenesig.aerial.trials import GEOMETRY, Trial, _affine, _footprint_margin, photometric_change, sensed_centre
from scenesig.surveys.settings import merge_settings

__all__ = ["DEFORM", "RECOLOUR", "VariantTrial", "make_trial_variant", "Deformation", "recolour"]

#: Ranges of the geometric deformation (see module docstring).
DEFORM = {
    "tilt_deg": (0.0, 15.0),
    "focal_px": 500.0,              # ~44 deg horizontal field of view on the 400-px sensed image
    "bumps": 6,
    "bump_sigma_px": (40.0, 100.0),
    "displacement_px": (2.0, 10.0),
    "margin": 1.3,                  # the footprint margin grows by this factor (a tilted footprint is larger)
}

#: Ranges of the ground-cover change (see module docstring).
RECOLOUR = {
    "cover": (0.2, 0.5),
    "clusters": 6,
    "kinds": ("snow", "grass", "soil"),
    "edge_sigma_px": 3.0,
}

# BGR colours of the new covers and how much of the old texture survives
_COVERS = {"snow": ((238.0, 236.0, 230.0), 0.25), "grass": ((60.0, 150.0, 85.0), 0.5),
           "soil": ((70.0, 105.0, 140.0), 0.6)}


@dataclass
class Deformation:
    """Sensed -> tile map of a deformed trial: ``A(g(x + d(x)) - g(0))`` (module docstring)."""

    affine: np.ndarray               # the trial's similarity (sensed -> tile)
    centre: np.ndarray               # sensed image centre
    rotation: np.ndarray             # 3 x 3 tilt rotation
    focal: float
    bump_centres: np.ndarray         # (B, 2), relative to the sensed centre
    bump_vectors: np.ndarray         # (B, 2)
    bump_sigmas: np.ndarray          # (B,)

    def displacement(self, u: np.ndarray) -> np.ndarray:
        d2 = ((u[:, None, :] - self.bump_centres[None]) ** 2).sum(axis=2)
        return np.exp(-d2 / (2 * self.bump_sigmas[None] ** 2)) @ self.bump_vectors

    def _tilt(self, u: np.ndarray) -> np.ndarray:
        r = np.column_stack([u, np.full(len(u), self.focal)]) @ self.rotation.T
        return self.focal * r[:, :2] / r[:, 2:3]

    def __call__(self, xy) -> np.ndarray:
        xy = np.asarray(xy, float)
        u = xy.reshape(-1, 2) - self.centre
        g = self._tilt(u + self.displacement(u)) - self._tilt(np.zeros((1, 2)))
        out = (g + self.centre) @ self.affine[:, :2].T + self.affine[:, 2]
        return out.reshape(xy.shape)


@dataclass
class VariantTrial(Trial):
    """A :class:`~scenesig.aerial.trials.Trial` with exact per-pixel truth.

    ``to_tile(xy)`` maps sensed pixels to the tile (the trial's affine when not deformed);
    ``centre`` is ``to_tile`` of the sensed centre; ``variant`` records the drawn deformation and
    ground-cover change.
    """

    to_tile: object = None
    variant: dict = field(default_factory=dict)


def _rotation(axis_deg: float, tilt_deg: float) -> np.ndarray:
    a, t = math.radians(axis_deg), math.radians(tilt_deg)
    k = np.array([math.cos(a), math.sin(a), 0.0])
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * (K @ K)


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = 8) -> np.ndarray:
    """Labels of a small deterministic k-means (numpy, seeded) on rows of ``x``."""
    c = x[rng.choice(len(x), size=k, replace=False)].copy()
    lab = np.zeros(len(x), np.int64)
    for _ in range(iters):
        lab = ((x[:, None, :] - c[None]) ** 2).sum(axis=2).argmin(axis=1)
        for j in range(k):
            if np.any(lab == j):
                c[j] = x[lab == j].mean(axis=0)
    return lab


def recolour(image: np.ndarray, rng: np.random.Generator, ranges: dict | None = None) -> tuple[np.ndarray, dict]:
    """Region-wise ground-cover change of a BGR uint8 image (module docstring); returns the image and
    the drawn parameters (kind, target cover, covered fraction)."""
    r = merge_settings(RECOLOUR, ranges, "recolour")
    h, w = image.shape[:2]
    small = cv2.resize(image, (max(1, w // 4), max(1, h // 4)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 1.5).reshape(-1, 3).astype(np.float64)
    k = int(r["clusters"])
    lab = _kmeans(small, k, rng).reshape(max(1, h // 4), max(1, w // 4))
    target = float(rng.uniform(*r["cover"]))
    kind = str(r["kinds"][int(rng.integers(len(r["kinds"])))])
    mask = np.zeros(lab.shape, bool)
    for j in rng.permutation(k):
        if mask.mean() >= target:
            break
        mask |= lab == j
    soft = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    soft = np.clip(cv2.GaussianBlur(soft, (0, 0), float(r["edge_sigma_px"])), 0, 1)[:, :, None]
    colour, keep = _COVERS[kind]
    img = image.astype(np.float32)
    texture = img - cv2.GaussianBlur(img, (0, 0), 4.0)
    new = np.asarray(colour, np.float32)[None, None, :] + keep * texture
    out = np.clip(np.rint(img * (1 - soft) + new * soft), 0, 255).astype(np.uint8)
    return out, {"kind": kind, "cover_target": target, "covered": float(soft.mean())}


def make_trial_variant(tile_images, index: int, seed: int, deform: bool = False, recolour_: bool = False,
                       photometric: bool = True, deform_ranges: dict | None = None,
                       recolour_ranges: dict | None = None, size=GEOMETRY["size"]) -> VariantTrial:
    """Trial ``index`` of ``seed`` with the deformation and/or ground-cover change (module docstring).

    With neither, the image, truth and photometric parameters equal
    :func:`scenesig.aerial.trials.make_trial`'s.
    """
    dr = merge_settings(DEFORM, deform_ranges, "deform")
    rng = np.random.default_rng([int(seed), int(index)])
    own = np.random.default_rng([int(seed), int(index), 38])
    t = int(rng.integers(len(tile_images)))
    tile = tile_images[t]
    scale = float(rng.uniform(*GEOMETRY["scale"]))
    rot = float(rng.uniform(*GEOMETRY["rotation_deg"]))
    mx, my = _footprint_margin(size, scale, rot)
    if deform:
        extra = float(dr["displacement_px"][1]) / scale
        mx, my = mx * float(dr["margin"]) + extra, my * float(dr["margin"]) + extra
    H, W = tile.shape[:2]
    if W - 1 < 2 * mx + 2 or H - 1 < 2 * my + 2:
        raise ValueError(f"tile {t} ({W}x{H}) is too small for a {size[0]}x{size[1]} sensed image")
    centre = np.array([rng.uniform(mx + 1, W - 2 - mx), rng.uniform(my + 1, H - 2 - my)])
    A = _affine(centre, scale, rot, size)
    c = sensed_centre((size[1], size[0]))
    variant: dict = {}
    if deform:
        tilt = float(own.uniform(*dr["tilt_deg"]))
        axis = float(own.uniform(0, 180))
        nb = int(dr["bumps"])
        sig = own.uniform(*dr["bump_sigma_px"], size=nb)
        cen = own.uniform(-0.5, 0.5, size=(nb, 2)) * np.array(size, float)
        ang = own.uniform(0, 2 * np.pi, size=nb)
        vec = np.column_stack([np.cos(ang), np.sin(ang)])
        peak = float(own.uniform(*dr["displacement_px"]))
        D = Deformation(A, c, _rotation(axis, tilt), float(dr["focal_px"]), cen, vec, sig)
        gx, gy = np.meshgrid(np.arange(size[0], dtype=float), np.arange(size[1], dtype=float))
        grid = np.column_stack([gx.ravel(), gy.ravel()])
        raw = D.displacement(grid - c)
        D.bump_vectors = vec * (peak / max(float(np.linalg.norm(raw, axis=1).max()), 1e-9))
        to_tile = D
        m = D(grid).reshape(size[1], size[0], 2).astype(np.float32)
        img = cv2.remap(tile, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        variant.update(tilt_deg=tilt, tilt_axis_deg=axis, displacement_px=peak)
    else:
        def to_tile(xy, A=A):
            xy = np.asarray(xy, float)
            return xy @ A[:, :2].T + A[:, 2]
        img = cv2.warpAffine(tile, A, tuple(int(v) for v in size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REFLECT)
    if recolour_:
        img, rc = recolour(img, own, recolour_ranges)
        variant["recolour"] = rc
    params = {}
    if photometric:
        img, params = photometric_change(img, rng)
    truth = np.asarray(to_tile(c[None]), float)[0]
    return VariantTrial(int(index), t, img, A, truth, scale, rot, params, to_tile=to_tile, variant=variant)
