"""One run's view of the world: a condition, its own distractors, textures lit for it, and rendering.

:class:`RunScene` is what the simulator renders frames from.  Textures are baked for the condition
lazily, the first time a quad is in view, so a scene costs nothing for parts of the world that are
never seen (``place_views`` renders one place under many conditions this way).
"""
from __future__ import annotations

import numpy as np

from ..geometry import CAMERA_FROM_VEHICLE_AXES, Camera, invert, make_pose, rot_y
from .conditions import Condition, PostProcessor, ShadowCaster, bake_texture, encode_light, make_condition
from .noise import rng_for
from .render import Renderer, billboard_corners, billboard_maps, build_pyramid, quad_texture_maps
from .sky import SKY_ELEV, SKY_QUADS, sky_panorama
from .world import CLS, BoardSet, QuadSet, World

__all__ = ["RunScene", "render_view", "static_depth", "default_camera", "default_extrinsic", "CAMERA_HEIGHT",
           "CAMERA_PITCH_DEG"]

CAMERA_HEIGHT = 1.5       # metres above the road
CAMERA_FORWARD = 1.2      # metres ahead of the vehicle origin (rear axle)
CAMERA_PITCH_DEG = 2.0    # looking slightly down
_CLS_NAME = {v: k for k, v in CLS.items()}


def default_camera(size=(640, 480)) -> Camera:
    """Pinhole camera of the simulated vehicle: fx = fy = 500 px at 640 px width (65 deg field of view)."""
    w, h = int(size[0]), int(size[1])
    f = 500.0 * w / 640.0
    return Camera(f, f, w / 2 - 0.5, h / 2 - 0.5, w, h)


def default_extrinsic() -> np.ndarray:
    """``T_vehicle_camera``: forward-looking camera 1.5 m above the road, pitched down 2 degrees."""
    R = rot_y(np.radians(CAMERA_PITCH_DEG)) @ CAMERA_FROM_VEHICLE_AXES
    return make_pose(R, [CAMERA_FORWARD, 0.0, CAMERA_HEIGHT])


def _concat_quads(a: QuadSet, b: QuadSet, offset: int) -> QuadSet:
    return QuadSet(np.concatenate([a.corners, b.corners]), np.concatenate([a.tex, b.tex + offset]),
                   np.concatenate([a.cls, b.cls]), np.concatenate([a.caster, b.caster]))


def _concat_boards(a: BoardSet, b: BoardSet, offset: int) -> BoardSet:
    return BoardSet(np.concatenate([a.base, b.base]), np.concatenate([a.size, b.size]),
                    np.concatenate([a.tex, b.tex + offset]), np.concatenate([a.cls, b.cls]),
                    np.concatenate([a.flip, b.flip]), np.concatenate([a.caster, b.caster]))


