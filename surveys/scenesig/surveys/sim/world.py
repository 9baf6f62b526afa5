"""The procedural world: a route lined with buildings, gardens, parks and street furniture.

The world is a set of textured planar quads (and camera-facing billboards for trees, lamp posts and
small furniture) laid out in route coordinates ``(s, d)`` -- see :mod:`scenesig.surveys.sim.route`.  Layout is
drawn once from the seed; textures are generated lazily, per season, from each object's own seeded
generator (:func:`scenesig.surveys.sim.noise.rng_for`), so a world is identical whatever part of it is rendered
first and in whichever process.

Geometry conventions: world z is up, the road surface is ``z = 0``.  A quad's corners are
``TL, TR, BR, BL`` as the texture's ``(0,0), (w,0), (w,h), (0,h)`` corners, ordered so that the
texture reads upright and unmirrored from its front; quads are drawn two-sided.  ``World.landmarks``
holds exact 3-D points (building facade corners) for geometric tests and evaluation.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..io import atomic_write_text
from . import ground, props, sky, textures
from .ground import KERB_OUT, PAVE_OUT, StreetStyle
from .noise import rng_for
from .route import Route
from .textures import TexData

__all__ = ["World", "PRESETS", "CLS", "QuadSet", "BoardSet", "TexSpec", "GENERATOR_VERSION"]

GENERATOR_VERSION = 1  # bump when the layout or texture generators change (world.json records it)

# per-pixel class ids (the renderer's class buffer); effects such as wet-road reflections use them
CLS = {"sky": 0, "skyline": 1, "ground": 2, "street": 3, "building": 4, "roof": 5, "vegetation": 6,
       "furniture": 7, "car": 8, "person": 9}

PRESETS = {
    # route kind, route length (m), image size, the runs simulated by default (one condition each)
    "tiny": {"route": "open", "length": 60.0, "size": (320, 240), "min_radius": 40.0,
             "runs": ["sunny", "overcast", "night", "snow"]},
    "demo": {"route": "loop", "length": 300.0, "size": (640, 480), "min_radius": 20.0,
             "runs": ["sunny", "overcast", "dusk", "night", "rain", "fog", "snow", "autumn"]},
    # the demo's character (loop, 640x480, the same conditions) on half its length: many cheap worlds for
    # calibrating and evaluating the integrity monitor (``scenesig bench integrity``, docs/integrity.md)
    "compact": {"route": "loop", "length": 180.0, "size": (640, 480), "min_radius": 20.0,
                "runs": ["sunny", "overcast", "dusk", "night", "rain", "snow", "night", "fog", "snow", "autumn",
                         "morning"]},
    "begbroke": {"route": "loop", "length": 650.0, "size": (640, 480), "min_radius": 28.0,
                 "runs": ["sunny", "overcast", "morning", "sunny", "dusk", "night", "rain", "fog", "snow",
                          "autumn", "overcast", "night"]},
}


@dataclass
class TexSpec:
    """How to generate one texture: generator ``kind``, random-stream ``key`` and parameters."""

    kind: str
    key: tuple
    params: dict = field(default_factory=dict)


@dataclass
class QuadSet:
    """Fixed planar quads: corners (N,4,3) TL,TR,BR,BL; texture index; class; casts a sun shadow."""

    corners: np.ndarray
    tex: np.ndarray
    cls: np.ndarray
    caster: np.ndarray

    @classmethod
    def empty(cls):
        return cls(np.zeros((0, 4, 3)), np.zeros(0, int), np.zeros(0, np.uint8), np.zeros(0, bool))

    def __len__(self):
        return len(self.tex)


@dataclass
class BoardSet:
    """Camera-facing billboards: base centre (M,3), (width, height) (M,2), texture, class, mirrored."""

    base: np.ndarray
    size: np.ndarray
    tex: np.ndarray
    cls: np.ndarray
    flip: np.ndarray
    caster: np.ndarray

    @classmethod
    def empty(cls):
        return cls(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, np.uint8),
                   np.zeros(0, bool), np.zeros(0, bool))

    def __len__(self):
        return len(self.tex)


class _Builder:
    """Accumulates quads, billboards and texture specs while laying out a world."""

    def __init__(self):
        self.q_corners, self.q_tex, self.q_cls, self.q_cast = [], [], [], []
        self.b_base, self.b_size, self.b_tex, self.b_cls, self.b_flip, self.b_cast = [], [], [], [], [], []
        self.specs: list[TexSpec] = []

    def tex(self, spec: TexSpec) -> int:
        self.specs.append(spec)
        return len(self.specs) - 1

    def quad(self, corners, tex: int, cls: str, caster: bool = False):
        self.q_corners.append(np.asarray(corners, float))
        self.q_tex.append(tex)
        self.q_cls.append(CLS[cls])
        self.q_cast.append(caster)
        return len(self.q_tex) - 1

    def board(self, base, w, h, tex, cls, flip=False, caster=False):
        self.b_base.append(np.asarray(base, float))
        self.b_size.append((w, h))
        self.b_tex.append(tex)
        self.b_cls.append(CLS[cls])
        self.b_flip.append(flip)
        self.b_cast.append(caster)

    def sets(self, tex_offset: int = 0):
        q = QuadSet(np.array(self.q_corners).reshape(-1, 4, 3), np.array(self.q_tex, int) + tex_offset,
                    np.array(self.q_cls, np.uint8), np.array(self.q_cast, bool)) if self.q_tex else QuadSet.empty()
        b = BoardSet(np.array(self.b_base).reshape(-1, 3), np.array(self.b_size, float).reshape(-1, 2),
                     np.array(self.b_tex, int) + tex_offset, np.array(self.b_cls, np.uint8),
                     np.array(self.b_flip, bool), np.array(self.b_cast, bool)) if self.b_tex else BoardSet.empty()
        return q, b


def vquad(q0, q1, facing, z0, z1):
    """Vertical quad between ground points q0, q1 whose front faces the horizontal direction ``facing``.

    Orders the two ends so that the texture is unmirrored when seen from the front: the front normal
    ``cross(BL - TL, TR - TL)`` equals ``facing``.
    """
    q0, q1, m = np.asarray(q0, float), np.asarray(q1, float), np.asarray(facing, float)
    right_dir = np.array([-m[1], m[0]])
    left, right = (q0, q1) if np.dot(q1 - q0, right_dir) > 0 else (q1, q0)
    return np.array([[left[0], left[1], z1], [right[0], right[1], z1], [right[0], right[1], z0],
                     [left[0], left[1], z0]])


def _leftperp(v):
    return np.array([-v[1], v[0]])


class World:
    """A procedural survey world.

    Parameters
    ----------
    preset : 'tiny', 'demo' or 'begbroke' (see ``PRESETS``).
    seed : everything (route, layout, textures) follows from it.
    tex_scale : texture resolution factor (defaults to image width / 640: small images need less).
    """

    def __init__(self, preset: str = "demo", seed: int = 0, tex_scale: float | None = None):
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
        self.preset = preset
        self.seed = int(seed)
        cfg = PRESETS[preset]
        self.config = dict(cfg)
        self.image_size = tuple(cfg["size"])
        self.tex_scale = float(tex_scale if tex_scale is not None else max(0.5, self.image_size[0] / 640))
        rng = rng_for(seed, "route")
        if cfg["route"] == "loop":
            self.route = Route.loop(cfg["length"], rng, cfg["min_radius"])
        else:
            self.route = Route.open(cfg["length"], rng)
        self._tex_cache: dict = {}
        self._layout()

    # ------------------------------------------------------------------ layout
    def _layout(self):
        rng = rng_for(self.seed, "layout")
        r = self.route
        B = _Builder()
        self._b = B
        self.landmarks: dict[str, np.ndarray] = {}
        self.buildings: list[dict] = []
        self._footprints: list[np.ndarray] = []
        lo = r.s[0] if not r.closed else r.s0
        hi = r.s[-1] if not r.closed else r.s0 + r.total
        self.s_range = (float(lo), float(hi))

        # crossings (where runs may stop); on straight stretches
        n_cross = max(1, int(round(r.drive_length / 200)))
        cand = np.linspace(0, r.drive_length, 400, endpoint=False)[5:-5]
        kappa = np.abs(np.interp(r.wrap(cand), r.s, r.curvature()))
        cand = cand[kappa < 1 / 80]
        self.crossings = np.sort(rng.choice(cand, size=min(n_cross, len(cand)), replace=False)) if len(cand) \
            else np.array([r.drive_length / 2])
        if not r.closed:
            self.crossings = np.array([r.drive_length * rng.uniform(0.45, 0.65)])

        self.half_width = 12.0
        self.street = StreetStyle(self.seed, self.half_width, r.total, self.crossings)
        self._street_tiles(B)
        self._field_tiles(B)
        for side in (+1, -1):
            self._side(B, rng, side, lo, hi)
        self._furniture(B, rng, lo, hi)
        self._skyline(B)
        self.lamps = np.array(self._lamps).reshape(-1, 3)
        self.quads, self.boards = B.sets()
        self.tex_specs = B.specs
        del self._b

    def _street_tiles(self, B):
        """Tiles of the street strip: long on straights, short on bends (they approximate the curve)."""
        r = self.route
        lo, hi = (r.s[0], r.s[-1]) if not r.closed else (r.s0, r.s0 + r.total)
        s = lo
        D = self.half_width
        while s < hi - 1e-6:
            e = min(s + 30.0, hi)
            # chord sag = length x turn / 8 stays under 8 cm: the polygonal road edge is invisible
            while e - s > 2.0 and (e - s) * abs(float(r.heading(e) - r.heading(s))) / 8 > 0.08:
                e = s + (e - s) / 2
            p = [r.point(e, D), r.point(e, -D), r.point(s, -D), r.point(s, D)]
            corners = np.array([[q[0], q[1], 0.0] for q in p])
            t = B.tex(TexSpec("street", ("street", round(s, 3)), {"s0": float(s), "s1": float(e)}))
            B.quad(corners, t, "street")
            s = e

    def _field_tiles(self, B):
        """Far ground: a grid of square cells, finer near the route."""
        xy = self.route.xy
        lo, hi = xy.min(0) - 250, xy.max(0) + 250
        big = 80.0
        nx, ny = int(np.ceil((hi[0] - lo[0]) / big)), int(np.ceil((hi[1] - lo[1]) / big))
        for i in range(nx):
            for j in range(ny):
                x0, y0 = lo[0] + i * big, lo[1] + j * big
                centre = np.array([[x0 + big / 2, y0 + big / 2]])
                if self.route.distance_to(centre)[0] < 50 + big * 0.71:
                    cells = [(x0 + a * 40.0, y0 + b * 40.0, 40.0, 6.0) for a in range(2) for b in range(2)]
                else:
                    cells = [(x0, y0, big, 1.5)]
                for (cx, cy, size, ppm) in cells:
                    corners = np.array([[cx, cy + size, -0.02], [cx + size, cy + size, -0.02],
                                        [cx + size, cy, -0.02], [cx, cy, -0.02]])
                    t = B.tex(TexSpec("field", ("field", round(cx, 2), round(cy, 2)),
                                      {"x0": cx, "y0": cy, "size": size, "ppm": ppm}))
                    B.quad(corners, t, "ground")

    def _clear_of_route(self, pts, min_d):
        return bool(np.all(self.route.distance_to(np.asarray(pts).reshape(-1, 2)) >= min_d))

    def _overlaps(self, poly):
        p = np.asarray(poly, np.float32)
        for f in self._footprints:
            area, _ = cv2.intersectConvexConvex(p, f)
            if area > 0.5:
                return True
        return False

    def _side(self, B, rng, side, lo, hi):
        r = self.route
        s = lo + rng.uniform(0, 5)
        end = hi - 3.0
        while s < end:
            u = rng.random()
            kind = "building" if u < 0.55 else ("green" if u < 0.85 else "open")
            L = {"building": rng.uniform(10, 26), "green": rng.uniform(14, 36), "open": rng.uniform(8, 18)}[kind]
            L = min(L, end - s)
            if L < 4:
                break
            if kind == "building" and abs(r.heading(s + L) - r.heading(s)) > 0.25:
                kind = "green"  # bends get parks: straight facades would cut the curve
            placed = False
            if kind == "building":
                placed = self._building(B, rng, side, s, s + L)
            if kind == "green" or (kind == "building" and not placed):
                self._green(B, rng, side, s, s + L)
            elif kind == "open":
                self._open(B, rng, side, s, s + L)
            s += L + rng.uniform(0.5, 3.0)

    def _building(self, B, rng, side, sa, sb) -> bool:
        r = self.route
        style = str(rng.choice(textures.FACADE_STYLES, p=[0.16, 0.12, 0.1, 0.12, 0.14, 0.08, 0.1, 0.08, 0.1]))
        ga, gb = rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0)
        sa, sb = sa + ga, sb - gb
        df = PAVE_OUT + (rng.uniform(1.5, 6.0) if style not in ("office_glass", "office_panel", "industrial")
                         else rng.uniform(3.0, 9.0))
        if style == "shop_row":
            df = PAVE_OUT + rng.uniform(0.2, 1.5)
        floors = {"brick_house": (2, 3), "terrace": (2, 3), "office_glass": (2, 5), "office_panel": (2, 4),
                  "shop_row": (2, 4), "stone": (2, 4), "plaster": (2, 3), "industrial": (2, 3),
                  "cladding": (2, 3)}[style]
        floor_h = 3.7 if style in ("office_glass", "office_panel", "industrial") else 3.1
        H = int(rng.integers(floors[0], floors[1] + 1)) * floor_h + rng.uniform(0.4, 1.2)
        Db = rng.uniform(8, 16)
        pA, pB = r.point(sa, side * df), r.point(sb, side * df)
        t_c = (pB - pA) / np.linalg.norm(pB - pA)
        away = side * _leftperp(t_c)
        for _ in range(2):
            back = [pA + away * Db, pB + away * Db]
            foot = np.array([pA, pB, back[1], back[0]])
            mids = np.array([(pA + pB) / 2, (back[0] + back[1]) / 2, (pA + back[0]) / 2, (pB + back[1]) / 2])
            if self._clear_of_route(np.vstack([foot, mids]), min(df, PAVE_OUT + 1.5) - 0.3) \
                    and not self._overlaps(foot):
                break
            Db *= 0.5
        else:
            return False
        self._footprints.append(foot.astype(np.float32))
        width = float(np.linalg.norm(pB - pA))
        pitched = style in ("brick_house", "terrace", "stone", "plaster") and rng.random() < 0.8
        rh = rng.uniform(2.0, 3.5) if pitched else 0.0
        bid = len(self.buildings)
        key = ("bldg", bid)
        seedf = rng.integers(1 << 30)
        front = vquad(pA, pB, -away, 0.0, H)
        t = B.tex(TexSpec("facade", key + ("front",), {"w": width, "h": H, "style": style, "seed": int(seedf)}))
        front_quad = B.quad(front, t, "building", caster=True)
        for name, corner in zip(("TL", "TR", "BR", "BL"), front):
            self.landmarks[f"b{bid}_front_{name}"] = corner.copy()
        # side walls (with the gable triangle under a pitched roof), back wall, roof
        for end, p, facing in (("a", pA, -t_c), ("b", pB, t_c)):
            q = vquad(p, p + away * Db, facing, 0.0, H + rh)
            front_u = 0 if np.allclose(q[0, :2], p) else 1
            t = B.tex(TexSpec("facade", key + ("side", end), {"w": Db, "h": H + rh, "style": style, "side": True,
                                                               "gable": (H, rh, front_u), "seed": int(seedf) + 1}))
            B.quad(q, t, "building", caster=True)
        qb = vquad(back[0], back[1], away, 0.0, H)
        t = B.tex(TexSpec("facade", key + ("back",), {"w": width, "h": H, "style": style, "side": True,
                                                      "seed": int(seedf) + 2}))
        B.quad(qb, t, "building", caster=True)
        if pitched:
            ridgeA, ridgeB = pA + away * Db / 2, pB + away * Db / 2
            base_q = vquad(pA, pB, -away, 0, 1)  # for left/right order as seen from the street
            left_is_A = np.allclose(base_q[0, :2], pA)
            (l_e, r_e, l_r, r_r) = (pA, pB, ridgeA, ridgeB) if left_is_A else (pB, pA, ridgeB, ridgeA)
            corners = np.array([[l_r[0], l_r[1], H + rh], [r_r[0], r_r[1], H + rh], [r_e[0], r_e[1], H],
                                [l_e[0], l_e[1], H]])
            slope = float(np.hypot(Db / 2, rh))
            t = B.tex(TexSpec("roof", key + ("roof",), {"w": width, "slope": slope}))
            B.quad(corners, t, "roof", caster=True)
        self.buildings.append({"id": bid, "style": style, "s": [float(sa), float(sb)], "side": side,
                               "setback": float(df), "height": float(H), "depth": float(Db),
                               "front": front.tolist(), "front_quad": int(front_quad)})
        # front garden: boundary hedge / wall / railings with a gap for the path, maybe a tree
        if df - PAVE_OUT > 1.2:
            self._boundary(B, rng, side, sa, sb, PAVE_OUT + 0.3, gap=True)
            if df - PAVE_OUT > 4.0 and rng.random() < 0.5:
                sm = rng.uniform(sa + 2, max(sa + 2.5, sb - 2))
                self._tree(B, rng, r.point(sm, side * rng.uniform(PAVE_OUT + 1.5, df - 1.5)), small=True)
        if rng.random() < 0.25:
            sm = rng.uniform(sa, sb)
            self._object(B, rng, r.point(sm, side * (df - 0.6)), "bin")
        return True

    def _boundary(self, B, rng, side, sa, sb, d, gap=False):
        r = self.route
        kind = str(rng.choice(["hedge", "wall", "railings", "wood", "picket", "none"],
                              p=[0.35, 0.2, 0.15, 0.1, 0.08, 0.12]))
        if kind == "none":
            return
        segs = [(sa, sb)]
        if gap and sb - sa > 6:
            m = (sa + sb) / 2 + rng.uniform(-1, 1)
            segs = [(sa, m - 0.7), (m + 0.7, sb)]
        for a, b in segs:
            pa, pb = r.point(a, side * d), r.point(b, side * d)
            n = np.linalg.norm(pb - pa)
            if n < 0.5 or not self._clear_of_route([pa, pb], d - 0.3):
                continue
            t_c = (pb - pa) / n
            facing = -side * _leftperp(t_c)
            if kind == "hedge":
                hh = rng.uniform(0.9, 1.6)
                depth = rng.uniform(0.6, 1.0)
                key = ("hedge", round(a, 2), side)
                t = B.tex(TexSpec("hedge", key, {"w": n, "h": hh}))
                B.quad(vquad(pa, pb, facing, 0.0, hh), t, "vegetation", caster=True)
                pa2, pb2 = pa - facing * depth, pb - facing * depth
                q = vquad(pa, pb, facing, 0, 1)
                left_a = np.allclose(q[0, :2], pa)
                fl, fr, bl, br = (pa, pb, pa2, pb2) if left_a else (pb, pa, pb2, pa2)
                top = np.array([[bl[0], bl[1], hh], [br[0], br[1], hh], [fr[0], fr[1], hh], [fl[0], fl[1], hh]])
                t2 = B.tex(TexSpec("hedge", key + ("top",), {"w": n, "h": depth, "top": True}))
                B.quad(top, t2, "vegetation")
            else:
                height = {"railings": 1.2, "wood": 1.8, "wall": 0.8, "picket": 1.0}[kind]
                t = B.tex(TexSpec("fence", ("fence", round(a, 2), side), {"w": n, "kind": kind}))
                B.quad(vquad(pa, pb, facing, 0.0, height), t, "furniture" if kind == "railings" else "building",
                       caster=kind != "railings")

    def _tree(self, B, rng, p2, small=False, big=False):
        if not self._clear_of_route([p2], PAVE_OUT + 0.8):
            return
        kind = str(rng.choice(["deciduous", "conifer", "birch"], p=[0.65, 0.15, 0.2]))
        h = rng.uniform(5, 8) if small else (rng.uniform(10, 18) if big else rng.uniform(7, 13))
        w = h * (rng.uniform(0.55, 0.8) if kind != "conifer" else rng.uniform(0.35, 0.5))
        t = B.tex(TexSpec("tree", ("tree", round(float(p2[0]), 2), round(float(p2[1]), 2)),
                          {"w": w, "h": h, "kind": kind}))
        B.board([p2[0], p2[1], 0.0], w, h, t, "vegetation", caster=True)

    def _object(self, B, rng, p2, kind):
        if not self._clear_of_route([p2], KERB_OUT + 0.1):
            return
        size = {"postbox": (0.6, 1.5), "bin": (0.6, 1.0), "bollard": (0.25, 0.95), "cabinet": (1.0, 1.3),
                "beacon": (0.5, 2.8)}[kind]
        t = B.tex(TexSpec("object", ("obj", kind, round(float(p2[0]), 2), round(float(p2[1]), 2)), {"kind": kind}))
        B.board([p2[0], p2[1], 0.0], size[0], size[1], t, "furniture")

    def _green(self, B, rng, side, sa, sb):
        r = self.route
        if rng.random() < 0.6:
            self._boundary(B, rng, side, sa, sb, PAVE_OUT + 0.3)
        n = max(1, int((sb - sa) / rng.uniform(6, 11)))
        for _ in range(n):
            self._tree(B, rng, r.point(rng.uniform(sa, sb), side * rng.uniform(PAVE_OUT + 1.5, PAVE_OUT + 12)))
        for _ in range(max(1, int((sb - sa) / 10))):  # a second, taller row further back
            self._tree(B, rng, r.point(rng.uniform(sa, sb), side * rng.uniform(PAVE_OUT + 14, PAVE_OUT + 40)),
                       big=True)
        if rng.random() < 0.25:
            sm = rng.uniform(sa, sb)
            pa, pb = r.point(sm, side * (PAVE_OUT + 1.0)), r.point(sm + 1.8, side * (PAVE_OUT + 1.0))
            if self._clear_of_route([pa, pb], PAVE_OUT):
                t = B.tex(TexSpec("object", ("bench", round(sm, 2), side), {"kind": "bench"}))
                facing = -side * _leftperp((pb - pa) / np.linalg.norm(pb - pa))
                B.quad(vquad(pa, pb, facing, 0.0, 0.9), t, "furniture")

    def _open(self, B, rng, side, sa, sb):
        r = self.route
        if rng.random() < 0.5:
            self._boundary(B, rng, side, sa, sb, PAVE_OUT + 0.3, gap=True)
        for _ in range(int(rng.integers(0, 4))):
            self._object(B, rng, r.point(rng.uniform(sa, sb), side * (PAVE_OUT + 0.4)), "bollard")
        if rng.random() < 0.5:
            self._tree(B, rng, r.point(rng.uniform(sa, sb), side * rng.uniform(PAVE_OUT + 4, PAVE_OUT + 10)))

    def _furniture(self, B, rng, lo, hi):
        r = self.route
        self._lamps = []
        s = lo + rng.uniform(3, 15)
        side = 1 if rng.random() < 0.5 else -1
        while s < hi - 2:
            d = side * (KERB_OUT + 0.45)
            p = r.point(s, d)
            if self._clear_of_route([p], KERB_OUT + 0.2):
                h = rng.uniform(6.5, 8.0)
                t = B.tex(TexSpec("lamp", ("lamp", round(s, 2)), {"h": h}))
                # the arm reaches over the road: mirrored on the right-hand side
                B.board([p[0], p[1], 0.0], 1.6, h, t, "furniture", flip=side < 0)
                head = r.point(s, d - side * 1.1)
                self._lamps.append([head[0], head[1], h - 0.55])
            s += rng.uniform(26, 36)
            side = -side if rng.random() < 0.8 else side
        for cs in self.crossings:
            for side in (1, -1):
                for off in (-1.7, 1.7):
                    self._object(B, rng, r.point(cs + off, side * (KERB_OUT + 0.3)), "beacon")
            self._sign(B, rng, cs - 25, 1, "warning")
        s = lo + rng.uniform(5, 30)
        while s < hi - 2:
            side = 1 if rng.random() < 0.5 else -1
            kind = str(rng.choice(["limit", "info", "name", "warning"], p=[0.3, 0.25, 0.3, 0.15]))
            self._sign(B, rng, s, side, kind)
            s += rng.uniform(35, 80)
        s = lo + rng.uniform(5, 20)
        while s < hi - 2:
            side = 1 if rng.random() < 0.5 else -1
            kind = str(rng.choice(["postbox", "bin", "cabinet", "bollard"], p=[0.2, 0.35, 0.25, 0.2]))
            self._object(B, rng, r.point(s, side * (PAVE_OUT - 0.35)), kind)
            s += rng.uniform(15, 40)

    def _sign(self, B, rng, s, side, kind):
        r = self.route
        d = side * (KERB_OUT + 0.5)
        p = r.point(s, d)
        if not self._clear_of_route([p], KERB_OUT + 0.2):
            return
        t_dir = np.array([np.cos(r.heading(s)), np.sin(r.heading(s))])
        # signs face oncoming traffic (and are edge-on when passed, like real ones)
        facing = -t_dir
        lat = _leftperp(t_dir)
        q = vquad(p - lat * 0.5, p + lat * 0.5, facing, 0.0, 2.8)
        t = B.tex(TexSpec("sign", ("sign", round(s, 2), side), {"kind": kind}))
        B.quad(q, t, "furniture")

    def _skyline(self, B):
        xy = self.route.xy
        c = (xy.min(0) + xy.max(0)) / 2
        R = float(np.max(np.linalg.norm(xy - c, axis=1))) + 160.0
        n = 18
        length = 2 * np.pi * R
        self.skyline = {"centre": c.tolist(), "radius": R}
        for k in range(n):
            a0, a1 = -2 * np.pi * k / n, -2 * np.pi * (k + 1) / n
            p0 = c + R * np.array([np.cos(a0), np.sin(a0)])
            p1 = c + R * np.array([np.cos(a1), np.sin(a1)])
            mid = (a0 + a1) / 2
            facing = -np.array([np.cos(mid), np.sin(mid)])
            q = vquad(p0, p1, facing, -1.0, 69.0)
            t = B.tex(TexSpec("skyline", ("skyline", k), {"k": k, "n": n, "length": length}))
            B.quad(q, t, "skyline")

    # ------------------------------------------------------------------ textures
    def texture(self, idx: int, season: str) -> TexData:
        """Base (albedo) texture ``idx`` for a season, cached."""
        key = (idx, season)
        hit = self._tex_cache.get(key)
        if hit is None:
            hit = self._make(self.tex_specs[idx], season)
            self._tex_cache[key] = hit
        return hit

    def _make(self, spec: TexSpec, season: str, rng_keys: tuple = ()) -> TexData:
        ts = self.tex_scale
        p = spec.params
        rng = rng_for(self.seed, *rng_keys, *spec.key)
        k = spec.kind
        if k == "facade":
            td = textures.facade(rng_for(self.seed, "facade", p["seed"]), p["w"], p["h"], p["style"], season,
                                 ppm=32 * ts, side=p.get("side", False))
            if "gable" in p:
                H, rh, front_u = p["gable"]
                h, w = td.shape
                u = (np.arange(w) + 0.5) / w
                du = u if front_u == 0 else 1 - u
                zmax = H + rh * (1 - np.abs(2 * du - 1)) if rh > 0 else np.full(w, H)
                z = (H + rh) - (np.arange(h) + 0.5)[:, None] / td.ppm
                td.alpha = np.where(z <= zmax[None, :] + 1e-6, 255, 0).astype(np.uint8)
            return td
        if k == "roof":
            return textures.roof(rng, p["w"], p["slope"], season, ppm=16 * ts)
        if k == "tree":
            return props.tree(rng, p["w"], p["h"], p["kind"], season, ppm=20 * ts)
        if k == "hedge":
            return props.hedge(rng, p["w"], p["h"], season, ppm=24 * ts, top=p.get("top", False))
        if k == "fence":
            return props.fence(rng, p["w"], p["kind"], season, ppm=24 * ts)
        if k == "lamp":
            return props.lamp_post(rng, p["h"], ppm=24 * ts)[0]
        if k == "sign":
            return props.road_sign(rng, p["kind"], ppm=40 * ts, season=season)
        if k == "object":
            return props.street_object(rng, p["kind"], season, ppm=40 * ts)[0]
        if k == "street":
            grid, to_px = self._street_grid(spec, 24 * ts)
            return ground.street_tile(self.street, p["s0"], p["s1"], season, ppm=24 * ts, grid=grid, to_px=to_px)
        if k == "field":
            return ground.ground_tile(self.seed, p["x0"], p["y0"], p["size"], season, ppm=p["ppm"] * ts)
        if k == "skyline":
            full = self._tex_cache.get(("skyline_full", season))
            if full is None:
                full = sky.skyline_texture(rng_for(self.seed, "skyline"), p["length"], season)
                self._tex_cache[("skyline_full", season)] = full
            W = full.bgr.shape[1]
            x0, x1 = int(W * p["k"] / p["n"]), int(W * (p["k"] + 1) / p["n"])
            wins = [(a - x0, b, c - x0, d) for (a, b, c, d) in full.windows if x0 <= a < x1]
            return TexData(full.bgr[:, x0:x1].copy(), full.alpha[:, x0:x1].copy(), wins, None, full.ppm)
        if k == "car":
            return props.car(rng, p["view"], p["length"], season, ppm=40 * ts, colour=p["colour"], plate=p["plate"])
        if k == "person":
            return props.pedestrian(rng, season, umbrella=p.get("umbrella", False), ppm=60 * ts)
        raise ValueError(f"unknown texture kind {k!r}")

    def _street_grid(self, spec: TexSpec, ppm: float):
        """Route coordinates (s, d) of every texel of a street tile, through the tile's actual mapping.

        On a bend the tile is a trapezoid and the renderer maps its texture projectively, which is not
        linear in ``d``; drawing each texel's content at its true (s, d) keeps markings and kerbs where
        the route puts them.
        """
        from .render import quad_texture_maps

        p = spec.params
        s0, s1 = p["s0"], p["s1"]
        D = self.half_width
        r = self.route
        corners = np.array([[*r.point(s1, D), 0], [*r.point(s1, -D), 0], [*r.point(s0, -D), 0],
                            [*r.point(s0, D), 0]])
        Wn = quad_texture_maps(corners[None])[0]
        G = Wn[[0, 1, 3]]  # (u, v, 1) -> ground (x, y, 1)
        h = max(2, int(round((s1 - s0) * ppm)))
        w = max(2, int(round(2 * D * ppm)))
        u = (np.arange(w) + 0.5) / w
        v = (np.arange(h) + 0.5) / h
        U, V = np.meshgrid(u, v)
        q = np.stack([U, V, np.ones_like(U)], -1) @ G.T
        XY = q[..., :2] / q[..., 2:]
        # foot of the perpendicular on the centreline by Newton steps from the linear guess
        xy = XY.reshape(-1, 2)
        S = np.repeat(s1 - (s1 - s0) * v, w)
        for _ in range(3):
            psi = r.heading(S)
            rel = xy - r.position(S)
            S = S + rel[:, 0] * np.cos(psi) + rel[:, 1] * np.sin(psi)
        psi = r.heading(S)
        rel = xy - r.position(S)
        Dd = (-rel[:, 0] * np.sin(psi) + rel[:, 1] * np.cos(psi)).reshape(h, w)
        S = S.reshape(h, w)
        Gi = np.linalg.inv(G)

        def to_px(s_, d_):
            s_, d_ = np.broadcast_arrays(np.asarray(s_, float), np.asarray(d_, float))
            xy = r.point(s_, d_)
            qq = np.c_[xy.reshape(-1, 2), np.ones(xy.size // 2)] @ Gi.T
            uu, vv = qq[:, 0] / qq[:, 2], qq[:, 1] / qq[:, 2]
            return (uu * w - 0.5).reshape(s_.shape), (vv * h - 0.5).reshape(s_.shape)

        return (S, Dd), to_px

    # ------------------------------------------------------------------ distractors
    def distractors(self, run_key: tuple, season: str, umbrellas: bool = False):
        """Parked cars and pedestrians of one run (each run draws its own).

        Returns (QuadSet, BoardSet, list[TexSpec]) with texture indices local to the returned list.
        Cars park along the right-hand kerb (the vehicle drives in the left lane) and in forecourts;
        pedestrians walk on the pavements.
        """
        rng = rng_for(self.seed, "distractors", *run_key)
        r = self.route
        B = _Builder()
        lo, hi = self.s_range
        density = rng.uniform(0.25, 0.65)
        s = lo + rng.uniform(0, 10)
        while s < hi - 6:
            L = rng.uniform(3.8, 4.9)
            near_cross = np.any(np.abs(self.crossings - s) < 15) or np.any(np.abs(self.crossings + r.total - s) < 15)
            if rng.random() < density and not near_cross:
                self._car(B, rng, s, s + L, -2.65, facing_fwd=rng.random() < 0.5)
            s += L + rng.uniform(0.8, 6.0)
        for bd in self.buildings:
            if bd["side"] == 1 and bd["setback"] - PAVE_OUT > 5.5 and rng.random() < 0.35:
                sa = rng.uniform(bd["s"][0], max(bd["s"][0] + 0.1, bd["s"][1] - 5))
                self._car(B, rng, sa, sa + rng.uniform(3.8, 4.8), PAVE_OUT + 2.6, facing_fwd=rng.random() < 0.5)
        n_ped = int(rng.poisson((hi - lo) / rng.uniform(12, 30)))
        for i in range(n_ped):
            s = rng.uniform(lo, hi)
            side = 1 if rng.random() < 0.5 else -1
            p = r.point(s, side * rng.uniform(KERB_OUT + 0.3, PAVE_OUT - 0.2))
            t = B.tex(TexSpec("person", ("person", i), {"umbrella": umbrellas and rng.random() < 0.7}))
            B.board([p[0], p[1], 0.0], 0.8, 1.9, t, "person")
        q, b = B.sets()
        return q, b, B.specs

    def _car(self, B, rng, sa, sb, d, facing_fwd):
        r = self.route
        side_plane = d + (0.9 if d < 0 else -0.9)  # the car flank that faces the road
        far_plane = d - (0.9 if d < 0 else -0.9)
        pa, pb = r.point(sa, side_plane), r.point(sb, side_plane)
        if not (self._clear_of_route([r.point(sa, far_plane), r.point(sb, far_plane)], abs(d) - 1.2)
                and self._clear_of_route([pa, pb], abs(side_plane) - 0.3)):
            return
        colour = props._CAR_COLOURS[rng.integers(len(props._CAR_COLOURS))]
        plate = "".join(rng.choice(list("ABCDEFGHJKLMNPRSTVWXY0123456789"), 7))
        t_c = (pb - pa) / np.linalg.norm(pb - pa)
        facing = np.sign(-d) * _leftperp(t_c)
        length = float(np.linalg.norm(pb - pa))
        cid = rng.integers(1 << 30)
        t = B.tex(TexSpec("car", ("car", int(cid), "side"), {"view": "side", "length": length, "colour": colour,
                                                             "plate": plate}))
        B.quad(vquad(pa, pb, facing, 0.0, 1.5), t, "car", caster=True)
        # the end that faces the approaching camera: rear if parked facing along the route
        qa, qb = r.point(sa, side_plane), r.point(sa, far_plane)
        t2 = B.tex(TexSpec("car", ("car", int(cid), "end"), {"view": "rear" if facing_fwd else "front",
                                                            "length": length, "colour": colour, "plate": plate}))
        B.quad(vquad(qa, qb, -t_c, 0.0, 1.5), t2, "car", caster=True)

    # ------------------------------------------------------------------ description
    def to_json(self) -> dict:
        return {"generator": "surveys.sim", "generator_version": GENERATOR_VERSION, "preset": self.preset,
                "seed": self.seed, "tex_scale": self.tex_scale, "image_size": list(self.image_size),
                "route": self.route.to_json(), "crossings_s": np.round(self.crossings, 3).tolist(),
                "street_half_width": self.half_width, "lamps": np.round(self.lamps, 3).tolist(),
                "n_quads": len(self.quads), "n_billboards": len(self.boards), "buildings": self.buildings,
                "skyline": self.skyline}

    def save(self, path) -> Path:
        path = Path(path)
        atomic_write_text(path, json.dumps(self.to_json(), indent=1))
        return path

    @classmethod
    def load(cls, path) -> "World":
        """Regenerate the world a ``world.json`` describes (layout and textures are re-derived from the seed)."""
        from ..errors import DataError

        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise DataError(path, f"cannot read world description: {exc}") from None
        for k in ("preset", "seed", "generator_version"):
            if k not in d:
                raise DataError(path, f"missing key {k!r}")
        if d["generator_version"] != GENERATOR_VERSION:
            raise DataError(path, f"written by simulator generator version {d['generator_version']}, this is "
                                  f"{GENERATOR_VERSION}: the world cannot be regenerated exactly")
        w = cls(d["preset"], int(d["seed"]), tex_scale=d.get("tex_scale"))
        if abs(w.route.total - d["route"]["length_m"]) > 1e-3:
            raise DataError(path, "regenerated route differs from the recorded one")
        return w
