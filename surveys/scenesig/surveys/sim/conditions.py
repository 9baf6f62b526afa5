"""Appearance conditions: lighting baked into textures, and per-frame camera/weather effects.

Each run has one condition.  What it changes, and how (the aim is appearance change as strong as a
real survey vehicle sees between days):

================  ==============================================================================
sunny             high sun (45-60 deg), hard cast shadows on the ground, bright clear sky, glare
                  when driving towards the sun.
morning           low sun (7-14 deg): long shadows, warm light, back-lit facades, strong glare.
overcast          no direct light, flat shading, grey cloud, lower contrast and saturation.
dusk              sky light only (ambient 0.09), street lamps, some lit windows, headlights,
                  sensor noise, slight motion blur.
night             dark except what lamps, lit windows and the headlight cone illuminate; high
                  sensor noise, motion blur (long exposure), bloom around lights.
rain              dark grey sky, wet road (darker asphalt mirroring the scene), rain streaks,
                  haze, low contrast, lens blur.
fog               per-pixel attenuation by true depth, visibility 30-80 m (Koschmieder: contrast
                  falls to 5 % at the visibility distance), washed-out colour.
snow              snow season: white ground and roofs, markings gone, bare trees, snow on ledges;
                  flat light, camera exposure pulled down by the snow, falling flakes, haze.
autumn            autumn season (orange/thinned foliage, leaves on the ground), lower sun.
================  ==============================================================================

Two lighting paths:

* Day conditions *bake* lighting into each texture once per run: ``albedo * (ambient + sun *
  max(0, n.s) * (1 - shadow))``, with cast shadows rasterised into ground textures from the sun's
  projection of every caster (facades, roofs, hedges, trees, parked cars).
* Lamp-lit conditions (dusk, night) keep the albedo in BGR and put the light level ``L`` (ambient +
  street lamps, cosine / distance^2, + lit windows and lamp heads as emitters) in the texture's 4th
  channel, encoded ``a = 128 + 127 sqrt(L / L_MAX)`` (``a < 128`` stays "transparent").  The
  headlight depends on the vehicle pose, so it is added per frame from the depth buffer:
  ``pixel = albedo * (L + headlight(u, v, depth)) * gain``.

Per-frame effects (:class:`PostProcessor`) work on the rendered buffers, vectorised: lighting
decode, wet-road reflection (the image mirrored about the horizon, on street pixels), fog by depth,
sun glare, bloom, rain streaks / snowflakes, motion blur along the true image motion, optics blur,
tone curve and sensor noise.  All randomness is drawn from generators keyed by run and frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .render import build_pyramid
from .textures import TexData

__all__ = ["Condition", "CONDITIONS", "make_condition", "bake_texture", "ShadowCaster", "PostProcessor",
           "L_MAX", "encode_light"]

L_MAX = 6.0


@dataclass
class Condition:
    """Parameters of one appearance condition (one run's draw, see :func:`make_condition`)."""

    name: str
    season: str = "summer"
    sun_elev: float | None = None      # degrees; None = no direct sun
    sun_az: float = 0.0                # radians, world frame
    sun: float = 1.0
    ambient: float = 0.45
    exposure: float | None = None      # None: normalise the sunlit ground to ~0.95
    lamp_lit: bool = False
    lamp_intensity: float = 45.0
    window_fraction: float = 0.0
    headlight: float = 0.0
    gain: float = 1.0
    sky: dict = field(default_factory=dict)
    contrast: float = 1.0
    saturation: float = 1.0
    gamma: float = 1.0
    tint: tuple = (1.0, 1.0, 1.0)      # B, G, R multipliers (white balance)
    fog_visibility: float | None = None
    fog_colour: tuple = (200, 200, 198)
    wet: bool = False
    rain_streaks: int = 0
    snowflakes: int = 0
    noise: float = 2.0                 # std of sensor noise (8-bit DN)
    exposure_time: float = 0.0         # seconds, for motion blur
    optics_blur: float = 0.5
    glare: bool = False
    bloom: float = 0.0
    odometry_factor: float = 1.0       # VO error multiplier (see surveys.sim.motion)
    clock: tuple = (2014, 7, 1, 13, 0)  # year, month, day, hour, minute of the run's start

    def sun_vector(self) -> np.ndarray | None:
        if self.sun_elev is None:
            return None
        e = np.radians(self.sun_elev)
        return np.array([np.cos(e) * np.cos(self.sun_az), np.cos(e) * np.sin(self.sun_az), np.sin(e)])

    def day_exposure(self) -> float:
        if self.exposure is not None:
            return self.exposure
        top = self.ambient + (self.sun * np.sin(np.radians(self.sun_elev)) if self.sun_elev is not None else 0)
        return 0.95 / top


_SKY_CLEAR = {"zenith": (205, 140, 80), "horizon": (235, 215, 195), "below": (175, 175, 170),
              "cloud": (250, 250, 250), "cloud_dark": (200, 200, 205), "coverage": 0.25, "glow": (90, 200, 255)}

CONDITIONS = {
    "sunny": Condition("sunny", sun_elev=52.0, ambient=0.42, sky=_SKY_CLEAR, contrast=1.05, saturation=1.05,
                       glare=True, noise=2.0, clock=(2014, 7, 14, 13, 0)),
    "morning": Condition("morning", sun_elev=10.0, ambient=0.3, sun=1.1, exposure=1.35,
                         sky={"zenith": (205, 165, 125), "horizon": (200, 215, 232), "below": (150, 160, 170),
                              "cloud": (220, 228, 245), "cloud_dark": (175, 180, 200), "coverage": 0.15,
                              "glow": (50, 110, 170)},
                         tint=(0.9, 0.97, 1.06), fog_visibility=500.0, fog_colour=(200, 208, 218), glare=True,
                         noise=2.5, odometry_factor=1.2, clock=(2014, 5, 6, 7, 40)),
    "overcast": Condition("overcast", ambient=1.0, exposure=0.9,
                          sky={"zenith": (178, 174, 170), "horizon": (205, 203, 200), "below": (170, 170, 168),
                               "cloud": (200, 200, 200), "cloud_dark": (150, 150, 155), "coverage": 0.95},
                          contrast=0.9, saturation=0.85, noise=2.5, clock=(2014, 10, 2, 11, 0)),
    "dusk": Condition("dusk", ambient=0.09, lamp_lit=True, lamp_intensity=40.0, window_fraction=0.35,
                      headlight=0.9, gain=1.5,
                      sky={"zenith": (95, 55, 35), "horizon": (90, 135, 205), "below": (55, 62, 70),
                           "cloud": (120, 110, 190), "cloud_dark": (75, 65, 100), "coverage": 0.3},
                      contrast=0.95, noise=6.0, exposure_time=0.025, optics_blur=0.7, bloom=0.3,
                      odometry_factor=1.8, clock=(2014, 11, 3, 16, 40)),
    "night": Condition("night", ambient=0.012, lamp_lit=True, lamp_intensity=45.0, window_fraction=0.25,
                       headlight=1.1, gain=1.3,
                       sky={"zenith": (22, 12, 8), "horizon": (45, 55, 70), "below": (15, 15, 18),
                            "cloud": (50, 60, 75), "cloud_dark": (25, 25, 30), "coverage": 0.3},
                       noise=7.0, exposure_time=0.04, optics_blur=0.8, bloom=0.6, odometry_factor=3.0,
                       clock=(2014, 11, 20, 22, 10)),
    "rain": Condition("rain", ambient=0.6, exposure=1.0, wet=True, rain_streaks=450,
                      sky={"zenith": (118, 116, 112), "horizon": (150, 148, 145), "below": (110, 110, 110),
                           "cloud": (140, 140, 140), "cloud_dark": (95, 95, 100), "coverage": 1.0},
                      contrast=0.72, saturation=0.75, fog_visibility=300.0, fog_colour=(150, 150, 148),
                      noise=3.0, optics_blur=1.0, odometry_factor=1.6,
                      clock=(2014, 11, 12, 15, 30)),
    "fog": Condition("fog", ambient=0.85, exposure=0.95,
                     sky={"zenith": (200, 200, 198), "horizon": (200, 200, 198), "below": (200, 200, 198),
                          "coverage": 0.0},
                     contrast=0.9, saturation=0.7, fog_visibility=50.0, fog_colour=(200, 200, 198), noise=3.0,
                     odometry_factor=2.2, clock=(2014, 12, 4, 9, 0)),
    "snow": Condition("snow", season="snow", ambient=0.95, exposure=0.8, snowflakes=600,
                      sky={"zenith": (212, 208, 205), "horizon": (225, 222, 220), "below": (215, 212, 210),
                           "cloud": (230, 230, 230), "cloud_dark": (190, 190, 192), "coverage": 0.8},
                      contrast=0.85, saturation=0.7, fog_visibility=220.0, fog_colour=(215, 213, 212),
                      tint=(1.05, 1.0, 0.96), noise=3.0, odometry_factor=1.4, clock=(2015, 1, 22, 12, 0)),
    "autumn": Condition("autumn", season="autumn", sun_elev=26.0, ambient=0.45, sun=0.9,
                        sky=dict(_SKY_CLEAR, coverage=0.45), tint=(0.9, 0.97, 1.05), glare=True, noise=2.5,
                        odometry_factor=1.1, clock=(2014, 10, 21, 14, 0)),
}


def make_condition(name: str, rng: np.random.Generator) -> Condition:
    """One run's draw of a condition: sun azimuth/elevation, fog visibility, lit windows vary per run."""
    if name not in CONDITIONS:
        raise ValueError(f"unknown condition {name!r}; choose from {', '.join(CONDITIONS)}")
    c = CONDITIONS[name]
    kw = {"sun_az": float(rng.uniform(0, 2 * np.pi))}
    if c.sun_elev is not None:
        lo, hi = {"sunny": (45, 60), "morning": (7, 14), "autumn": (20, 32)}.get(name, (c.sun_elev, c.sun_elev))
        kw["sun_elev"] = float(rng.uniform(lo, hi))
    if name == "fog":
        kw["fog_visibility"] = float(rng.uniform(30, 80))
    elif c.fog_visibility is not None:
        kw["fog_visibility"] = float(c.fog_visibility * rng.uniform(0.8, 1.25))
    if c.window_fraction:
        kw["window_fraction"] = float(c.window_fraction * rng.uniform(0.7, 1.3))
    if c.snowflakes:
        kw["snowflakes"] = int(c.snowflakes * rng.uniform(0.5, 1.3))
    return replace(c, **kw)


def encode_light(L: np.ndarray) -> np.ndarray:
    """Light level -> 4th-channel code (128..255); see the module docstring."""
    return (128 + np.round(127 * np.sqrt(np.clip(L / L_MAX, 0, 1)))).astype(np.uint8)


_DECODE = np.where(np.arange(256) >= 128, ((np.arange(256) - 128) / 127.0) ** 2 * L_MAX, 0).astype(np.float32)


# ----------------------------------------------------------------------------------- shadows
@dataclass
class ShadowCaster:
    """Sun shadows on the ground plane: polygons (world x, y) with a darkness each, and their boxes."""

    polys: list
    dark: np.ndarray
    boxes: np.ndarray  # (P, 4) xmin, ymin, xmax, ymax

    @classmethod
    def build(cls, sun: np.ndarray, quad_corners: np.ndarray, boards_base: np.ndarray, boards_size: np.ndarray):
        polys, dark = [], []
        shift = sun[:2] / sun[2]  # ground offset per metre of height (away from the sun)

        def proj(P):
            return P[:, :2] - np.outer(P[:, 2], shift)

        for C in quad_corners:
            pts = proj(C)
            hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2)
            polys.append(hull.astype(np.float64))
            dark.append(1.0)
        # trees: crown ellipse in the vertical plane square to the sun, and the trunk
        perp = np.array([-sun[1], sun[0], 0.0])
        perp /= max(np.linalg.norm(perp), 1e-9)
        ang = np.linspace(0, 2 * np.pi, 14, endpoint=False)
        for b, (w, h) in zip(boards_base, boards_size):
            crown = b + np.outer(0.42 * w * np.cos(ang), perp) + np.outer(0.62 * h + 0.3 * h * np.sin(ang),
                                                                           [0, 0, 1])
            polys.append(cv2.convexHull(proj(crown).astype(np.float32)).reshape(-1, 2).astype(np.float64))
            dark.append(0.8)
            tw = max(0.15, 0.04 * w)
            trunk = np.array([b - perp * tw, b + perp * tw, b + perp * tw + [0, 0, 0.5 * h], b - perp * tw + [0, 0, 0.5 * h]])
            polys.append(cv2.convexHull(proj(trunk).astype(np.float32)).reshape(-1, 2).astype(np.float64))
            dark.append(1.0)
        boxes = np.array([[p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()] for p in polys]).reshape(-1, 4)
        return cls(polys, np.array(dark), boxes)

    def mask(self, Wn: np.ndarray, shape: tuple) -> np.ndarray | None:
        """Shadow darkness (h, w) float32 for a horizontal ground quad with texture map ``Wn``."""
        h, w = shape
        G = Wn[[0, 1, 3]]  # (u, v, 1) -> (x, y, 1) on the ground plane
        corners = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float) @ G.T
        corners = corners[:, :2] / corners[:, 2:]
        lo, hi = corners.min(0), corners.max(0)
        sel = np.nonzero((self.boxes[:, 0] <= hi[0]) & (self.boxes[:, 2] >= lo[0]) & (self.boxes[:, 1] <= hi[1])
                         & (self.boxes[:, 3] >= lo[1]))[0]
        if len(sel) == 0:
            return None
        Gi = np.linalg.inv(G)
        sc = 0.5  # shadows are soft: rasterise at half resolution
        hs, ws = max(2, int(h * sc)), max(2, int(w * sc))
        m = np.zeros((hs, ws), np.float32)
        for i in sel:
            p = np.c_[self.polys[i], np.ones(len(self.polys[i]))] @ Gi.T
            if np.any(p[:, 2] <= 0):
                continue
            uv = p[:, :2] / p[:, 2:]
            px = np.stack([uv[:, 0] * ws - 0.5, uv[:, 1] * hs - 0.5], 1)
            cv2.fillPoly(m, [np.round(px * 16).astype(np.int32)], float(self.dark[i]), cv2.LINE_AA, shift=4)
        if not m.any():
            return None
        m = cv2.GaussianBlur(m, (0, 0), 1.0)
        return cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR)