class RunScene:
    """The world as one run sees it.

    Parameters
    ----------
    world : the :class:`World`.
    condition : condition name (drawn per run with :func:`make_condition`) or a :class:`Condition`.
    run_key : tuple identifying the run; distractors, sun position, lit windows, clouds and per-frame
        noise are drawn from it.
    camera : defaults to :func:`default_camera` at the world's image size.
    distractors : include this run's parked cars and pedestrians.
    """

    def __init__(self, world: World, condition, run_key=(0,), camera: Camera | None = None,
                 distractors: bool = True):
        self.world = world
        self.run_key = tuple(int(k) if isinstance(k, (int, np.integer)) else k for k in np.atleast_1d(run_key))
        self.cond: Condition = condition if isinstance(condition, Condition) else \
            make_condition(condition, rng_for(world.seed, "condition", *self.run_key))
        self.camera = camera or default_camera(world.image_size)
        self.renderer = Renderer(self.camera)
        season = self.cond.season
        if distractors:
            dq, db, dspecs = world.distractors(self.run_key, season, umbrellas=self.cond.wet)
        else:
            dq, db, dspecs = QuadSet.empty(), BoardSet.empty(), []
        n0 = len(world.tex_specs)
        self.n_static_tex = n0
        self.specs = list(world.tex_specs) + list(dspecs)
        self.quads = _concat_quads(world.quads, dq, n0)
        self.boards = _concat_boards(world.boards, db, n0)
        if not hasattr(world, "_Wn"):
            world._Wn = quad_texture_maps(world.quads.corners)
        self.Wn = np.concatenate([world._Wn, quad_texture_maps(dq.corners)]) if len(dq) else world._Wn
        C = self.quads.corners
        nrm = np.cross(C[:, 3] - C[:, 0], C[:, 1] - C[:, 0])
        self.normals = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        self.owner = {}
        for i, t in enumerate(self.quads.tex):
            self.owner[int(t)] = ("q", i)
        for j, t in enumerate(self.boards.tex):
            self.owner[int(t)] = ("b", j)
        sun = self.cond.sun_vector()
        self.shadows = None
        if sun is not None and not self.cond.lamp_lit:
            cq = self.quads.corners[self.quads.caster]
            cb = self.boards.caster
            self.shadows = ShadowCaster.build(sun, cq, self.boards.base[cb], self.boards.size[cb])
        self._pyr: dict[int, list] = {}
        self._sky = self._make_sky()
        self.post = PostProcessor(self.cond, self.camera, rng_for(world.seed, "post", *self.run_key))
        self.frames = 0

    # ------------------------------------------------------------------ textures
    def _make_sky(self):
        c = self.cond
        sun = None
        if c.sun_elev is not None:
            sun = (c.sun_az, np.radians(c.sun_elev))
        rng = rng_for(self.world.seed, "sky", *self.run_key)
        w_px = int(2048 * max(0.5, self.world.tex_scale))
        pano = sky_panorama(rng, c.sky, sun, width=w_px, height=int(400 * max(0.5, self.world.tex_scale)))
        pano = np.clip(pano, 0, 255).astype(np.uint8)
        if c.lamp_lit:
            a = np.full(pano.shape[:2], encode_light(np.array(1.0 / c.gain)), np.uint8)
        else:
            a = np.full(pano.shape[:2], 255, np.uint8)
        bgra = np.dstack([pano, a])
        n = SKY_QUADS
        W = bgra.shape[1]
        self._sky_pad = 4  # texels of overlap on each side, so neighbouring sky quads leave no seam
        out = []
        for k in range(n):
            cols = np.arange(int(W * k / n) - self._sky_pad, int(W * (k + 1) / n) + self._sky_pad)
            out.append(build_pyramid(np.take(bgra, cols, axis=1, mode="wrap").copy()))
        self._sky_width = W
        return out

    def levels(self, tex: int) -> list:
        """Condition-baked mip pyramid of texture ``tex`` (cached)."""
        p = self._pyr.get(tex)
        if p is not None:
            return p
        w = self.world
        spec = self.specs[tex]
        if tex < self.n_static_tex:
            td = w.texture(tex, self.cond.season)
        else:
            td = w._make(spec, self.cond.season, rng_keys=("run",) + self.run_key)
        kind, i = self.owner[tex]
        rng = rng_for(w.seed, "bake", *self.run_key, tex)
        if kind == "q":
            cls_name = _CLS_NAME[int(self.quads.cls[i])]
            p = bake_texture(td, self.cond, cls_name, rng, Wn=self.Wn[i], normal=self.normals[i],
                             lamps=w.lamps, shadows=self.shadows)
        else:
            cls_name = _CLS_NAME[int(self.boards.cls[i])]
            p = bake_texture(td, self.cond, cls_name, rng, board=(self.boards.base[i], self.boards.size[i]),
                             lamps=w.lamps)
        self._pyr[tex] = p
        return p

    # ------------------------------------------------------------------ rendering
    def render(self, T_world_camera: np.ndarray, frame: int | None = None, velocity=(0.0, 0.0),
               buffers: bool = False):
        """Render the view from ``T_world_camera``.

        Parameters
        ----------
        frame : frame number (keys the per-frame noise, rain and snow); default: a running counter.
        velocity : (forward speed m/s, yaw rate rad/s) for motion blur.
        buffers : also return the raw buffers (dict with 'cls', 'invz', 'fb').

        Returns
        -------
        image : (H, W, 3) uint8 BGR.
        depth : (H, W) float32 z-depth in metres (inf where only sky).
        """
        if frame is None:
            frame = self.frames
        self.frames += 1
        T_cw = invert(np.asarray(T_world_camera, float))
        r = self.renderer
        r.record_ids = buffers
        r.begin()
        cam_pos = np.asarray(T_world_camera)[:3, 3]
        # sky cylinder around the camera (no parallax): drawn first, without depth
        n = SKY_QUADS
        R = 2000.0
        pad = 2 * np.pi * self._sky_pad / self._sky_width
        a0 = -2 * np.pi * np.arange(n) / n + pad
        a1 = -2 * np.pi * (np.arange(n) + 1) / n - pad
        z0, z1 = R * np.tan(np.radians(SKY_ELEV[0])), R * np.tan(np.radians(SKY_ELEV[1]))
        C = np.zeros((n, 4, 3))
        p0 = cam_pos[None, :2] + R * np.stack([np.cos(a0), np.sin(a0)], 1)
        p1 = cam_pos[None, :2] + R * np.stack([np.cos(a1), np.sin(a1)], 1)
        C[:, 0, :2], C[:, 1, :2], C[:, 2, :2], C[:, 3, :2] = p0, p1, p1, p0
        C[:, 0, 2] = C[:, 1, 2] = cam_pos[2] + z1
        C[:, 2, 2] = C[:, 3, 2] = cam_pos[2] + z0
        r.draw(T_cw, C, billboard_maps(C), lambda i: self._sky[i], np.zeros(n, np.uint8), depth_test=False,
               cull_far=1e5)
        # the world: fixed quads and camera-facing billboards
        b = self.boards
        BC = billboard_corners(b.base, b.size, b.flip, cam_pos)
        corners = np.concatenate([self.quads.corners, BC])
        Wn = np.concatenate([self.Wn, billboard_maps(BC)])
        tex = np.concatenate([self.quads.tex, b.tex])
        cls = np.concatenate([self.quads.cls, b.cls])
        far = r.far
        if self.cond.fog_visibility:
            far = min(far, 3.0 * self.cond.fog_visibility)  # beyond this fog leaves < 0.01 % contrast
        layer = np.where(cls == CLS["ground"], 2, np.where(cls == CLS["street"], 1, 0))
        r.draw(T_cw, corners, Wn, lambda i: self.levels(int(tex[i])), cls, cull_far=far, draw_last=layer)
        depth = r.depth()
        rng = rng_for(self.world.seed, "frame", *self.run_key, frame)
        img = self.post(r.fb, r.invz, r.cls, depth, rng, np.asarray(T_world_camera, float), velocity)
        if buffers:
            # ids: index into [fixed quads (world's first, then this run's cars), billboards]
            return img, depth, {"cls": r.cls.copy(), "invz": r.invz.copy(), "fb": r.fb.copy(), "ids": r.ids.copy(),
                                "stats": dict(r.stats)}
        return img, depth


