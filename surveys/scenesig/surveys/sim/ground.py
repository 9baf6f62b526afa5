"""Ground textures: the street cross-section along the route, and the far ground.

The street (road, kerbs, pavements, verges) is one long strip in route coordinates ``(s, d)``,
generated tile by tile on demand.  Its noise comes from lattices indexed by ``(s, d)`` so tiles made
independently (even in different processes) join without seams, and markings are functions of
``s`` (dashes every 9 m, zebra crossings at the world's crossing points).

Tile texture layout: row 0 is the far end of the tile (larger ``s``), column 0 the left edge
(``d = +half_width``); so the strip reads upright to a camera looking along the route.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .noise import lattice_noise, rng_for, speckle
from .textures import TexData, _clip_u8

__all__ = ["StreetStyle", "street_tile", "ground_tile", "ROAD_HALF", "KERB_OUT", "PAVE_OUT"]

ROAD_HALF = 3.6   # carriageway edge |d| (m): two 3.5 m lanes and a little gutter
KERB_OUT = 3.75   # outer edge of the kerb stones
PAVE_OUT = 5.75   # outer edge of the pavement (2 m wide)


@dataclass
class StreetStyle:
    """Per-world street parameters (random lattices and section types along ``s``)."""

    seed: int
    half_width: float
    route_length: float
    crossings: np.ndarray          # s of zebra crossings
    section_len: float = 20.0

    def __post_init__(self):
        rng = rng_for(self.seed, "street")
        self.lat_coarse = rng.random((64, 1024), dtype=np.float32)  # cells of 4 m (s) x 1 m (d)
        self.lat_mid = rng.random((64, 2048), dtype=np.float32)     # 1 m x 0.5 m
        self.lat_fine = rng.random((128, 4096), dtype=np.float32)   # 0.25 m
        n_sec = int(np.ceil((self.route_length + 400) / self.section_len)) + 2
        # verge kind per section and side: 0 grass, 1 mown stripes, 2 gravel, 3 paved forecourt
        self.verge = rng.choice(4, size=(n_sec, 2), p=[0.45, 0.2, 0.15, 0.2])
        self.pave = rng.choice(2, size=(n_sec, 2), p=[0.65, 0.35])  # 0 slabs, 1 tarmac
        self.edge_line = rng.random(n_sec) < 0.5
        self.yellow = rng.random((n_sec, 2)) < 0.25
        n_p = int(self.route_length / 14) + 40
        self.patches = np.stack([rng.uniform(-250, self.route_length + 250, n_p), rng.uniform(-3.3, 3.3, n_p),
                                 rng.uniform(0.6, 3.0, n_p), rng.uniform(0.5, 2.0, n_p),
                                 rng.uniform(0.7, 1.3, n_p)], 1)
        n_m = int(self.route_length / 40) + 12
        self.manholes = np.stack([rng.uniform(-250, self.route_length + 250, n_m), rng.uniform(-3.0, 3.0, n_m),
                                  rng.integers(0, 2, n_m)], 1)
        n_t = max(1, int(self.route_length / 120))
        self.texts = np.stack([rng.uniform(0, self.route_length, n_t), rng.integers(0, 3, n_t)], 1)
        n_c = int(self.route_length / 25) + 10
        self.cracks = [(float(rng.uniform(-250, self.route_length + 250)), rng.uniform(-3.3, 3.3, 5),
                        rng.uniform(0, 4, 5)) for _ in range(n_c)]

    def section(self, s):
        # a bend's projective tile maps texels far off the road to arc lengths beyond the route's range
        # (tight loops): they take the end sections (in-range values are unchanged)
        sec = np.floor((np.asarray(s) + 200) / self.section_len).astype(int)
        return np.clip(sec, 0, len(self.edge_line) - 1)


def _sd_grid(s0, s1, D, ppm):
    h = max(2, int(round((s1 - s0) * ppm)))
    w = max(2, int(round(2 * D * ppm)))
    s = s1 - (np.arange(h, dtype=np.float32) + 0.5) * (s1 - s0) / h
    d = D - (np.arange(w, dtype=np.float32) + 0.5) * (2 * D) / w
    return s, d, h, w


def street_tile(style: StreetStyle, s0: float, s1: float, season: str = "summer", ppm: float = 24.0,
                grid=None, to_px=None) -> TexData:
    """Albedo of the street strip between arc lengths ``s0 < s1`` (full width ``2*half_width``).

    ``grid``: optional (S, D) arrays giving each texel's route coordinates, and ``to_px(s, d) -> (x, y)``
    the inverse, for tiles whose texture maps onto the ground projectively (bends): the content is
    then drawn where each texel really lands, so the road stays where the route says.
    """
    D = style.half_width
    if grid is None:
        s, d, h, w = _sd_grid(s0, s1, D, ppm)
        S, Dd = np.meshgrid(s, d, indexing="ij")
    else:
        S, Dd = (np.asarray(a, np.float32) for a in grid)
        h, w = S.shape
    if to_px is None:
        def to_px(ss, dd):
            return (D - np.asarray(dd)) * ppm, (s1 - np.asarray(ss)) * ppm
    ad = np.abs(Dd)
    n_c = lattice_noise(style.lat_coarse, S / 4.0, Dd + 32)
    n_m = lattice_noise(style.lat_mid, S / 1.0, Dd / 0.5 + 32)
    n_f = lattice_noise(style.lat_fine, S / 0.25, Dd / 0.25 + 64)
    grain = speckle(rng_for(style.seed, "grain", int(s0 * 10)), h, w, 0.6)
    img = np.empty((h, w, 3), np.float32)

    # carriageway: asphalt, worn wheel paths, repair patches
    road = ad <= ROAD_HALF
    asphalt = 78 + 22 * (n_c - 0.5) + 10 * (n_m - 0.5) + 6 * (n_f - 0.5) + 7 * grain
    wheel = np.zeros_like(ad)
    for c in (0.95, 2.55):  # wheel paths are polished darker
        wheel += np.exp(-((ad - c) ** 2) / (2 * 0.25 ** 2))
    asphalt = asphalt - 8 * wheel
    img[..., 0] = asphalt * 1.02
    img[..., 1] = asphalt
    img[..., 2] = asphalt * 0.97
    sel = (style.patches[:, 0] > s0 - 4) & (style.patches[:, 0] < s1 + 4)
    for ps, pd, pl, pw, tone in style.patches[sel]:
        m = (np.abs(S - ps) < pl / 2) & (np.abs(Dd - pd) < pw / 2) & road
        img[m] *= tone * 0.92
    for cs, cd, ca in style.cracks:
        if s0 - 6 < cs < s1 + 6:
            px, py = to_px(cs + ca - 2, cd)
            pts = np.stack([px, py], 1)
            cv2.polylines(img, [np.round(pts).astype(np.int32)], False, (40, 40, 42), 1, cv2.LINE_AA)

    # markings (only on the carriageway; gone under snow)
    sec = style.section(S)
    dash = np.mod(S, 9.0) < 3.0
    mark = (np.abs(Dd) < 0.05) & dash
    mark |= style.edge_line[sec] & (np.abs(ad - (ROAD_HALF - 0.35)) < 0.05)
    for cs in style.crossings:
        if s0 - 4 < cs < s1 + 4:
            zebra = (np.abs(S - cs) < 1.5) & road & (np.mod(Dd + 10, 1.0) < 0.5)
            mark |= zebra
            mark |= (np.abs(S - cs - 2.2) < 0.15) & (Dd > 0) & road & (np.mod(Dd, 0.6) < 0.3)  # give-way line
    img[mark] = 0.6 * img[mark] + 0.4 * np.array([225, 228, 230], np.float32) * (0.85 + 0.3 * n_f[mark, None])
    side_idx = (Dd < 0).astype(int)
    yel = style.yellow[sec, side_idx] & ((np.abs(ad - 3.45) < 0.05) | (np.abs(ad - 3.3) < 0.05))
    img[yel] = np.array([40, 170, 215], np.float32) * (0.8 + 0.3 * n_f[yel, None])
    for ts, kind in style.texts:
        if s0 - 6 < ts < s1 + 6:
            word = ["SLOW", "BUS", "LOOK"][int(kind)]
            # road text is stretched along the direction of travel to be legible in perspective
            tile = np.zeros((int(5 * ppm), int(2.6 * ppm)), np.uint8)
            (tw, th), _ = cv2.getTextSize(word, cv2.FONT_HERSHEY_SIMPLEX, 1.0, 2)
            small = np.zeros((th + 6, tw + 4), np.uint8)
            cv2.putText(small, word, (2, th + 2), cv2.FONT_HERSHEY_SIMPLEX, 1.0, 255, 2)
            tile = cv2.resize(small, (tile.shape[1], tile.shape[0]))
            px, py = to_px(ts + 2.5, 2.9)
            x0, y0 = int(px), int(py)
            ys, xs = np.nonzero(tile > 128)
            ys, xs = ys + y0, xs + x0
            ok = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
            img[ys[ok], xs[ok]] = 0.5 * img[ys[ok], xs[ok]] + 0.5 * np.array([225, 228, 230], np.float32)
    sel = (style.manholes[:, 0] > s0 - 2) & (style.manholes[:, 0] < s1 + 2)
    for ms, md, kind in style.manholes[sel]:
        px, py = to_px(ms, md)
        c = (int(px), int(py))
        if kind == 0:
            cv2.circle(img, c, int(0.35 * ppm), (55, 58, 60), -1)
            cv2.circle(img, c, int(0.35 * ppm), (100, 100, 100), 1)
        else:
            r = int(0.3 * ppm)
            cv2.rectangle(img, (c[0] - r, c[1] - r), (c[0] + r, c[1] + r), (60, 60, 62), -1)
            for yy in range(c[1] - r + 2, c[1] + r, 3):
                cv2.line(img, (c[0] - r + 1, yy), (c[0] + r - 1, yy), (30, 30, 30), 1)

    # kerb stones: lighter granite with joints every metre, shadowed face towards the road
    kerb = (ad > ROAD_HALF) & (ad <= KERB_OUT)
    kv = 150 + 20 * (n_f - 0.5) + 6 * grain
    img[kerb] = (kv[kerb] * np.where(np.mod(S[kerb], 1.0) < 0.03, 0.6, 1.0))[:, None] * np.array([1.0, 1.0, 0.98])
    edge = (ad > ROAD_HALF) & (ad <= ROAD_HALF + 0.03)
    img[edge] *= 0.45

    # pavements: slabs or tarmac
    pave = (ad > KERB_OUT) & (ad <= PAVE_OUT)
    ptype = style.pave[sec, side_idx]
    slab = pave & (ptype == 0)
    tarmac = pave & (ptype == 1)
    v = 140 + 18 * (n_m - 0.5) + 8 * (n_f - 0.5) + 6 * grain
    img[slab] = v[slab, None] * np.array([1.0, 1.0, 0.97])
    joint = slab & ((np.mod(S, 0.6) < 0.025) | (np.mod(ad - KERB_OUT, 0.6) < 0.025))
    img[joint] *= 0.65
    img[tarmac] = (95 + 15 * (n_m[tarmac] - 0.5) + 8 * grain[tarmac])[:, None] * np.array([1.0, 1.0, 0.98])
    gum = pave & (n_f > 0.93)
    img[gum] *= 0.8

    # verges / front gardens / forecourts
    verge = ad > PAVE_OUT
    vtype = style.verge[sec, side_idx]
    grass_v = np.stack([48 + 18 * n_c + 12 * n_f, 88 + 32 * n_c + 20 * n_f - 8 * n_m, 72 + 26 * n_m + 10 * n_f],
                       -1) * (1 + 0.12 * grain)[..., None]
    g = verge & (vtype <= 1)
    img[g] = grass_v[g]
    stripes = verge & (vtype == 1) & (np.mod(S, 4.0) < 2.0)
    img[stripes] *= 1.12
    gravel = verge & (vtype == 2)
    img[gravel] = (150 + 30 * (n_f[gravel] - 0.5) + 20 * grain[gravel])[:, None] * np.array([0.85, 0.95, 1.05])
    fore = verge & (vtype == 3)
    img[fore] = (125 + 15 * (n_m[fore] - 0.5) + 6 * grain[fore])[:, None] * np.array([0.95, 1.0, 1.03])
    fj = fore & ((np.mod(S, 0.2) < 0.02) | (np.mod(ad, 0.1) < 0.01))
    img[fj] *= 0.8

    if season == "autumn":
        # fallen leaves collect along kerbs and on grass
        leaves = (n_f > 0.7) & (((ad > 2.8) & (ad < ROAD_HALF + 0.05)) | verge | pave) & (n_m > 0.4)
        img[leaves] = np.array([40, 85, 145], np.float32) * (0.6 + 0.6 * n_m[leaves, None]) * (1 + 0.15 * grain[
            leaves, None])
        img[verge] *= np.array([0.8, 0.9, 1.15], np.float32)
    elif season == "snow":
        # snow covers everything; slushy grey tyre tracks remain on the road, footprints on pavements
        snow = 232 + 12 * n_c + 6 * grain
        out = np.repeat(snow[..., None], 3, axis=2) * np.array([1.02, 1.0, 0.98], np.float32)
        tracks = np.zeros_like(ad)
        for c in (0.95, 2.55, -0.95, -2.55):
            tracks += np.exp(-((Dd - c) ** 2) / (2 * 0.22 ** 2))
        tracks = np.clip(tracks * (0.7 + 0.5 * n_m), 0, 1) * road
        out *= (1 - 0.35 * tracks)[..., None]
        steps = pave & (n_f > 0.7)
        out[steps] *= 0.9
        img = out
    return TexData(_clip_u8(img), None, [], None, ppm)


def ground_tile(seed: int, x0: float, y0: float, size: float, season: str = "summer", ppm: float = 4.0) -> TexData:
    """Far ground (fields, lawns, bare earth) for a square cell of the world grid, continuous across cells."""
    rng = rng_for(seed, "field")
    lat = rng.random((256, 256), dtype=np.float32)
    lat2 = rng.random((256, 256), dtype=np.float32)
    n = max(4, int(size * ppm))
    xs = x0 + (np.arange(n) + 0.5) / ppm
    ys = y0 + size - (np.arange(n) + 0.5) / ppm  # row 0 at the far (+y) edge
    X, Y = np.meshgrid(xs, ys)
    a = lattice_noise(lat, X / 12.0, Y / 12.0)
    b = lattice_noise(lat2, X / 3.0, Y / 3.0)
    grain = speckle(rng_for(seed, "fieldgrain", int(x0), int(y0)), n, n, 0.8)
    img = np.stack([48 + 22 * a + 10 * b, 85 + 35 * a + 15 * b, 75 + 30 * (1 - a) + 10 * b], -1)
    earth = (a < 0.25)[..., None]
    img = np.where(earth, np.array([70, 95, 120], np.float32) * (0.8 + 0.4 * b[..., None]), img)
    img *= (1 + 0.1 * grain)[..., None]
    if season == "autumn":
        img *= np.array([0.75, 0.9, 1.2], np.float32)
    elif season == "snow":
        img = (228 + 14 * a + 5 * grain)[..., None] * np.array([1.02, 1.0, 0.98], np.float32)
    return TexData(_clip_u8(img), None, [], None, ppm)