# ----------------------------------------------------------------------------------- baking
def _bleed(alb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Give transparent texels the average colour of nearby opaque ones.

    Bilinear sampling and mip-mapping mix transparent texels into the edges of cut-outs; if those
    are black, every tree and lamp post gets a dark halo.
    """
    a = (alpha >= 128).astype(np.float32)
    num = cv2.blur(alb * a[..., None], (7, 7))
    den = cv2.blur(a, (7, 7))[..., None]
    fill = num / np.maximum(den, 1e-6)
    far = den < 1e-6
    if far.any():  # beyond the first ring: the cut-out's mean colour
        mean = (alb * a[..., None]).sum((0, 1)) / max(float(a.sum()), 1.0)
        fill = np.where(far, mean, fill)
    return np.where(a[..., None] > 0, alb, fill)


def _grid_points(Wn, h, w, step):
    gh, gw = max(2, int(np.ceil(h / step)) + 1), max(2, int(np.ceil(w / step)) + 1)
    u = np.linspace(0, 1, gw)
    v = np.linspace(0, 1, gh)
    U, V = np.meshgrid(u, v)
    q = np.stack([U, V, np.ones_like(U)], -1) @ Wn.T
    return q[..., :3] / q[..., 3:], (gh, gw)


def bake_texture(td: TexData, cond: Condition, cls_name: str, rng: np.random.Generator, Wn: np.ndarray | None = None,
                 normal: np.ndarray | None = None, board: tuple | None = None, lamps: np.ndarray | None = None,
                 shadows: ShadowCaster | None = None, levels: int = 7) -> list:
    """Condition variant of one texture as a mip pyramid of BGRA levels.

    Parameters
    ----------
    Wn, normal : texture map and unit normal of a fixed quad (or ``board`` = (base, (w, h)) for a billboard).
    lamps : (L, 3) lantern positions (lamp-lit conditions).
    shadows : ground shadow caster (sunny conditions; applied to 'street' and 'ground' quads).
    """
    h, w = td.shape
    alb = td.bgr.astype(np.float32)
    alpha = td.alpha if td.alpha is not None else np.full((h, w), 255, np.uint8)
    if td.alpha is not None:
        alb = _bleed(alb, alpha)
    if cond.saturation != 1.0:  # baked: cheaper than per frame, and fog/glare desaturate on their own
        g = alb.mean(2, keepdims=True)
        alb = g + (alb - g) * cond.saturation
    if cls_name == "vegetation":
        # leaves move in the wind and catch the light differently every day: the crown's fine texture
        # is redrawn per run (its shape is not), so point features on foliage do not repeat
        from .noise import speckle

        alb *= (1.0 + 0.22 * speckle(rng, h, w, 1.0))[..., None]
    if cond.wet and cls_name == "street":
        alb *= 0.62  # wet asphalt and paving are darker (and mirror the scene, added per frame)
    if cls_name == "skyline":
        # aerial perspective: distant silhouettes take on the horizon colour
        hor = np.array(cond.sky.get("horizon", (200, 200, 200)), np.float32)
        alb = 0.4 * alb + 0.6 * hor * (0.75 if not cond.lamp_lit else 0.12)
    if not cond.lamp_lit:
        sun = cond.sun_vector()
        shade = np.float32(cond.ambient)
        if sun is not None:
            if board is not None or cls_name == "skyline":
                ns = 0.55  # billboards and far silhouettes: no single face orientation
            else:
                ns = max(0.0, float(np.dot(normal, sun))) if normal is not None else 0.5
                # two-sided quads: a face turned away from the viewer may still face the sun; use |n.s|
                # only for thin things (fences, signs), walls keep one lit side
                if cls_name in ("furniture", "car") and normal is not None:
                    ns = abs(float(np.dot(normal, sun)))
            direct = cond.sun * ns
            if shadows is not None and cls_name in ("street", "ground") and Wn is not None:
                m = shadows.mask(Wn, (h, w))
                shade = cond.ambient + direct * (1 - m) if m is not None else np.float32(cond.ambient + direct)
            else:
                shade = np.float32(cond.ambient + direct)
        gain = cond.day_exposure()
        out = alb * (np.asarray(shade, np.float32) * gain)[..., None] if np.ndim(shade) else alb * float(shade * gain)
        bgr = np.clip(out, 0, 255).astype(np.uint8)
        bgra = np.dstack([bgr, alpha])
        return build_pyramid(bgra, levels)

    # lamp-lit: light level per texel (coarse grid, then upsampled)
    step = 8
    if board is not None:
        base, (bw, bh) = board
        gh = max(2, int(np.ceil(h / step)) + 1)
        zz = (1 - np.linspace(0, 1, gh)) * bh + base[2]
        P = np.zeros((gh, 2, 3))
        P[:, :, 0], P[:, :, 1], P[:, :, 2] = base[0], base[1], zz[:, None]
        nrm = None
    else:
        P, (gh, gw) = _grid_points(Wn, h, w, step)
        nrm = normal
    L = np.full(P.shape[:2], cond.ambient, np.float32)
    if lamps is not None and len(lamps):
        c = P.reshape(-1, 3).mean(0)
        rad = np.linalg.norm(P.reshape(-1, 3) - c, axis=1).max()
        near = lamps[np.linalg.norm(lamps - c, axis=1) < rad + 45.0]
        for lp in near:
            v = lp - P
            d2 = np.einsum("...i,...i->...", v, v)
            if nrm is None:
                cos = 0.7
            else:
                cos = np.abs(np.einsum("...i,i->...", v, nrm)) / np.sqrt(d2 + 1e-9)
            L += cond.lamp_intensity * cos / (d2 + 4.0)
    L = cv2.resize(L.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    # emitters: a run's own subset of lit windows, and always-on lamp heads / beacons
    for (x0, y0, x1, y1) in td.windows:
        if rng.random() < cond.window_fraction:
            warm = np.array([rng.uniform(60, 140), rng.uniform(150, 210), rng.uniform(215, 255)], np.float32)
            sub = alb[y0:y1, x0:x1]
            # curtains and blinds stay visible as darker parts of the glow
            lum = sub.mean(2, keepdims=True) / max(float(sub.mean()), 1.0)
            alb[y0:y1, x0:x1] = warm * np.clip(0.6 + 0.4 * lum, 0.4, 1.4)
            L[y0:y1, x0:x1] = rng.uniform(1.2, 2.6)
    if td.emissive is not None:
        e = td.emissive > 0
        alb[e] = np.array([200, 235, 250], np.float32)
        L[e] = L_MAX
    a = encode_light(L)
    a = np.where(alpha >= 128, a, 0).astype(np.uint8)
    bgra = np.dstack([np.clip(alb, 0, 255).astype(np.uint8), a])
    return build_pyramid(bgra, levels)


# ----------------------------------------------------------------------------------- per frame
class PostProcessor:
    """Per-frame effects for one condition and camera (precomputes the static maps)."""

    def __init__(self, cond: Condition, camera, rng: np.random.Generator, bank: int = 3):
        self.c = cond
        self.cam = camera
        W, H = camera.width, camera.height
        self.W, self.H = W, H
        u = (np.arange(W, dtype=np.float32) - camera.cx) / camera.fx
        v = (np.arange(H, dtype=np.float32) - camera.cy) / camera.fy
        self.U, self.V = np.meshgrid(u, v)
        r2 = self.U ** 2 + self.V ** 2
        vig = (1.0 - 0.22 * r2 / r2.max()).astype(np.float32)
        self.vignette3 = np.repeat(np.round(vig * 255)[..., None], 3, axis=2).astype(np.uint8)
        self.ray_len = np.sqrt(1 + r2).astype(np.float32)
        if cond.headlight:
            # dipped beams: wide horizontally, centred a little below the horizon, sharp upper cut-off
            ah = np.arctan(self.U)
            av = np.arctan(self.V)
            cone = np.exp(-(ah / 0.38) ** 2) * np.exp(-((av - 0.06) / 0.12) ** 2)
            cone *= 1 / (1 + np.exp(-(av + 0.015) / 0.008))
            self.cone = (cond.headlight * cone).astype(np.float32)
        s = max(W, H) / 640
        self.noise_bank = [np.round(rng.standard_normal((H + 32, W + 32, 3), dtype=np.float32) * cond.noise)
                           .astype(np.int16) for _ in range(bank)]
        self.scale = s
        # tone curve: contrast about mid-grey, gamma, white balance
        x = np.arange(256, dtype=np.float32) / 255
        y = (x ** cond.gamma - 0.5) * cond.contrast + 0.5
        self.lut = np.clip(np.stack([y * t for t in cond.tint], -1) * 255, 0, 255).astype(np.uint8).reshape(256, 1, 3)
        self.fog_img = np.empty((H, W, 3), np.uint8)
        self.fog_img[:] = np.array(cond.fog_colour, np.uint8)

    def __call__(self, fb: np.ndarray, invz: np.ndarray, cls: np.ndarray, depth: np.ndarray, rng: np.random.Generator,
                 T_world_camera: np.ndarray, velocity: tuple = (0.0, 0.0)) -> np.ndarray:
        """Finish a frame: rendered buffers -> BGR uint8 camera image.

        velocity : (forward speed m/s, yaw rate rad/s) of the camera, for motion blur.
        """
        c = self.c
        if c.lamp_lit or c.wet or c.bloom:
            img = fb[..., :3].astype(np.float32)
            if c.lamp_lit:
                L = _DECODE[fb[..., 3]]
                if c.headlight:
                    r = np.minimum(depth, 1e4) * self.ray_len * np.float32(1 / 14.0)
                    L += self.cone / (1 + r * r)
                img *= (L * c.gain)[..., None]
            if c.wet:
                img = self._wet(img, cls, T_world_camera)
            if c.bloom:
                small = cv2.resize(img, (self.W // 4, self.H // 4), interpolation=cv2.INTER_AREA)
                bright = np.clip(small.max(2) - 200, 0, None)
                if bright.max() > 0:
                    sm = cv2.GaussianBlur(bright, (0, 0), 4.0 * self.scale)
                    glow = cv2.resize(sm, (self.W, self.H), interpolation=cv2.INTER_LINEAR) * (c.bloom * 2.5)
                    img += glow[..., None] * np.array([0.8, 0.95, 1.0], np.float32)
            out = cv2.convertScaleAbs(img)
        else:
            out = cv2.cvtColor(fb, cv2.COLOR_BGRA2BGR)
        if c.fog_visibility:
            # Koschmieder: transmission exp(-3 range / visibility); the sky (inf) is all fog
            t = cv2.exp(depth * self.ray_len * np.float32(-3.0 / c.fog_visibility))
            out = cv2.blendLinear(out, self.fog_img, t, 1 - t)
        if c.glare:
            g = self._glare_map(T_world_camera)
            if g is not None:
                out = cv2.add(out, np.minimum(g, 255).astype(np.uint8))
        out = cv2.multiply(out, self.vignette3, scale=1 / 255.0)
        if c.rain_streaks:
            out = self._streaks(out, rng)
        if c.snowflakes:
            out = self._flakes(out, rng)
        if c.exposure_time and velocity[0] > 0.2:
            out = self._motion_blur(out, depth, velocity)
        if c.optics_blur:
            out = cv2.GaussianBlur(out, (0, 0), c.optics_blur * self.scale)
        out = cv2.LUT(out, self.lut)
        if c.noise:
            n = self.noise_bank[int(rng.integers(len(self.noise_bank)))]
            oy, ox = int(rng.integers(0, 32)), int(rng.integers(0, 32))
            out = np.clip(out.astype(np.int16) + n[oy:oy + self.H, ox:ox + self.W], 0, 255).astype(np.uint8)
        return out

    # -- effects
    def _horizon_rows(self, T_world_camera):
        """Image row of the horizon at the left and right image edges."""
        R = T_world_camera[:3, :3]
        up_c = R.T @ np.array([0, 0, 1.0])  # world up in camera coordinates
        rows = []
        for x in (0.0, self.W - 1.0):
            u = (x - self.cam.cx) / self.cam.fx
            # ray (u, v, 1) horizontal  <=>  up_c . (u, v, 1) = 0
            v = -(up_c[0] * u + up_c[2]) / up_c[1] if abs(up_c[1]) > 1e-9 else 0.0
            rows.append(v * self.cam.fy + self.cam.cy)
        return rows

    def _wet(self, img, cls, T_world_camera):
        """Wet street: blend in the scene mirrored about the horizon (computed at half resolution: the
        reflection on wet asphalt is blurred anyway)."""
        street = cls == 3
        if not street.any():
            return img
        r0, r1 = self._horizon_rows(T_world_camera)
        h2, w2 = self.H // 2, self.W // 2
        small = cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA)
        xs = np.arange(w2, dtype=np.float32)
        vh = (r0 + (r1 - r0) * (xs * 2) / max(self.W - 1, 1)) / 2
        ys = np.arange(h2, dtype=np.float32)[:, None]
        map_y = (2 * vh[None, :] - ys).astype(np.float32)
        if not hasattr(self, "_wet_mx"):
            self._wet_mx = np.broadcast_to(xs[None, :], (h2, w2)).astype(np.float32)
        refl = cv2.remap(small, self._wet_mx, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        refl = cv2.blur(refl, (3, 9))
        # Fresnel: grazing reflections (near the horizon) are strongest
        fres = np.clip(1.0 - (ys - vh[None, :]) / (0.25 * self.H), 0.15, 1.0) * 0.55
        refl = cv2.resize(refl, (self.W, self.H), interpolation=cv2.INTER_LINEAR)
        fres = cv2.resize(fres.astype(np.float32), (self.W, self.H), interpolation=cv2.INTER_LINEAR)
        wgt = (fres * street)[..., None]
        img += (refl - img) * wgt
        return img

    def _glare_map(self, T_world_camera):
        """Sun halo plus veiling glare (added light, float32 (H, W, 3)) when driving towards the sun."""
        sun = self.c.sun_vector()
        if sun is None:
            return None
        d = T_world_camera[:3, :3].T @ sun
        if d[2] <= 0.05:
            return None
        ang = np.degrees(np.arccos(np.clip(d[2], -1, 1)))
        if ang > 60:
            return None
        u = self.cam.fx * d[0] / d[2] + self.cam.cx
        v = self.cam.fy * d[1] / d[2] + self.cam.cy
        k = (1 - ang / 60.0) ** 2
        strength = 140.0 * k * (1.6 if self.c.sun_elev is not None and self.c.sun_elev < 20 else 0.8)
        f = 8  # smooth: compute at 1/8 resolution
        X = (np.arange(0, self.W, f, dtype=np.float32) - u)[None, :]
        Y = (np.arange(0, self.H, f, dtype=np.float32) - v)[:, None]
        r = np.sqrt(X * X + Y * Y) / self.W
        glow = (strength * (np.exp(-r / 0.12) + 0.35)).astype(np.float32)
        glow = cv2.resize(glow, (self.W, self.H), interpolation=cv2.INTER_LINEAR)
        return glow[..., None] * np.array([0.9, 0.97, 1.0], np.float32)

    def _streaks(self, out, rng):
        layer = np.zeros((self.H, self.W), np.uint8)
        n = self.c.rain_streaks
        x = rng.uniform(0, self.W, n)
        y = rng.uniform(0, self.H, n)
        ln = rng.uniform(8, 28, n) * self.scale
        dx = rng.normal(0.15, 0.05, n)
        for i in range(n):
            cv2.line(layer, (int(x[i]), int(y[i])), (int(x[i] + dx[i] * ln[i]), int(y[i] + ln[i])),
                     int(rng.uniform(25, 70)), 1, cv2.LINE_AA)
        return cv2.add(out, cv2.merge([layer, layer, layer]))

    def _flakes(self, out, rng):
        layer = np.zeros((self.H, self.W), np.uint8)
        n = self.c.snowflakes
        x = rng.uniform(0, self.W, n).astype(int)
        y = rng.uniform(0, self.H, n).astype(int)
        r = (rng.pareto(2.5, n) * 1.0 + 1).clip(1, 6) * self.scale
        val = rng.uniform(120, 230, n)
        for i in range(n):
            cv2.circle(layer, (x[i], y[i]), max(1, int(r[i])), int(val[i]), -1, cv2.LINE_AA)
        layer = cv2.GaussianBlur(layer, (0, 0), 0.8 * self.scale)
        a3 = cv2.merge([layer, layer, layer])
        # out + (240 - out) * a, in saturating uint8 arithmetic
        return cv2.add(out, cv2.multiply(cv2.subtract(np.full_like(out, 240), out), a3, scale=1 / 255.0))

    def _motion_blur(self, out, depth, velocity):
        v, w = velocity
        T = self.c.exposure_time
        inv = np.minimum(np.where(np.isfinite(depth), 1.0 / np.maximum(depth, 1e-3), 0.0), 1.0).astype(np.float32)
        # image motion during the exposure: expansion from the focus of expansion, plus yaw
        k = np.float32(v * T)
        fx = self.U * (self.cam.fx * k) * inv + np.float32(self.cam.fx * w * T)
        fy = self.V * (self.cam.fy * k) * inv
        if not hasattr(self, "_gx"):
            self._gx, self._gy = np.meshgrid(np.arange(self.W, dtype=np.float32), np.arange(self.H, dtype=np.float32))
        samples = [cv2.remap(out, self._gx + np.float32(t) * fx, self._gy + np.float32(t) * fy, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE) for t in (-0.375, -0.125, 0.125, 0.375)]
        a = cv2.addWeighted(samples[0], 0.5, samples[1], 0.5, 0)
        b = cv2.addWeighted(samples[2], 0.5, samples[3], 0.5, 0)
        return cv2.addWeighted(a, 0.5, b, 0.5, 0)
