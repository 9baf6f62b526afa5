"""Views of one place under many conditions, like the training images of one place in the paper.

:func:`place_views` renders the same place along the route again and again, each time under another
condition, with that run's own distractors and a small pose jitter like a real revisit (lateral
offset, along-track position, heading).  :func:`view_pose` gives the pose for a route position.
"""
from __future__ import annotations

import numpy as np

from ..geometry import make_pose, rot_x, rot_y, rot_z
from .conditions import CONDITIONS
from .motion import LANE_CENTRE
from .noise import rng_for
from .scene import RunScene, default_camera, default_extrinsic
from .world import World

__all__ = ["place_views", "place_views_with_poses", "view_pose", "get_world"]

_CACHE: dict = {}


def get_world(preset: str = "demo", seed: int = 0) -> World:
    """A cached :class:`World` (building one takes about a second)."""
    key = (preset, int(seed))
    if key not in _CACHE:
        _CACHE.clear()
        _CACHE[key] = World(preset, seed)
    return _CACHE[key]


def view_pose(world: World, s: float, d: float = LANE_CENTRE, dyaw: float = 0.0, dpitch: float = 0.0,
              droll: float = 0.0) -> np.ndarray:
    """``T_world_camera`` of the vehicle camera at route position ``s``, lateral offset ``d``."""
    p = world.route.point(s, d)
    psi = float(world.route.heading(s))
    T_wv = make_pose(rot_z(psi + dyaw) @ rot_y(dpitch) @ rot_x(droll), [p[0], p[1], 0.0])
    return T_wv @ default_extrinsic()


def _default_s(world: World) -> float:
    """A place with a building in view: ~15 m before the front of a mid-route facade."""
    L = world.route.drive_length
    best = L * 0.37
    for b in world.buildings:
        s0 = b["s"][0]
        if 0.25 * L < s0 < 0.8 * L:
            return float(s0 - 12.0)
    return float(best)


def place_views_with_poses(preset: str = "demo", seed: int = 0, n: int = 31, s: float | None = None,
                           size=(640, 480), conditions=None, jitter: bool = True):
    """Like :func:`place_views`, also returning each view's ``T_world_camera`` and true depth.

    Returns a list of dicts with keys 'image', 'condition', 'T_world_camera', 'depth', 'camera'.
    """
    world = get_world(preset, seed)
    if s is None:
        s = _default_s(world)
    conds = list(conditions) if conditions else list(CONDITIONS)
    cam = default_camera(size)
    out = []
    for i in range(n):
        cond = conds[i % len(conds)]
        r = rng_for(seed, "place_views", round(float(s), 3), i)
        if jitter and i > 0:
            ds, dd = float(np.clip(r.normal(0, 0.7), -1.5, 1.5)), float(r.uniform(-0.8, 0.8))
            dyaw, dp, dr = np.radians(r.normal(0, 1.5)), np.radians(r.normal(0, 0.4)), np.radians(r.normal(0, 0.3))
        else:
            ds = dd = dyaw = dp = dr = 0.0
        T = view_pose(world, s + ds, LANE_CENTRE + dd, dyaw, dp, dr)
        scene = RunScene(world, cond, run_key=("view", i), camera=cam)
        img, depth = scene.render(T, frame=0, velocity=(8.0, 0.0))
        out.append({"image": img, "condition": cond, "T_world_camera": T, "depth": depth, "camera": cam})
    return out


def place_views(preset: str = "demo", seed: int = 0, n: int = 31, s: float | None = None, size=(640, 480)):
    """``n`` renders of (about) the same place under varied conditions.

    Parameters
    ----------
    preset, seed : the world.
    n : number of views; conditions cycle through sunny, morning, overcast, dusk, night, rain, fog,
        snow, autumn.  View 0 is the unjittered reference.
    s : route position (m); default a place ~12 m before a building front.
    size : (width, height); the camera keeps its 65 deg field of view.

    Returns
    -------
    list of (BGR uint8 image, condition name).
    """
    return [(v["image"], v["condition"]) for v in place_views_with_poses(preset, seed, n, s, size)]
