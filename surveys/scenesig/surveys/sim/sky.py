"""Sky panoramas (per run: clouds move on between days) and the distant skyline (per world).

The sky is a cylinder of quads that travels with the camera (infinitely far: no parallax); its
texture rows are linear in ``tan(elevation)``, which is how heights on a cylinder project.  The
skyline is a fixed ring of cut-out quads a few hundred metres beyond the route -- hills, tree lines,
roofs, towers and cranes -- the kind of far-field structure that survives most appearance change.
"""
from __future__ import annotations

import cv2
import numpy as np

from .noise import fbm, speckle
from .textures import TexData, _clip_u8

__all__ = ["sky_panorama", "skyline_texture", "SKY_ELEV", "SKY_QUADS"]

SKY_ELEV = (-12.0, 52.0)  # elevation range (deg) covered by the sky cylinder
SKY_QUADS = 16


def _periodic(a: np.ndarray, width: int) -> np.ndarray:
    """Crop a noise field generated ``extra`` columns too wide to ``width`` columns that wrap seamlessly
    (the extra columns are cross-faded into the first ones)."""
    extra = a.shape[1] - width
    w = np.linspace(0, 1, extra, dtype=np.float32)[None, :]
    out = a[:, :width].copy()
    out[:, :extra] = a[:, width:] * (1 - w) + a[:, :extra] * w
    return out


