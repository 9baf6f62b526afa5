"""Procedural textures of street furniture, vegetation and distractors (cut-outs with alpha).

Trees, hedges, fences, lamp posts, signs, bins and post boxes belong to the world; parked cars and
pedestrians are drawn per run (distractors: present in one run, gone in the next).  The season
changes foliage (full green, autumn colours and thinning, bare branches under snow) but never the
branch structure, which is drawn from the same random stream in every season.
"""
from __future__ import annotations

import cv2
import numpy as np

from .noise import fbm, speckle
from .textures import TexData, _clip_u8, _jitter_colour, random_word

__all__ = ["tree", "hedge", "fence", "lamp_post", "road_sign", "street_object", "car", "pedestrian"]

_SUMMER_GREENS = [(40, 110, 60), (35, 95, 45), (50, 125, 80), (30, 80, 55), (60, 130, 95)]
_AUTUMN = [(40, 115, 185), (35, 90, 165), (40, 145, 195), (40, 70, 140), (50, 100, 135), (35, 130, 175)]


def _canvas(w, h):
    return np.zeros((h, w, 3), np.float32), np.zeros((h, w), np.uint8)


def tree(rng: np.random.Generator, width_m: float, height_m: float, kind: str = "deciduous",
         season: str = "summer", ppm: float = 20.0) -> TexData:
    """A tree billboard: trunk, branch skeleton and (seasonal) foliage clusters."""
    W, H = max(8, int(width_m * ppm)), max(8, int(height_m * ppm))
    img, alpha = _canvas(W, H)
    bark = np.array(_jitter_colour(rng, (60, 75, 90) if kind != "birch" else (200, 205, 210), 12), np.float32)
    trunk_w = max(2, int(rng.uniform(0.25, 0.45) * ppm * (height_m / 10) ** 0.5))
    crown_base = H - int(rng.uniform(0.2, 0.35) * H)
    cx = W // 2 + int(rng.normal(0, 0.03 * W))
    segs = []  # (x0, y0, x1, y1, thickness)

    if kind == "conifer":
        segs.append((cx, H - 1, cx, int(0.05 * H), trunk_w))
        n_tiers = int(rng.integers(6, 10))
        clusters = []
        for i in range(n_tiers):
            y = int(crown_base - (crown_base - 0.05 * H) * i / n_tiers)
            half = (W / 2 - 2) * (1 - i / n_tiers) * rng.uniform(0.85, 1.0)
            clusters.append((y, half, rng.uniform(0.85, 1.15)))
    else:
        def grow(x, y, ang, length, thick, depth):
            x1 = x + length * np.sin(ang)
            y1 = y - length * np.cos(ang)
            segs.append((int(x), int(y), int(x1), int(y1), max(1, int(thick))))
            if depth == 0:
                return
            for _ in range(int(rng.integers(2, 4))):
                grow(x1, y1, ang + rng.uniform(-0.75, 0.75), length * rng.uniform(0.6, 0.8), thick * 0.62,
                     depth - 1)

        segs.append((cx, H - 1, cx, crown_base, trunk_w))
        crown_top = int(0.03 * H)
        crown_h = crown_base - crown_top
        for _ in range(int(rng.integers(3, 5))):
            grow(cx, crown_base, rng.uniform(-0.7, 0.7), crown_h * rng.uniform(0.3, 0.42), trunk_w * 0.75, 3)
        # keep the skeleton inside the canvas (branches may not poke out of the billboard)
        segs[:] = [(int(np.clip(a, 1, W - 2)), int(np.clip(b, 1, H - 1)), int(np.clip(c, 1, W - 2)),
                    int(np.clip(d, crown_top, H - 1)), t) for a, b, c, d, t in segs]
        # foliage clusters: near the branch tips, and filling the crown ellipse
        ends = np.array([(s_[2], s_[3]) for s_ in segs[1:]], float)
        ecx, ecy = cx, (crown_top + crown_base) / 2 - 0.05 * H
        erx, ery = W / 2 - 2, crown_h / 2 + 0.03 * H
        n_tip = int(rng.integers(25, 40))
        n_fill = int(rng.integers(25, 40))
        tips = ends[rng.integers(0, len(ends), n_tip)] + rng.normal(0, 0.05 * W, (n_tip, 2))
        ang, rad = rng.uniform(0, 2 * np.pi, n_fill), np.sqrt(rng.uniform(0, 1, n_fill)) * 0.85
        fill = np.stack([ecx + erx * rad * np.cos(ang), ecy + ery * rad * np.sin(ang)], 1)
        pick = np.concatenate([tips, fill])
        n = len(pick)
        rx = rng.uniform(0.07, 0.14, n) * W
        ry = rng.uniform(0.05, 0.1, n) * H
        # clusters stay inside the canvas
        pick[:, 0] = np.clip(pick[:, 0], rx + 1, W - rx - 2)
        pick[:, 1] = np.clip(pick[:, 1], ry + 1, crown_base + 0.05 * H)
        clusters = [(pick[i, 0], pick[i, 1], rx[i], ry[i], rng.random(), rng.integers(len(_SUMMER_GREENS)),
                     rng.integers(len(_AUTUMN))) for i in range(n)]

    # skeleton (always drawn: under snow it is all there is)
    for x0, y0, x1, y1, t in segs:
        cv2.line(img, (x0, y0), (x1, y1), bark.tolist(), t, cv2.LINE_AA)
        cv2.line(alpha, (x0, y0), (x1, y1), 255, t)
    if kind == "birch":
        for _ in range(int(H / 6)):
            y = int(rng.uniform(crown_base, H))
            cv2.line(img, (cx - trunk_w // 2, y), (cx + trunk_w // 2, y), (40, 40, 40), 1)
    leaf_noise = speckle(rng, H, W, 1.2)
    holes = fbm(rng, H, W, cell=max(4, W / 10), octaves=3)

    if kind == "conifer":
        base = np.array(_jitter_colour(rng, (40, 75, 35), 8), np.float32)
        for y, half, shade in clusters:
            pts = np.array([[cx - half, y + 0.12 * H], [cx, y - 0.12 * H], [cx + half, y + 0.12 * H]], np.int32)
            col = base * shade
            if season == "snow":
                col = col * 0.8
            cv2.fillConvexPoly(img, pts, col.tolist(), cv2.LINE_AA)
            cv2.fillConvexPoly(alpha, pts, 255)
            if season == "snow":  # snow lies on each tier's upper edge
                cv2.polylines(img, [pts[:2], pts[1:]], False, (235, 238, 240), max(2, int(0.1 * ppm)))
        img *= (1 + 0.15 * leaf_noise)[..., None]
    elif season != "snow":
        mask = np.zeros((H, W), np.uint8)
        layer = np.zeros_like(img)
        keep_frac = 1.0 if season == "summer" else 0.7
        for (x, y, rx, ry, u, gi, ai) in clusters:
            if u > keep_frac:
                continue
            col = _SUMMER_GREENS[gi] if season == "summer" else _AUTUMN[ai]
            c = np.array(col, np.float32) * (0.75 + 0.5 * (1 - y / H))  # lit from above
            cv2.ellipse(layer, (int(x), int(y)), (int(rx), int(ry)), 0, 0, 360, c.tolist(), -1, cv2.LINE_AA)
            cv2.ellipse(mask, (int(x), int(y)), (int(rx), int(ry)), 0, 0, 360, 255, -1)
        # darker underside of the crown, leaf grain and see-through gaps
        shade = np.linspace(1.15, 0.7, H, dtype=np.float32)[:, None]
        layer *= (shade * (1 + 0.22 * leaf_noise))[..., None]
        thin = 0.33 if season == "summer" else 0.42
        m = (mask > 0) & (holes > thin * (0.6 + 0.4 * (leaf_noise > 1.2)))
        img[m] = layer[m]
        alpha[m] = 255
    else:
        # bare deciduous tree in winter: twigs and snow on the upper side of thick branches
        for x0, y0, x1, y1, t in segs:
            if t >= 3:
                cv2.line(img, (x0, y0 - 1), (x1, y1 - 1), (235, 238, 240), max(1, t // 3))
        for _ in range(int(0.6 * len(segs))):
            s = segs[int(rng.integers(1, len(segs)))]
            a = rng.uniform(0, 2 * np.pi)
            L = rng.uniform(0.03, 0.08) * W
            p1 = (int(s[2] + L * np.cos(a)), int(s[3] + L * np.sin(a)))
            cv2.line(img, (s[2], s[3]), p1, (bark * 0.8).tolist(), 1)
            cv2.line(alpha, (s[2], s[3]), p1, 255, 1)
    return TexData(_clip_u8(img), alpha, [], None, ppm)


def hedge(rng: np.random.Generator, width_m: float, height_m: float, season: str = "summer",
          ppm: float = 24.0, top: bool = False) -> TexData:
    """Hedge face (or top, seen from above at a grazing angle): dense leaf texture."""
    W, H = max(4, int(width_m * ppm)), max(4, int(height_m * ppm))
    base = np.array(_jitter_colour(rng, (40, 100, 55), 10), np.float32)
    n1 = fbm(rng, H, W, cell=ppm * 0.8, octaves=3)
    n2 = speckle(rng, H, W, 0.8)
    img = base * (0.7 + 0.5 * n1)[..., None] * (1 + 0.2 * n2)[..., None]
    alpha = np.full((H, W), 255, np.uint8)
    if not top:
        # irregular clipped top edge
        bump = (fbm(rng, 1, W, cell=ppm * 0.7, octaves=2)[0] * 0.12 * ppm).astype(int)
        for x in range(W):
            alpha[:bump[x], x] = 0
    if season == "autumn":
        img *= np.array([0.8, 0.95, 1.3], np.float32)
    if season == "snow":
        if top:
            img = 236 + 10 * n1[..., None] * np.ones(3, np.float32)
        else:
            cover = np.arange(H)[:, None] < (0.25 + 0.35 * n1) * H
            img[cover] = 235 + 6 * n2[cover][:, None]
            img[~cover] *= 0.6
    return TexData(_clip_u8(img), alpha, [], None, ppm)


def fence(rng: np.random.Generator, width_m: float, kind: str, season: str = "summer",
          ppm: float = 24.0) -> TexData:
    """Railings (cut-out), close-boarded wooden fence, or a low brick/stone wall with coping."""
    from .textures import wall_material

    height = {"railings": 1.2, "wood": 1.8, "wall": 0.8, "picket": 1.0}[kind]
    W, H = max(4, int(width_m * ppm)), max(4, int(height * ppm))
    if kind == "railings":
        img, alpha = _canvas(W, H)
        col = _jitter_colour(rng, rng.choice([(30, 30, 30), (40, 70, 30), (30, 30, 90)]), 5)
        pitch = max(3, int(0.13 * ppm))
        t = max(1, int(0.03 * ppm))
        for x in range(pitch // 2, W, pitch):
            cv2.line(img, (x, 0), (x, H), col, t)
            cv2.line(alpha, (x, 0), (x, H), 255, t)
            cv2.circle(img, (x, 2), t + 1, col, -1)
            cv2.circle(alpha, (x, 2), t + 1, 255, -1)
        for y in (int(0.12 * H), int(0.85 * H)):
            cv2.line(img, (0, y), (W, y), col, t + 1)
            cv2.line(alpha, (0, y), (W, y), 255, t + 1)
        if season == "snow":
            cv2.line(img, (0, int(0.12 * H) - 1), (W, int(0.12 * H) - 1), (240, 240, 240), t)
    elif kind in ("wood", "picket"):
        alpha = np.full((H, W), 255, np.uint8)
        base = np.array(_jitter_colour(rng, (50, 90, 120), 15), np.float32)
        board = max(3, int(0.1 * ppm if kind == "wood" else 0.09 * ppm))
        img = np.empty((H, W, 3), np.float32)
        for x in range(0, W, board):
            img[:, x:x + board] = base * rng.uniform(0.85, 1.15)
        img *= (0.85 + 0.3 * fbm(rng, H, W, cell=ppm, octaves=3))[..., None]
        img[:, ::board] *= 0.55
        if kind == "picket":
            img[:] = np.array(_jitter_colour(rng, (225, 230, 232), 6), np.float32) * (img / base.mean()).mean(2,
                                                                                                          keepdims=True)
            for x in range(0, W, 2 * board):
                alpha[:, x + board:x + 2 * board] = 0
            for x in range(0, W, 2 * board):
                alpha[:int(0.08 * H), x:x + board] = 0
        post = int(1.8 * ppm)
        for x in range(0, W, post):
            img[:, x:x + max(2, int(0.1 * ppm))] = base * 0.6
        if season == "snow":
            img[:max(2, int(0.05 * H))] = 240
    else:  # low wall with coping stones
        alpha = np.full((H, W), 255, np.uint8)
        img = wall_material(rng, H, W, str(rng.choice(["brick", "stone"])), ppm)
        img[:max(2, int(0.12 * ppm))] = np.array(_jitter_colour(rng, (170, 175, 180), 8), np.float32)
        if season == "snow":
            img[:max(2, int(0.15 * ppm))] = 242
    return TexData(_clip_u8(img), alpha, [], None, ppm)


def lamp_post(rng: np.random.Generator, height_m: float, ppm: float = 24.0):
    """Street lamp: pole, arm and lantern.  Returns the texture and the lantern's (u, v) in metres
    from the quad's top-left corner (the light's position for night lighting)."""
    W, H = int(1.6 * ppm), int(height_m * ppm)
    img, alpha = _canvas(W, H)
    emis = np.zeros((H, W), np.uint8)
    col = _jitter_colour(rng, rng.choice([(50, 50, 50), (40, 70, 40), (140, 140, 145)]), 5)
    px = int(0.25 * ppm)
    t = max(2, int(0.12 * ppm))
    cv2.line(img, (px, H), (px, int(0.3 * ppm)), col, t)
    cv2.line(alpha, (px, H), (px, int(0.3 * ppm)), 255, t)
    cv2.rectangle(img, (px - t, H - int(1.0 * ppm)), (px + t, H), col, -1)  # base
    cv2.rectangle(alpha, (px - t, H - int(1.0 * ppm)), (px + t, H), 255, -1)
    ax = W - int(0.2 * ppm)
    cv2.line(img, (px, int(0.3 * ppm)), (ax, int(0.4 * ppm)), col, max(1, t // 2))
    cv2.line(alpha, (px, int(0.3 * ppm)), (ax, int(0.4 * ppm)), 255, max(1, t // 2))
    head = np.array([[ax - int(0.45 * ppm), int(0.35 * ppm)], [ax + int(0.15 * ppm), int(0.35 * ppm)],
                     [ax + int(0.05 * ppm), int(0.6 * ppm)], [ax - int(0.35 * ppm), int(0.6 * ppm)]], np.int32)
    cv2.fillConvexPoly(img, head, col)
    cv2.fillConvexPoly(alpha, head, 255)
    glow = np.array([[ax - int(0.33 * ppm), int(0.5 * ppm)], [ax + int(0.03 * ppm), int(0.5 * ppm)],
                     [ax - 0, int(0.62 * ppm)], [ax - int(0.3 * ppm), int(0.62 * ppm)]], np.int32)
    cv2.fillConvexPoly(img, glow, (200, 225, 235))
    cv2.fillConvexPoly(alpha, glow, 255)
    cv2.fillConvexPoly(emis, glow, 255)
    lantern_uv = ((ax - 0.15 * ppm) / ppm, 0.58)
    return TexData(_clip_u8(img), alpha, [], emis, ppm), lantern_uv


def road_sign(rng: np.random.Generator, kind: str, ppm: float = 40.0, season: str = "summer") -> TexData:
    """A traffic or street-name sign on a post (quad 1 m wide, 2.8 m tall)."""
    W, H = int(1.0 * ppm), int(2.8 * ppm)
    img, alpha = _canvas(W, H)
    cx = W // 2
    cv2.line(img, (cx, H), (cx, int(0.5 * ppm)), (120, 120, 125), max(2, int(0.06 * ppm)))
    cv2.line(alpha, (cx, H), (cx, int(0.5 * ppm)), 255, max(2, int(0.06 * ppm)))
    r = int(0.32 * ppm)
    cy = int(0.45 * ppm)
    if kind == "limit":
        cv2.circle(img, (cx, cy), r, (255, 255, 255), -1)
        cv2.circle(img, (cx, cy), r, (30, 30, 200), max(2, r // 5))
        cv2.circle(alpha, (cx, cy), r + 1, 255, -1)
        txt = str(int(rng.choice([20, 30, 40])))
        (tw, th), _ = cv2.getTextSize(txt, cv2.FONT_HERSHEY_DUPLEX, r / 22, max(1, r // 8))
        cv2.putText(img, txt, (cx - tw // 2, cy + th // 2), cv2.FONT_HERSHEY_DUPLEX, r / 22, (10, 10, 10),
                    max(1, r // 8), cv2.LINE_AA)
    elif kind == "warning":
        pts = np.array([[cx, cy - r], [cx - r, cy + int(0.75 * r)], [cx + r, cy + int(0.75 * r)]], np.int32)
        cv2.fillConvexPoly(img, pts, (30, 30, 200))
        cv2.fillConvexPoly(alpha, pts, 255)
        inner = ((pts - [cx, cy]) * 0.72 + [cx, cy]).astype(np.int32)
        cv2.fillConvexPoly(img, inner, (255, 255, 255))
        sym = int(rng.integers(3))
        if sym == 0:
            cv2.circle(img, (cx, cy + r // 6), r // 6, (10, 10, 10), -1)
        elif sym == 1:
            cv2.line(img, (cx - r // 4, cy + r // 3), (cx + r // 4, cy - r // 6), (10, 10, 10), max(1, r // 8))
        else:
            cv2.putText(img, "!", (cx - r // 8, cy + r // 3), cv2.FONT_HERSHEY_SIMPLEX, r / 40, (10, 10, 10),
                        max(1, r // 8))
    else:  # rectangular: blue information sign or white street-name plate
        blue = kind == "info"
        x0, x1 = int(0.05 * W), int(0.95 * W)
        y0, y1 = int(0.15 * ppm), int((0.85 if blue else 0.45) * ppm)
        cv2.rectangle(img, (x0, y0), (x1, y1), (160, 80, 20) if blue else (250, 250, 250), -1)
        cv2.rectangle(img, (x0, y0), (x1, y1), (255, 255, 255) if blue else (20, 20, 20), 2)
        cv2.rectangle(alpha, (x0, y0), (x1, y1), 255, -1)
        txt = random_word(rng, False)[:8]
        (tw, th), _ = cv2.getTextSize(txt, cv2.FONT_HERSHEY_SIMPLEX, 1.0, 1)
        sc = min((x1 - x0) * 0.9 / tw, (y1 - y0) * 0.45 / th)
        cv2.putText(img, txt, (x0 + 3, (y0 + y1) // 2 + int(th * sc / 2)), cv2.FONT_HERSHEY_SIMPLEX, sc,
                    (255, 255, 255) if blue else (20, 20, 20), max(1, int(sc * 1.5)), cv2.LINE_AA)
        if blue:
            cv2.arrowedLine(img, (x0 + 4, y1 - 6), (x1 - 6, y1 - 6), (255, 255, 255), 2, tipLength=0.2)
    if season == "snow":
        ys, xs = np.nonzero(alpha[:int(1.0 * ppm)])
        if len(ys):
            top = np.full(W, 10 ** 6)
            np.minimum.at(top, xs, ys)
            for x in np.unique(xs):
                img[top[x]:top[x] + 2, x] = 240
    return TexData(_clip_u8(img), alpha, [], None, ppm)


def street_object(rng: np.random.Generator, kind: str, season: str = "summer", ppm: float = 40.0):
    """Small furniture: 'postbox', 'bin', 'bollard', 'bench', 'cabinet'.  Returns (TexData, width, height)."""
    size = {"postbox": (0.6, 1.5), "bin": (0.6, 1.0), "bollard": (0.25, 0.95), "bench": (1.8, 0.9),
            "cabinet": (1.0, 1.3), "beacon": (0.5, 2.8)}[kind]
    W, H = int(size[0] * ppm), int(size[1] * ppm)
    img, alpha = _canvas(W, H)
    emis = None
    if kind == "beacon":  # Belisha beacon: striped pole, orange globe lit day and night
        cx, r = W // 2, W // 2 - 1
        t = max(2, int(0.08 * ppm))
        for y in range(2 * r, H, max(2, int(0.3 * ppm))):
            cv2.line(img, (cx, y), (cx, min(H, y + int(0.3 * ppm))), (20, 20, 20) if (y // int(0.3 * ppm)) % 2
                     else (240, 240, 240), t)
        cv2.line(alpha, (cx, 2 * r), (cx, H), 255, t)
        cv2.circle(img, (cx, r), r, (40, 150, 250), -1, cv2.LINE_AA)
        cv2.circle(alpha, (cx, r), r, 255, -1)
        emis = np.zeros((H, W), np.uint8)
        cv2.circle(emis, (cx, r), r, 255, -1)
    elif kind == "postbox":
        cv2.rectangle(img, (2, int(0.2 * H)), (W - 3, H - 1), (20, 20, 190), -1)
        cv2.ellipse(img, (W // 2, int(0.2 * H)), (W // 2 - 2, int(0.15 * H)), 0, 180, 360, (20, 20, 190), -1)
        cv2.rectangle(alpha, (2, int(0.2 * H)), (W - 3, H - 1), 255, -1)
        cv2.ellipse(alpha, (W // 2, int(0.2 * H)), (W // 2 - 2, int(0.15 * H)), 0, 180, 360, 255, -1)
        cv2.rectangle(img, (W // 5, int(0.3 * H)), (4 * W // 5, int(0.34 * H)), (10, 10, 10), -1)
        cv2.rectangle(img, (W // 4, int(0.45 * H)), (3 * W // 4, int(0.6 * H)), (220, 220, 220), -1)
        cv2.rectangle(img, (0, H - int(0.1 * H)), (W, H), (15, 15, 15), -1)
    elif kind == "bin":
        col = _jitter_colour(rng, rng.choice([(30, 30, 30), (30, 70, 30), (40, 40, 100)]))
        pts = np.array([[3, 4], [W - 4, 4], [W - 8, H - 1], [7, H - 1]], np.int32)
        cv2.fillConvexPoly(img, pts, col)
        cv2.fillConvexPoly(alpha, pts, 255)
        cv2.rectangle(img, (3, 4), (W - 4, int(0.15 * H)), tuple(int(c * 1.5) for c in col), -1)
        cv2.putText(img, "LITTER", (5, H // 2), cv2.FONT_HERSHEY_SIMPLEX, W / 120, (200, 200, 200), 1)
    elif kind == "bollard":
        cv2.rectangle(img, (1, 0), (W - 2, H - 1), (30, 30, 30), -1)
        cv2.rectangle(alpha, (1, 0), (W - 2, H - 1), 255, -1)
        cv2.rectangle(img, (1, int(0.1 * H)), (W - 2, int(0.22 * H)), (240, 240, 240), -1)
    elif kind == "bench":
        wood = _jitter_colour(rng, (60, 100, 140))
        for y in (int(0.1 * H), int(0.25 * H), int(0.5 * H)):
            cv2.rectangle(img, (0, y), (W - 1, y + int(0.08 * H)), wood, -1)
            cv2.rectangle(alpha, (0, y), (W - 1, y + int(0.08 * H)), 255, -1)
        for x in (int(0.1 * W), int(0.9 * W)):
            cv2.line(img, (x, int(0.1 * H)), (x, H), (30, 30, 30), 3)
            cv2.line(alpha, (x, int(0.1 * H)), (x, H), 255, 3)
    else:  # green telecom cabinet
        cv2.rectangle(img, (1, 1), (W - 2, H - 1), (60, 90, 40), -1)
        cv2.rectangle(alpha, (1, 1), (W - 2, H - 1), 255, -1)
        cv2.line(img, (W // 2, 4), (W // 2, H - 4), (30, 50, 20), 2)
        cv2.putText(img, str(int(rng.integers(1, 99))), (4, H // 4), cv2.FONT_HERSHEY_SIMPLEX, W / 80,
                    (230, 230, 230), 1)
    img *= (0.9 + 0.2 * fbm(rng, H, W, cell=max(4, W / 3), octaves=2))[..., None]
    if season == "snow":
        ys, xs = np.nonzero(alpha)
        top = np.full(W, 10 ** 6)
        np.minimum.at(top, xs, ys)
        for x in np.unique(xs):
            img[top[x]:top[x] + max(2, int(0.05 * ppm)), x] = 240
    return TexData(_clip_u8(img), alpha, [], emis, ppm), size


# ----------------------------------------------------------------------------------- distractors
_CAR_COLOURS = [(200, 200, 200), (35, 35, 35), (240, 240, 240), (50, 50, 190), (170, 95, 45), (120, 120, 120),
                (60, 120, 60), (30, 140, 220), (160, 160, 150), (120, 60, 40), (185, 185, 190)]


def car(rng: np.random.Generator, view: str, length_m: float, season: str = "summer", ppm: float = 40.0,
        colour=None, plate: str | None = None) -> TexData:
    """A parked car seen from the 'side', 'rear' or 'front' (cut-out)."""
    height = 1.5
    Wm = length_m if view == "side" else 1.8
    W, H = int(Wm * ppm), int(height * ppm)
    img, alpha = _canvas(W, H)
    col = np.array(colour if colour is not None else _CAR_COLOURS[rng.integers(len(_CAR_COLOURS))], np.float32)
    glass = (70, 60, 50)
    y_sill = int(0.45 * H)
    y_base = H - int(0.2 * ppm)
    if view == "side":
        body = np.array([[2, y_sill], [W - 3, y_sill + 3], [W - 2, y_base], [1, y_base]], np.int32)
        cab = np.array([[int(0.22 * W), y_sill], [int(0.33 * W), 2], [int(0.72 * W), 2], [int(0.86 * W), y_sill]],
                       np.int32)
        for poly in (body, cab):
            cv2.fillConvexPoly(img, poly, col.tolist(), cv2.LINE_AA)
            cv2.fillConvexPoly(alpha, poly, 255)
        win = np.array([[int(0.25 * W), y_sill - 3], [int(0.345 * W), 6], [int(0.70 * W), 6],
                        [int(0.82 * W), y_sill - 3]], np.int32)
        cv2.fillConvexPoly(img, win, glass)
        cv2.line(img, (int(0.53 * W), 6), (int(0.53 * W), y_sill), col.tolist(), 3)
        cv2.line(img, (int(0.53 * W), y_sill), (int(0.53 * W), y_base - 6), (col * 0.6).tolist(), 1)
        for xw in (int(0.18 * W), int(0.82 * W)):
            r = int(0.33 * ppm)
            cv2.circle(img, (xw, H - r - 1), r, (25, 25, 25), -1)
            cv2.circle(alpha, (xw, H - r - 1), r, 255, -1)
            cv2.circle(img, (xw, H - r - 1), r // 2, (150, 150, 155), -1)
        cv2.rectangle(img, (int(0.6 * W), y_sill + 6), (int(0.6 * W) + 6, y_sill + 8), (20, 20, 20), -1)
        # the shadowed underbody between the wheels is dark, never see-through
        cv2.rectangle(img, (int(0.18 * W), y_base - 2), (int(0.82 * W), H - 2), (18, 18, 20), -1)
        cv2.rectangle(alpha, (int(0.18 * W), y_base - 2), (int(0.82 * W), H - 2), 255, -1)
    else:
        body = np.array([[1, y_sill], [W - 2, y_sill], [W - 2, y_base], [1, y_base]], np.int32)
        cab = np.array([[int(0.12 * W), y_sill], [int(0.2 * W), 2], [int(0.8 * W), 2], [int(0.88 * W), y_sill]],
                       np.int32)
        for poly in (body, cab):
            cv2.fillConvexPoly(img, poly, col.tolist(), cv2.LINE_AA)
            cv2.fillConvexPoly(alpha, poly, 255)
        win = np.array([[int(0.16 * W), y_sill - 3], [int(0.23 * W), 6], [int(0.77 * W), 6],
                        [int(0.84 * W), y_sill - 3]], np.int32)
        cv2.fillConvexPoly(img, win, glass)
        light = (30, 30, 200) if view == "rear" else (230, 230, 220)
        for x0 in (3, W - 3 - int(0.25 * W)):
            cv2.rectangle(img, (x0, y_sill + 4), (x0 + int(0.25 * W), y_sill + int(0.12 * H)), light, -1)
        pw, ph = int(0.52 * ppm), int(0.11 * ppm)
        px, py = W // 2 - pw // 2, y_base - int(0.32 * ppm)
        cv2.rectangle(img, (px, py), (px + pw, py + ph), (40, 200, 240) if view == "rear" else (245, 245, 245), -1)
        plate = plate or "".join(rng.choice(list("ABCDEFGHJKLMNPRSTVWXY0123456789"), 7))
        cv2.putText(img, plate, (px + 1, py + ph - 1), cv2.FONT_HERSHEY_PLAIN, ph / 14, (10, 10, 10), 1)
        cv2.rectangle(img, (1, y_base - int(0.12 * ppm)), (W - 2, y_base), (25, 25, 25), -1)
        if view == "front":
            cv2.rectangle(img, (int(0.35 * W), y_sill + 6), (int(0.65 * W), y_sill + int(0.2 * H)), (30, 30, 30), -1)
        cv2.rectangle(img, (int(0.08 * W), y_base), (int(0.92 * W), H - 2), (18, 18, 20), -1)
        cv2.rectangle(alpha, (int(0.08 * W), y_base), (int(0.92 * W), H - 2), 255, -1)
    img *= (0.9 + 0.15 * np.linspace(1.0, 0.0, H, dtype=np.float32))[:, None, None]
    if season == "snow":  # snow on the roof and bonnet
        ys, xs = np.nonzero(alpha[: H // 2])
        top = np.full(W, 10 ** 6)
        np.minimum.at(top, xs, ys)
        for x in np.unique(xs):
            img[top[x]:top[x] + int(0.08 * ppm), x] = 242
    return TexData(_clip_u8(img), alpha, [], None, ppm)


def pedestrian(rng: np.random.Generator, season: str = "summer", umbrella: bool = False,
               ppm: float = 60.0) -> TexData:
    """A pedestrian billboard, 0.8 m x 1.9 m (cut-out), dressed for the season."""
    W, H = int(0.8 * ppm), int(1.9 * ppm)
    img, alpha = _canvas(W, H)
    height = rng.uniform(1.55, 1.9)
    top = H - int(height * ppm)
    cx = W // 2
    skin = _jitter_colour(rng, rng.choice([(150, 180, 225), (110, 150, 200), (60, 90, 130), (40, 60, 90)]), 10)
    coat = _jitter_colour(rng, rng.choice([(30, 30, 30), (120, 60, 20), (40, 40, 150), (150, 150, 150),
                                           (50, 100, 50), (180, 200, 220), (40, 140, 200)]), 20)
    legs = _jitter_colour(rng, rng.choice([(110, 60, 30), (30, 30, 30), (80, 80, 80), (140, 150, 170)]), 10)
    hh = int(0.12 * height * ppm)
    shoulder = top + int(0.18 * height * ppm)
    hip = top + int(0.52 * height * ppm)
    bw = int(rng.uniform(0.36, 0.46) * ppm) if season != "snow" else int(0.48 * ppm)
    stride = rng.uniform(-0.12, 0.12) * ppm

    def fill(poly, c):
        p = np.array(poly, np.int32)
        cv2.fillConvexPoly(img, p, c, cv2.LINE_AA)
        cv2.fillConvexPoly(alpha, p, 255)

    fill([[cx - bw // 2, shoulder], [cx + bw // 2, shoulder], [cx + bw // 2 - 2, hip + (int(0.1 * ppm) if season in
          ("snow", "autumn") else 0)], [cx - bw // 2 + 2, hip]], coat)
    for sgn in (-1, 1):  # legs
        fill([[cx + sgn * 2, hip], [cx + sgn * int(0.16 * ppm), hip], [cx + sgn * int(0.12 * ppm) + sgn * stride, H - 4],
              [cx + sgn * int(0.02 * ppm) + sgn * stride, H - 4]], legs)
        fill([[cx + sgn * int(0.02 * ppm) + sgn * stride - 3, H - 5], [cx + sgn * int(0.14 * ppm) + sgn * stride + 4,
              H - 5], [cx + sgn * int(0.14 * ppm) + sgn * stride + 4, H - 1], [cx + sgn * int(0.02 * ppm) + sgn * stride - 3,
              H - 1]], (20, 20, 20))
        fill([[cx + sgn * bw // 2, shoulder], [cx + sgn * (bw // 2 + 5), shoulder + 4],
              [cx + sgn * (bw // 2 + 3), hip], [cx + sgn * (bw // 2 - 3), hip]], coat)
    cv2.circle(img, (cx, top + hh // 2 + 2), hh // 2, skin, -1, cv2.LINE_AA)
    cv2.circle(alpha, (cx, top + hh // 2 + 2), hh // 2, 255, -1)
    hair = _jitter_colour(rng, rng.choice([(20, 20, 20), (30, 60, 90), (120, 170, 200), (150, 150, 150)]), 10)
    cv2.ellipse(img, (cx, top + hh // 2), (hh // 2, hh // 3), 0, 180, 360, hair, -1)
    if season == "snow" or rng.random() < 0.2:  # hat
        cv2.ellipse(img, (cx, top + hh // 3), (hh // 2 + 1, hh // 3), 0, 180, 360,
                    _jitter_colour(rng, (60, 60, 160), 40), -1)
    if rng.random() < 0.3:  # bag
        bx = cx + bw // 2
        fill([[bx, hip - int(0.2 * ppm)], [bx + int(0.15 * ppm), hip - int(0.2 * ppm)], [bx + int(0.15 * ppm), hip],
              [bx, hip]], _jitter_colour(rng, (40, 60, 90), 30))
    if umbrella:
        uc = _jitter_colour(rng, rng.choice([(20, 20, 20), (30, 30, 180), (160, 60, 20)]), 20)
        cv2.ellipse(img, (cx, top), (W // 2 - 1, int(0.18 * ppm)), 0, 180, 360, uc, -1)
        cv2.ellipse(alpha, (cx, top), (W // 2 - 1, int(0.18 * ppm)), 0, 180, 360, 255, -1)
        cv2.line(img, (cx, top), (cx, shoulder), (30, 30, 30), 1)
    return TexData(_clip_u8(img), alpha, [], None, ppm)
