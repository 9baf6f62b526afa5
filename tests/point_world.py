"""A tiny ray-cast world of textured planes for the point-feature tests: exact geometry, exact depth.

Walls along a straight road (world x forward, y left, z up) and a facade across it, each a rectangle
with its own random texture of blobs and boxes (corners and blobs for ORB and SIFT).  ``render`` casts a
ray through every pixel, so the depth of every keypoint is known exactly.
"""
from __future__ import annotations

import cv2
import numpy as np

from scenesig.surveys.geometry import CAMERA_FROM_VEHICLE_AXES, Camera, make_pose, rot_z

CAMERA = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
T_VC = make_pose(CAMERA_FROM_VEHICLE_AXES, [0.0, 0.0, 1.5])


def _texture(rng, w=512, h=256):
    img = np.full((h, w), 110, np.uint8)
    for _ in range(260):
        c = int(rng.integers(0, 256))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(2, 12)), c, -1)
        else:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(3, 24)), y + int(rng.integers(3, 24))), c, -1)
    return cv2.GaussianBlur(img, (0, 0), 0.8)


def planes(seed=0):
    """List of (origin, u, v, Lu, Lv, texture): rectangle ``origin + a u + b v``, a in [0,Lu], b in [0,Lv]."""
    rng = np.random.default_rng(seed)
    ex, ey, ez = np.eye(3)
    return [
        (np.array([4.0, 7.0, 0.0]), ex, ez, 70.0, 9.0, _texture(rng)),       # left wall
        (np.array([4.0, -7.5, 0.0]), ex, ez, 70.0, 11.0, _texture(rng)),     # right wall
        (np.array([45.0, -25.0, 0.0]), ey, ez, 50.0, 16.0, _texture(rng)),   # facade across the road
        (np.array([22.0, 1.5, 0.0]), ey, ez, 4.0, 4.0, _texture(rng, 128, 128)),  # a sign closer by
    ]


def render(T_world_camera, world=None, camera=CAMERA):
    """Gray image (uint8) and z-depth (inf where nothing is hit) seen from ``T_world_camera``."""
    world = planes() if world is None else world
    h, w = camera.height, camera.width
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays_c = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    R, c = T_world_camera[:3, :3], T_world_camera[:3, 3]
    d = rays_c @ R.T                                  # world ray per pixel, scaled so camera z = 1
    img = np.full((h, w), 200.0, np.float32)          # sky
    depth = np.full((h, w), np.inf)
    for o, eu, ev, Lu, Lv, tex in world:
        n = np.cross(eu, ev)
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = ((o - c) @ n) / den
        p = c + lam[..., None] * d
        a, b = (p - o) @ eu, (p - o) @ ev
        hit = (lam > 0.1) & (a >= 0) & (a <= Lu) & (b >= 0) & (b <= Lv) & (lam < depth)
        th, tw = tex.shape
        mx = (a / Lu * (tw - 1)).astype(np.float32)
        my = ((1 - b / Lv) * (th - 1)).astype(np.float32)
        sample = cv2.remap(tex.astype(np.float32), np.nan_to_num(mx), np.nan_to_num(my), cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REFLECT)
        img[hit] = sample[hit]
        depth[hit] = lam[hit]
    return np.clip(img, 0, 255).astype(np.uint8), depth


def vehicle_pose(x, y=0.0, yaw=0.0):
    """Vehicle on the road plane at (x, y) heading ``yaw`` (rad)."""
    return make_pose(rot_z(yaw), [x, y, 0.0])


def camera_pose(T_world_vehicle):
    return T_world_vehicle @ T_VC


def frame_prior(T_world_place):
    """The point-method tests' detector frame: vehicle pose (3.0, 0.8, 2 deg) in the place, and a motion prior
    0.5 m and about a degree off it.  Returns ``(T_place_vehicle, T_world_vehicle, prior)``."""
    from scenesig.localiser.pipeline import MotionPrior
    from scenesig.localiser.solver import pose_exp

    T_pv = vehicle_pose(3.0, 0.8, np.radians(2.0))
    T_true = T_world_place @ T_pv
    P = np.diag([0.01, 0.01, 0.03, 1.0, 1.0, 0.3]) ** 2
    prior = MotionPrior(0.0, T_true @ pose_exp([0.005, -0.005, 0.02, 0.5, -0.4, 0.1]), P, 0, T_world_place, 1,
                        False, 0.0)
    return T_pv, T_true, prior