def sky_panorama(rng: np.random.Generator, palette: dict, sun: tuple | None, width: int = 2048,
                 height: int = 400) -> np.ndarray:
    """BGR float32 panorama; column 0 at azimuth 0, azimuth decreasing to the right.

    palette: 'zenith', 'horizon', 'below' BGR colours, 'cloud' BGR, 'cloud_dark' BGR,
    'coverage' in [0, 1], 'glow' BGR (sun halo) ; sun: (azimuth, elevation) radians or None.
    """
    t0, t1 = np.tan(np.radians(SKY_ELEV[1])), np.tan(np.radians(SKY_ELEV[0]))
    tan_el = np.linspace(t0, t1, height, dtype=np.float32)
    el = np.arctan(tan_el)
    zen = np.array(palette["zenith"], np.float32)
    hor = np.array(palette["horizon"], np.float32)
    bel = np.array(palette.get("below", palette["horizon"]), np.float32)
    u = np.clip(el / np.radians(45), 0, 1) ** 0.6
    col = np.where(el[:, None] >= 0, hor * (1 - u[:, None]) + zen * u[:, None], bel)
    img = np.repeat(col[:, None, :], width, axis=1)
    cov = float(palette.get("coverage", 0.0))
    if cov > 0:
        # clouds: stretched fractal noise, flattened towards the horizon; made periodic in azimuth
        n = _periodic(fbm(rng, height, width + width // 8, cell=width / 12, octaves=5, persistence=0.55), width)
        detail = _periodic(fbm(rng, height, width + width // 8, cell=width / 60, octaves=3), width)
        thresh = 1.0 - cov
        c = np.clip((n - thresh) / 0.18 + 0.25 * (detail - 0.5), 0, 1)
        c *= np.clip(el / np.radians(2.0), 0, 1)[:, None]  # no clouds below the horizon
        shade = (0.75 + 0.35 * detail)[..., None]
        cloud = np.array(palette["cloud"], np.float32) * shade
        dark = np.array(palette.get("cloud_dark", palette["cloud"]), np.float32)
        cloud = cloud * (1 - 0.5 * n[..., None]) + dark * 0.5 * n[..., None]
        img = img * (1 - c[..., None]) + cloud * c[..., None]
    if sun is not None and "glow" in palette:
        az = -2 * np.pi * (np.arange(width, dtype=np.float32) + 0.5) / width
        daz = np.angle(np.exp(1j * (az - sun[0])))
        ang = np.sqrt((daz[None, :] * np.cos(sun[1])) ** 2 + (el[:, None] - sun[1]) ** 2)
        glow = np.exp(-ang / 0.12) * 0.8 + np.exp(-ang / 0.02) * 2.0
        img = img + np.array(palette["glow"], np.float32) * glow[..., None]
    return img


def skyline_texture(rng: np.random.Generator, length_m: float, season: str = "summer", ppm: float = 2.0,
                    height_m: float = 70.0) -> TexData:
    """One long strip of distant silhouettes (hills behind, trees and buildings in front)."""
    W, H = int(length_m * ppm), int(height_m * ppm)
    img = np.zeros((H, W, 3), np.float32)
    alpha = np.zeros((H, W), np.uint8)
    windows = []
    # hills: a smooth far silhouette, lighter (further away)
    hill = np.clip(fbm(rng, 1, W, cell=W / 10, octaves=3)[0] * 1.4 - 0.45, 0, 1) * 0.4 * H + 0.05 * H
    hill_mask = (np.arange(H)[:, None] > (H - hill[None, :]))
    hill_col = np.array([150, 140, 125] if season != "snow" else [228, 225, 222], np.float32)
    img[hill_mask] = hill_col
    alpha[hill_mask] = 255
    # tree lines: bumpy, darker
    trees = (0.12 + 0.2 * fbm(rng, 1, W, cell=max(4, W / 60), octaves=4)[0]) * H
    tm = (np.arange(H)[:, None] > (H - trees[None, :]))
    tcol = {"summer": [70, 95, 70], "autumn": [60, 95, 115], "snow": [150, 150, 150]}[season]
    img[tm] = np.array(tcol, np.float32) * (0.85 + 0.3 * speckle(rng, H, W, 1.0)[tm, None] * 0.3)
    alpha[tm] = 255
    # buildings, towers, spires, cranes: landmarks that make each direction distinct
    x = 0
    while x < W:
        kind = rng.choice(["gap", "block", "block", "tower", "spire", "crane", "chimney"], p=[0.3, 0.25, 0.15, 0.1,
                                                                                             0.07, 0.05, 0.08])
        bw = int(rng.uniform(8, 40) * ppm)
        if kind == "gap":
            x += bw
            continue
        bh = {"block": rng.uniform(8, 20), "tower": rng.uniform(25, 45), "spire": rng.uniform(30, 50),
              "crane": rng.uniform(35, 55), "chimney": rng.uniform(25, 45)}[kind] * ppm
        col = np.array([95, 95, 100], np.float32) * rng.uniform(0.7, 1.2)
        y0 = int(H - bh)
        if kind in ("block", "tower"):
            if kind == "tower":
                bw = int(rng.uniform(8, 14) * ppm)
            cv2.rectangle(img, (x, y0), (x + bw, H), col.tolist(), -1)
            cv2.rectangle(alpha, (x, y0), (x + bw, H), 255, -1)
            if season == "snow":
                cv2.rectangle(img, (x, y0), (x + bw, y0 + 1), (235, 235, 235), -1)
            for wy in range(y0 + 3, H - 3, 4):
                for wx in range(x + 2, min(x + bw - 2, W - 1), 4):
                    if rng.random() < 0.5:
                        img[wy, wx] = col * 0.7
                        windows.append((wx, wy, wx + 1, wy + 1))
        elif kind == "spire":
            pts = np.array([[x, H], [x + bw // 3, H], [x + bw // 6, y0]], np.int32)
            cv2.fillConvexPoly(img, pts, col.tolist())
            cv2.fillConvexPoly(alpha, pts, 255)
            cv2.rectangle(img, (x - 6, int(H - bh * 0.45)), (x + bw // 3 + 6, H), col.tolist(), -1)
            cv2.rectangle(alpha, (x - 6, int(H - bh * 0.45)), (x + bw // 3 + 6, H), 255, -1)
        elif kind == "chimney":
            cw = max(2, int(3 * ppm))
            cv2.rectangle(img, (x, y0), (x + cw, H), (60, 70, 110), -1)
            cv2.rectangle(alpha, (x, y0), (x + cw, H), 255, -1)
            cv2.rectangle(img, (x - 8, int(H - 10 * ppm)), (x + bw, H), col.tolist(), -1)
            cv2.rectangle(alpha, (x - 8, int(H - 10 * ppm)), (x + bw, H), 255, -1)
        else:  # crane: mast, jib, counter-jib
            cc = (30, 150, 210)
            cv2.line(img, (x, H), (x, y0), cc, 2)
            cv2.line(alpha, (x, H), (x, y0), 255, 2)
            cv2.line(img, (x - int(10 * ppm), y0 + 3), (x + int(30 * ppm), y0 + 3), cc, 2)
            cv2.line(alpha, (x - int(10 * ppm), y0 + 3), (x + int(30 * ppm), y0 + 3), 255, 2)
        x += bw + int(rng.uniform(2, 20) * ppm)
    img *= (0.9 + 0.2 * fbm(rng, H, W, cell=8, octaves=2))[..., None]
    return TexData(_clip_u8(img), alpha, windows, None, ppm)
