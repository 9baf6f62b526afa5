"""Procedural textures of buildings: wall materials, facades (windows, doors, shops, signs), roofs.

Each generator draws one object's *albedo* (what the surface looks like under neutral white light)
from its own seeded generator, at ``ppm`` pixels per metre, for one season.  The season only changes
what snow or leaves cover; the structure (where windows, doors, signs are) comes from the same random
draws, so the snowy facade is the same facade.  Lighting, night and weather are applied later
(:mod:`scenesig.surveys.sim.conditions`).

Why so much detail: the world must give corner detectors (window corners, sign letters, brick
edges) *and* mid-level patch detectors (a shopfront, a window column, a logo) something to find, and
no two places may look alike -- every facade draws its own palette, layout and signage.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .noise import fbm, speckle

__all__ = ["TexData", "facade", "roof", "wall_material", "random_word", "FACADE_STYLES"]

FACADE_STYLES = ("brick_house", "terrace", "office_glass", "office_panel", "shop_row", "stone",
                 "plaster", "industrial", "cladding")

_SYLLABLES = ["ar", "bel", "cor", "dan", "el", "fin", "gra", "hal", "in", "jo", "kel", "lum", "mar",
              "nor", "ox", "pem", "qui", "ros", "sto", "tek", "ul", "ven", "wes", "xan", "york", "zen",
              "bio", "gen", "tech", "lab", "med", "tron", "soft", "bridge", "ford", "ton", "ley"]
_SUFFIXES = ["", "", " LTD", " LABS", " & CO", " HOUSE", " CENTRE", " CAFE", " BAKERY", " PHARMACY",
             " SYSTEMS", " HALL", " COURT", " PLC"]


@dataclass
class TexData:
    """One texture: albedo (BGR uint8), optional alpha cut-out, and night-lighting hints.

    ``windows`` are rectangles (x0, y0, x1, y1) that may be lit at night (each run lights its own
    subset); ``emissive`` marks always-on lights (lamp heads, illuminated signs).
    """

    bgr: np.ndarray
    alpha: np.ndarray | None = None
    windows: list = field(default_factory=list)
    emissive: np.ndarray | None = None
    ppm: float = 32.0

    @property
    def shape(self):
        return self.bgr.shape[:2]


def random_word(rng: np.random.Generator, suffix: bool = True) -> str:
    n = int(rng.integers(2, 4))
    w = "".join(rng.choice(_SYLLABLES) for _ in range(n)).upper()
    if suffix:
        w += str(rng.choice(_SUFFIXES))
    return w


def _clip_u8(a) -> np.ndarray:
    return np.clip(a, 0, 255).astype(np.uint8)


def _jitter_colour(rng, bgr, amount=18):
    return tuple(int(np.clip(c + rng.normal(0, amount), 0, 255)) for c in bgr)


# ----------------------------------------------------------------------------------- materials
_BRICKS = [(55, 75, 150), (60, 90, 165), (70, 85, 130), (90, 140, 185), (75, 110, 160), (50, 60, 110),
           (100, 120, 150)]
_RENDERS = [(225, 232, 238), (200, 222, 235), (190, 200, 205), (170, 200, 220), (215, 215, 210),
            (180, 210, 200), (150, 175, 200), (205, 190, 170)]
_STONES = [(150, 175, 190), (130, 160, 185), (160, 170, 175), (120, 135, 150)]
_CLADS = [(90, 110, 120), (60, 90, 120), (170, 170, 165), (70, 70, 75), (40, 80, 140), (120, 140, 110)]


def wall_material(rng: np.random.Generator, h: int, w: int, kind: str, ppm: float,
                  base=None) -> np.ndarray:
    """Wall surface of the given kind: 'brick', 'stone', 'plaster', 'cladding', 'panel', 'metal'.

    Returns float32 BGR (h, w, 3) in 0..255 (kept float so that details can be composited before
    the final rounding).
    """
    if kind == "brick":
        base = np.array(base if base is not None else _BRICKS[rng.integers(len(_BRICKS))], np.float32)
        course = max(2, int(round(0.075 * ppm)))
        blen = max(4, int(round(0.225 * ppm)))
        rows = h // course + 2
        cols = w // blen + 3
        # per-brick colour variation, staggered every other course (stretcher bond)
        var = rng.normal(0, 1, (rows, cols, 3)).astype(np.float32) * np.array([6, 8, 12], np.float32)
        var += rng.normal(0, 1, (rows, cols, 1)).astype(np.float32) * 10
        cells = np.repeat(np.repeat(var, course, axis=0), blen, axis=1)
        shift = np.zeros_like(cells)
        for r in range(rows):
            off = (blen // 2) * (r % 2)
            shift[r * course:(r + 1) * course] = np.roll(cells[r * course:(r + 1) * course], off, axis=1)
        img = base + shift[:h, :w]
        mortar = np.array([150, 160, 170], np.float32) * rng.uniform(0.7, 1.1)
        yy = np.arange(h) % course == 0
        img[yy] = 0.55 * img[yy] + 0.45 * mortar
    elif kind == "stone":
        base = np.array(base if base is not None else _STONES[rng.integers(len(_STONES))], np.float32)
        img = np.empty((h, w, 3), np.float32)
        img[:] = base
        y = 0
        while y < h:
            bh = max(3, int(rng.uniform(0.25, 0.45) * ppm))
            x = -int(rng.uniform(0, 0.6) * ppm)
            while x < w:
                bw = max(4, int(rng.uniform(0.4, 0.9) * ppm))
                c = base + rng.normal(0, 9, 3) + rng.normal(0, 8)
                img[y:y + bh, max(x, 0):x + bw] = c
                cv2.line(img, (x, y), (x, y + bh), (base * 0.7).tolist(), 1)
                x += bw
            cv2.line(img, (0, y), (w, y), (base * 0.72).tolist(), 1)
            y += bh
    elif kind == "cladding":
        base = np.array(base if base is not None else _CLADS[rng.integers(len(_CLADS))], np.float32)
        img = np.empty((h, w, 3), np.float32)
        img[:] = base
        board = max(3, int(rng.uniform(0.12, 0.2) * ppm))
        for y in range(0, h, board):
            img[y:y + board] *= rng.uniform(0.93, 1.07)
            img[y + board - 1:y + board] *= 0.6
    elif kind == "panel":
        base = np.array(base if base is not None else _RENDERS[rng.integers(len(_RENDERS))], np.float32) * 0.85
        img = np.empty((h, w, 3), np.float32)
        img[:] = base
        pw, ph = int(rng.uniform(1.2, 2.4) * ppm), int(rng.uniform(0.8, 1.6) * ppm)
        for y in range(0, h, ph):
            for x in range(0, w, pw):
                img[y:y + ph, x:x + pw] *= rng.uniform(0.92, 1.08)
        img[::ph] *= 0.55
        img[:, ::pw] *= 0.55
    elif kind == "metal":
        base = np.array(base if base is not None else _CLADS[rng.integers(len(_CLADS))], np.float32)
        img = np.empty((h, w, 3), np.float32)
        img[:] = base
        pitch = max(3, int(0.2 * ppm))
        ridge = (np.sin(np.arange(w) * 2 * np.pi / pitch) * 0.12 + 1.0).astype(np.float32)
        img *= ridge[None, :, None]
    else:  # plaster / render
        base = np.array(base if base is not None else _RENDERS[rng.integers(len(_RENDERS))], np.float32)
        img = np.empty((h, w, 3), np.float32)
        img[:] = base
    # weathering common to all: low-frequency stains, grain, grime towards the ground
    stain = fbm(rng, h, w, cell=ppm * 2.5, octaves=4)
    img *= (0.86 + 0.2 * stain)[..., None]
    img += speckle(rng, h, w, 0.7)[..., None] * 4.0
    grime = np.clip(1.0 - np.arange(h, dtype=np.float32)[::-1] / (1.2 * ppm), 0, 1) * 0.25
    img *= (1.0 - grime)[:, None, None]
    return img


# ----------------------------------------------------------------------------------- details
def _clamp_rect(rect, shape) -> tuple:
    """``rect`` (x0, y0, x1, y1) with every coordinate clamped into an image of ``shape``.

    A rectangle inside the image is returned unchanged (so are degenerate ones inside it): the
    night renderer draws one random number per listed window, so windows are clamped, never dropped.
    """
    h, w = shape[:2]
    x0, y0, x1, y1 = (int(v) for v in rect)
    return (min(max(x0, 0), w), min(max(y0, 0), h), min(max(x1, 0), w), min(max(y1, 0), h))


def _paste(img: np.ndarray, patch: np.ndarray, x0: int, y0: int) -> None:
    """Write ``patch`` into ``img`` with its top-left corner at (x0, y0), clipped to ``img``.

    Destination and source are cut by the same rectangle, so a patch that overhangs an edge (a
    window wider than a narrow side wall) keeps its inside part; plain slicing would instead
    shorten only the destination (and wrap negative starts to the far edge).
    """
    cx0, cy0, cx1, cy1 = _clamp_rect((x0, y0, x0 + patch.shape[1], y0 + patch.shape[0]), img.shape)
    if cx1 > cx0 and cy1 > cy0:
        img[cy0:cy1, cx0:cx1] = patch[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]


def _window(img, rng, x0, y0, x1, y1, frame_c, style, ppm, season):
    """Draw one window (frame, glass with a sky reflection, interior hints, sill).

    The rectangle may overhang the texture (a window bay wider than a narrow wall): the glass is
    drawn in the window's own coordinates and pasted clipped, and every random draw is made
    whatever the overlap, so the random stream -- and hence the rest of the facade -- does not
    depend on it.
    """
    h = y1 - y0
    w = x1 - x0
    if w < 3 or h < 3:
        return
    # glass: darkish, vertical gradient of reflected sky, random interior/curtain/blind
    g = np.linspace(1.0, 0.55, h, dtype=np.float32)[:, None, None]
    glass_base = np.array([95, 80, 65], np.float32) * rng.uniform(0.7, 1.3) if style != "office_glass" \
        else np.array([120, 100, 70], np.float32) * rng.uniform(0.8, 1.2)
    glass = glass_base * g * np.ones((1, w, 1), np.float32)
    # diagonal reflection streak: different per window, gives texture inside the glass
    k = rng.uniform(-1.5, 1.5)
    xs = np.arange(w)[None, :]
    ys = np.arange(h)[:, None]
    streak = ((xs + k * ys + rng.integers(0, 50)) % max(6, w) < max(2, w // 4)).astype(np.float32)
    glass += streak[..., None] * rng.uniform(15, 40)
    inner = rng.random()
    if inner < 0.3:  # curtains drawn to the sides
        cc = np.array(_jitter_colour(rng, rng.choice([(60, 60, 140), (150, 140, 120), (50, 120, 160),
                                                        (200, 200, 210), (90, 60, 50)]), 25), np.float32)
        cw = int(w * rng.uniform(0.15, 0.35))
        glass[:, :cw] = 0.4 * glass[:, :cw] + 0.6 * cc
        glass[:, w - cw:] = 0.4 * glass[:, w - cw:] + 0.6 * cc
    elif inner < 0.5:  # blind, part-lowered
        bh = int(h * rng.uniform(0.2, 0.8))
        glass[:bh] = 0.3 * glass[:bh] + 0.7 * np.array([200, 205, 210], np.float32)
        glass[:bh:3] *= 0.8
    elif inner < 0.6:  # something on the sill inside
        cv2.circle(glass, (w // 2, h - 2), max(2, w // 6), (40, 110, 60), -1)
    _paste(img, glass, x0, y0)
    t = max(1, int(0.06 * ppm))
    cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), frame_c, t)
    # glazing bars
    if style in ("brick_house", "terrace", "stone", "plaster") and rng.random() < 0.7:
        cv2.line(img, (x0 + w // 2, y0), (x0 + w // 2, y1), frame_c, max(1, t // 2 + 1))
        if rng.random() < 0.6:
            cv2.line(img, (x0, y0 + h // 3), (x1, y0 + h // 3), frame_c, max(1, t // 2 + 1))
    elif style in ("office_glass", "office_panel", "industrial") and w > 1.2 * ppm:
        for xi in range(x0 + int(1.2 * ppm), x1 - 2, int(1.2 * ppm)):
            cv2.line(img, (xi, y0), (xi, y1), frame_c, t)
    # sill: a lighter ledge that snow settles on
    sill_h = max(2, int(0.08 * ppm))
    sill_c = (210, 215, 220) if style != "office_glass" else frame_c
    cv2.rectangle(img, (x0 - t, y1), (x1 + t, y1 + sill_h), sill_c, -1)
    streak_h = int(rng.uniform(0.1, 0.6) * ppm)  # drawn in every season: keeps the random stream aligned
    if season == "snow":
        cv2.rectangle(img, (x0 - t, y1 - 1), (x1 + t, y1 + sill_h), (245, 246, 248), -1)
        cv2.rectangle(img, (x0 + t, y1 - sill_h), (x1 - t, y1), (235, 238, 242), -1)
    else:
        # rain streak below the sill (weathering)
        vx0, _, vx1, _ = _clamp_rect((x0, 0, x1, 0), img.shape)
        img[y1 + sill_h:y1 + sill_h + streak_h, vx0:vx1] *= 0.92


def _door(img, rng, x0, y1, ppm, colour=None, width_m=1.0, height_m=2.1, glass=False):
    w, h = int(width_m * ppm), int(height_m * ppm)
    x1, y0 = x0 + w, y1 - h
    c = colour or _jitter_colour(rng, rng.choice([(40, 30, 120), (90, 60, 20), (30, 30, 30), (60, 110, 40),
                                                   (200, 200, 200), (30, 60, 110), (120, 40, 60)]), 15)
    cv2.rectangle(img, (x0 - 3, y0 - 3), (x1 + 3, y1), (200, 205, 210), -1)
    cv2.rectangle(img, (x0, y0), (x1, y1), c, -1)
    if glass:
        cv2.rectangle(img, (x0 + w // 6, y0 + h // 10), (x1 - w // 6, y1 - h // 3), (80, 70, 60), -1)
    else:
        for (a, b) in ((0.15, 0.45), (0.55, 0.9)):
            cv2.rectangle(img, (x0 + w // 6, y0 + int(a * h)), (x1 - w // 6, y0 + int(b * h)),
                          tuple(int(v * 0.8) for v in c), 1)
    cv2.circle(img, (x1 - w // 6, y0 + h // 2), max(1, int(0.04 * ppm)), (60, 180, 210), -1)
    # fanlight above traditional doors
    if not glass and rng.random() < 0.5:
        cv2.rectangle(img, (x0, y0 - int(0.3 * ppm)), (x1, y0 - 2), (90, 80, 70), -1)
    return x0, y0, x1, y1


def _sign(img, rng, x0, y0, x1, y1, text=None, colours=None):
    """A fascia/company sign with text -- corners for ORB, a distinctive patch for HOG."""
    bg, fg = colours or rng.choice([((30, 30, 30), (240, 240, 240)), ((120, 40, 20), (255, 255, 255)),
                                    ((40, 40, 160), (255, 255, 255)), ((230, 230, 230), (40, 40, 40)),
                                    ((40, 120, 40), (230, 240, 240)), ((20, 160, 220), (20, 20, 20)),
                                    ((100, 30, 90), (200, 230, 255))])
    cv2.rectangle(img, (x0, y0), (x1, y1), tuple(int(v) for v in bg), -1)
    cv2.rectangle(img, (x0, y0), (x1, y1), tuple(int(v * 0.5) for v in bg), 2)
    text = text or random_word(rng)
    h = y1 - y0
    w = x1 - x0
    font = int(rng.choice([cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX,
                           cv2.FONT_HERSHEY_COMPLEX]))
    thick = max(1, h // 12)
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, thick)
    scale = min(0.7 * h / max(th, 1), 0.92 * w / max(tw, 1))
    if scale < 0.15:
        return
    (tw, th), _ = cv2.getTextSize(text, font, scale, thick)
    cv2.putText(img, text, (x0 + (w - tw) // 2, y0 + (h + th) // 2), font, scale,
                tuple(int(v) for v in fg), thick, cv2.LINE_AA)
    # a logo next to the text on some signs
    if rng.random() < 0.5 and h > 8:
        cx = x0 + h // 2 + 2
        shape = rng.integers(3)
        col = tuple(int(v) for v in rng.integers(0, 255, 3))
        if shape == 0:
            cv2.circle(img, (cx, y0 + h // 2), h // 3, col, -1)
        elif shape == 1:
            pts = np.array([[cx, y0 + h // 6], [cx - h // 3, y1 - h // 6], [cx + h // 3, y1 - h // 6]], np.int32)
            cv2.fillConvexPoly(img, pts, col)
        else:
            cv2.rectangle(img, (cx - h // 3, y0 + h // 6), (cx + h // 3, y1 - h // 6), col, -1)


def _poster(img, rng, x0, y0, w, h):
    """Bill posters / murals: blocks of colour and shapes (change between runs is not modelled)."""
    base = rng.integers(30, 230, 3)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), tuple(int(v) for v in base), -1)
    for _ in range(int(rng.integers(2, 6))):
        col = tuple(int(v) for v in rng.integers(0, 255, 3))
        cx, cy = int(x0 + rng.uniform(0, w)), int(y0 + rng.uniform(0, h))
        r = int(rng.uniform(0.1, 0.4) * min(w, h))
        if rng.random() < 0.5:
            cv2.circle(img, (cx, cy), r, col, -1)
        else:
            cv2.rectangle(img, (cx - r, cy - r // 2), (cx + r, cy + r // 2), col, -1)
    if h > 12:
        cv2.putText(img, random_word(rng, False)[:6], (x0 + 2, y0 + h - 3), cv2.FONT_HERSHEY_SIMPLEX,
                    max(0.2, h / 70), (255, 255, 255), 1, cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), (30, 30, 30), 1)


def _graffiti(img, rng, x0, y0, w, h):
    col = tuple(int(v) for v in rng.integers(0, 255, 3))
    pts = np.stack([x0 + rng.uniform(0, w, 8), y0 + rng.uniform(0, h, 8)], 1).astype(np.int32)
    cv2.polylines(img, [pts], False, col, max(1, h // 12), cv2.LINE_AA)


# ----------------------------------------------------------------------------------- facades
def facade(rng: np.random.Generator, width_m: float, height_m: float, style: str, season: str = "summer",
           ppm: float = 32.0, side: bool = False) -> TexData:
    """Albedo of one building face (front, or ``side`` wall with fewer openings).

    The bottom row of the texture is ground level; the top row the eaves/parapet.
    """
    w, h = max(8, int(round(width_m * ppm))), max(8, int(round(height_m * ppm)))
    kind = {"brick_house": "brick", "terrace": "brick", "stone": "stone", "plaster": "plaster",
            "office_glass": "panel", "office_panel": "panel", "shop_row": rng.choice(["brick", "plaster"]),
            "industrial": "metal", "cladding": "cladding"}[style]
    img = wall_material(rng, h, w, kind, ppm)
    windows = []
    floor_h = rng.uniform(2.8, 3.4) if style not in ("office_glass", "office_panel", "industrial") \
        else rng.uniform(3.4, 4.0)
    n_floors = max(1, int(height_m // floor_h))
    frame_c = _jitter_colour(rng, rng.choice([(235, 235, 235), (40, 40, 40), (60, 50, 40), (200, 210, 215),
                                              (90, 90, 95)]), 10)
    shop = style == "shop_row" and not side

    if style == "office_glass" and not side:
        # curtain wall: full-height glazing bands between spandrel panels
        band_h = int(floor_h * ppm)
        for f in range(n_floors):
            y1 = h - f * band_h - int(0.9 * ppm)
            y0 = y1 - int(floor_h * 0.62 * ppm)
            if y0 < int(0.3 * ppm):
                break
            x0 = int(rng.uniform(0.3, 0.8) * ppm)
            x1 = w - x0
            _window(img, rng, x0, y0, x1, y1, frame_c, style, ppm, season)
            pane = int(rng.uniform(1.2, 1.8) * ppm)
            for xs in range(x0, x1, pane):
                windows.append(_clamp_rect((xs, y0, min(xs + pane, x1), y1), img.shape))
    else:
        win_w = rng.uniform(0.9, 1.6) if style not in ("industrial",) else rng.uniform(1.5, 3.0)
        win_h = rng.uniform(1.2, 1.7)
        pitch = win_w + rng.uniform(0.8, 2.0)
        if side:
            pitch *= rng.uniform(1.5, 3.0)
        n_cols = max(1, int((width_m - 0.6) // pitch))
        margin = (width_m - n_cols * pitch) / 2 + (pitch - win_w) / 2
        skip_prob = 0.08 if not side else 0.4
        for f in range(n_floors):
            if f == 0 and (shop or style == "industrial"):
                continue
            base_y = height_m - f * floor_h  # metres from top
            y1 = int((base_y - 0.9) * ppm)
            y0 = int((base_y - 0.9 - win_h) * ppm)
            if y0 < int(0.4 * ppm):
                continue
            for c in range(n_cols):
                if rng.random() < skip_prob:
                    continue
                x0 = int((margin + c * pitch) * ppm)
                x1 = int((margin + c * pitch + win_w) * ppm)
                if f == 0 and not side and c == n_cols // 2 and style in ("brick_house", "terrace", "plaster",
                                                                          "stone", "cladding"):
                    # the front door takes this bay on the ground floor
                    cx = (x0 + x1) // 2
                    _door(img, rng, cx - int(0.5 * ppm), h - 1, ppm)
                    continue
                _window(img, rng, x0, y0, x1, y1, frame_c, style, ppm, season)
                windows.append(_clamp_rect((x0, y0, x1, y1), img.shape))
        if style == "terrace" and not side:
            # party-wall lines and a second door: terraces repeat, but each house its own colour
            for xs in np.linspace(0, w, int(rng.integers(2, 4)) + 1)[1:-1]:
                cv2.line(img, (int(xs), 0), (int(xs), h), (120, 120, 130), 2)
    if shop:
        # shopfronts: big display windows, a fascia sign each
        x = int(rng.uniform(0.2, 0.6) * ppm)
        while x < w - 2 * ppm:
            sw = int(rng.uniform(4.0, 7.0) * ppm)
            sw = min(sw, w - x - int(0.3 * ppm))
            fascia_y0 = h - int(3.6 * ppm)
            fascia_y1 = h - int(2.9 * ppm)
            _sign(img, rng, x, fascia_y0, x + sw, fascia_y1)
            dw = int(1.0 * ppm)
            _door(img, rng, x + sw - dw - 4, h - 1, ppm, glass=True, height_m=2.3)
            win = (x + 4, fascia_y1 + 4, x + sw - dw - 10, h - int(0.5 * ppm))
            _window(img, rng, *win, frame_c, "office_glass", ppm, season)
            windows.append(_clamp_rect(win, img.shape))
            if rng.random() < 0.4:  # awning
                pts = np.array([[x, fascia_y1], [x + sw, fascia_y1], [x + sw, fascia_y1 + int(0.6 * ppm)],
                                [x, fascia_y1 + int(0.6 * ppm)]], np.int32)
                col = _jitter_colour(rng, rng.choice([(40, 40, 160), (40, 120, 40), (150, 80, 30)]))
                cv2.fillConvexPoly(img, pts, col)
                for xs in range(x, x + sw, max(4, int(0.5 * ppm))):
                    cv2.line(img, (xs, fascia_y1), (xs, fascia_y1 + int(0.6 * ppm)), (235, 235, 235), 2)
            x += sw + int(rng.uniform(0.3, 1.0) * ppm)
    if style in ("office_glass", "office_panel") and not side:
        # entrance and a company sign: the kind of distinctive element scene signatures latch onto
        ex = int(rng.uniform(0.2, 0.7) * w)
        _door(img, rng, ex, h - 1, ppm, colour=(60, 60, 60), width_m=2.4, height_m=2.6, glass=True)
        sw = int(rng.uniform(4, 9) * ppm)
        sy = int(rng.uniform(0.2, 0.6) * ppm) if rng.random() < 0.5 else h - int(3.5 * ppm)
        sx = int(rng.uniform(0, max(1, w - sw)))
        _sign(img, rng, sx, sy, sx + sw, sy + int(rng.uniform(0.6, 1.0) * ppm))
    if style == "industrial" and not side:
        for _ in range(int(rng.integers(1, 3))):
            dw = int(rng.uniform(3.0, 5.0) * ppm)
            dx = int(rng.uniform(0, max(1, w - dw)))
            dy = h - int(rng.uniform(3.5, 4.5) * ppm)
            cv2.rectangle(img, (dx, dy), (dx + dw, h), (110, 115, 120), -1)
            for yy in range(dy, h, 4):
                cv2.line(img, (dx, yy), (dx + dw, yy), (80, 85, 90), 1)
            cv2.rectangle(img, (dx, dy), (dx + dw, h), (40, 40, 40), 2)
        _sign(img, rng, int(0.5 * ppm), int(0.5 * ppm), int(min(w - 4, rng.uniform(4, 8) * ppm)),
              int(1.3 * ppm))
        for _ in range(int(rng.integers(0, 3))):
            _graffiti(img, rng, int(rng.uniform(0, w - ppm)), h - int(2.2 * ppm), int(3 * ppm), int(1.6 * ppm))
    # details: drainpipes, vents, posters, house numbers, wall lamps
    for _ in range(int(rng.integers(0, 3))):
        x = int(rng.uniform(0.05, 0.95) * w)
        cv2.line(img, (x, 0), (x, h), (45, 45, 50), max(2, int(0.08 * ppm)))
    if not side and rng.random() < 0.35:
        pw, ph = int(rng.uniform(0.7, 1.2) * ppm), int(rng.uniform(1.0, 1.5) * ppm)
        _poster(img, rng, int(rng.uniform(0, max(1, w - pw))), h - int(2.2 * ppm), pw, ph)
    if not side and rng.random() < 0.5 and style in ("brick_house", "terrace", "plaster", "stone"):
        cv2.putText(img, str(int(rng.integers(1, 200))), (int(rng.uniform(0.1, 0.9) * w), h - int(2.5 * ppm)),
                    cv2.FONT_HERSHEY_SIMPLEX, ppm / 40, (30, 30, 30), max(1, int(ppm / 16)), cv2.LINE_AA)
    if rng.random() < 0.3:
        vx, vy = int(rng.uniform(0.1, 0.9) * w), int(rng.uniform(0.2, 0.8) * h)
        cv2.rectangle(img, (vx, vy), (vx + int(0.8 * ppm), vy + int(0.5 * ppm)), (170, 175, 180), -1)
        for yy in range(vy + 2, vy + int(0.5 * ppm), 3):
            cv2.line(img, (vx + 2, yy), (vx + int(0.8 * ppm) - 2, yy), (90, 90, 95), 1)
    # cornice / parapet: a ledge along the top
    ch = max(2, int(rng.uniform(0.2, 0.5) * ppm))
    cc = _jitter_colour(rng, (200, 205, 210) if style != "industrial" else (90, 95, 100))
    img[:ch] = np.array(cc, np.float32)
    img[ch:ch + 2] *= 0.6
    if season == "snow":
        img[:max(2, ch // 2)] = 246.0
        # snow banked against the wall and splashed slush above it
        bank = (0.25 + 0.2 * fbm(rng, 1, w, cell=ppm, octaves=2)[0]) * ppm
        ys = np.arange(h)[:, None]
        mask = ys >= (h - bank[None, :])
        img[mask] = 240.0 + speckle(rng, h, w, 1.0)[mask][:, None] * 4
        img[(ys >= h - bank[None, :] - 0.3 * ppm) & ~mask] *= 0.85
    return TexData(_clip_u8(img), None, windows, None, ppm)


def roof(rng: np.random.Generator, width_m: float, slope_m: float, season: str = "summer",
         ppm: float = 16.0, kind: str | None = None) -> TexData:
    """A pitched roof plane seen from the street; top row is the ridge, bottom the eaves."""
    w, h = max(8, int(round(width_m * ppm))), max(6, int(round(slope_m * ppm)))
    kind = kind or str(rng.choice(["clay", "slate", "concrete"]))
    base = {"clay": (50, 75, 140), "slate": (85, 80, 78), "concrete": (95, 100, 110)}[kind]
    base = np.array(_jitter_colour(rng, base, 12), np.float32)
    img = np.empty((h, w, 3), np.float32)
    img[:] = base
    row = max(2, int(0.3 * ppm))
    tile = max(2, int(0.3 * ppm))
    var = rng.normal(1.0, 0.07, (h // row + 1, w // tile + 2)).astype(np.float32)
    cells = np.repeat(np.repeat(var, row, 0), tile, 1)[:h, :w]
    img *= cells[..., None]
    img[::row] *= 0.6
    img *= (0.85 + 0.25 * fbm(rng, h, w, cell=ppm * 3, octaves=3))[..., None]
    # ridge tiles, a chimney stack or roof light gives each roof a landmark
    img[:max(2, int(0.2 * ppm))] *= 0.75
    if rng.random() < 0.6:
        cx = int(rng.uniform(0.1, 0.9) * w)
        cw = int(rng.uniform(0.6, 1.2) * ppm)
        cv2.rectangle(img, (cx, 0), (cx + cw, int(0.9 * ppm)), _jitter_colour(rng, (60, 80, 140)), -1)
    if rng.random() < 0.4:
        rx = int(rng.uniform(0.1, 0.8) * w)
        cv2.rectangle(img, (rx, h // 3), (rx + int(0.8 * ppm), h // 3 + int(1.0 * ppm)), (90, 80, 70), -1)
        cv2.rectangle(img, (rx, h // 3), (rx + int(0.8 * ppm), h // 3 + int(1.0 * ppm)), (200, 200, 200), 1)
    if season == "snow":
        # a roof under snow is white; only the chimney and a darker eaves line survive
        snow = 238 + 10 * fbm(rng, h, w, cell=ppm * 2, octaves=3)
        keep = np.zeros((h, w), bool)
        keep[-max(1, int(0.1 * ppm)):] = True
        img = np.where(keep[..., None], img, snow[..., None] * np.array([1.0, 0.99, 0.97], np.float32))
    return TexData(_clip_u8(img), None, [], None, ppm)