# ---------------------------------------------------------------------------------------------- one-off views
def _cached_scene(world: World, condition, run_key, camera, distractors=True) -> RunScene:
    """The world's last one-off scene if it has these settings, else a new one (kept on the world, one at a
    time: each holds its textures)."""
    key = (condition, None if run_key is None else tuple(np.atleast_1d(run_key)), camera, distractors)
    cache = world.__dict__.setdefault("_one_off_scene", {})
    sc = cache.get(key)
    if sc is None:
        sc = RunScene(world, condition, run_key=run_key if run_key is not None else ("static",), camera=camera,
                      distractors=distractors)
        cache.clear()
        cache[key] = sc
    return sc


def render_view(world: World, T_world_camera, condition: str = "sunny", run_key=(0,), camera=None):
    """Render one view of ``world``: returns (BGR uint8 image, float32 depth (z, metres; inf for sky)).

    ``run_key`` selects the run whose distractors (cars, pedestrians) and per-run draws are used; the
    simulator's run number ``i`` is ``run_key=(i,)``.  The scene is kept for the next call with the
    same settings.
    """
    return _cached_scene(world, condition, run_key, camera).render(T_world_camera)


def static_depth(world: World, T_world_camera, camera=None, run_key=None) -> np.ndarray:
    """Ground-truth depth image (z, metres; inf where only sky) of the *static* world from a pose.

    Parked cars and pedestrians are left out unless ``run_key`` names a run, so that it gives the true
    depth of the permanent structure a map's landmarks should lie on.
    """
    return _cached_scene(world, "overcast", run_key, camera, distractors=run_key is not None).render(T_world_camera)[1]
