"""Rasteriser for textured planar quads: one ``cv2.warpPerspective`` per visible quad and a z-buffer.

Why this design: a street scene is almost entirely planes (facades, road, signs) plus cut-out
billboards (trees, people), and a plane maps to the image by a homography.  Warping each quad's
texture (at a mip level matched to its on-screen size, so far surfaces do not alias) into its
bounding box and keeping, per pixel, the nearest surface by *inverse depth* -- which is affine in
pixel coordinates on a plane, so it costs one broadcast add -- renders VGA frames in a few
milliseconds on one core, with exact geometry: a world point on a quad lands on the pixel the
pinhole model predicts, and the depth buffer holds the true depth of every pixel.

Texture mapping: normalised texture coordinates ``(u, v)`` in [0, 1]^2 (``u`` right, ``v`` down; the
outer edges of the texels, so texel ``x`` of a ``w``-texel level has centre ``u = (x + 0.5) / w``) map
to world points by a 4x3 matrix ``Wn``: ``X_h = Wn @ (u, v, 1)`` -- affine for rectangles, projective
for general planar quadrilaterals (road tiles on bends).  Mip levels come from ``cv2.pyrDown``, which
centres texel ``i`` of level ``L`` on level-0 texel ``2^L i``; the level's texel-to-``(u, v)`` map accounts
for it (a half-texel slip here shows up as a quarter-pixel shift of everything seen at mip level 1).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from ..geometry import Camera

__all__ = ["Renderer", "quad_texture_maps", "billboard_corners", "build_pyramid"]

MAX_LEVELS = 7


class Pyramid(list):
    """Mip levels (BGRA uint8, level 0 = full resolution); ``opaque`` when no texel is cut out."""

    opaque: bool = False


def build_pyramid(bgra: np.ndarray, levels: int = MAX_LEVELS, min_size: int = 4) -> Pyramid:
    """Mip pyramid by Gaussian ``pyrDown``."""
    out = Pyramid([np.ascontiguousarray(bgra)])
    out.opaque = bool(bgra[..., 3].min() >= 128)
    while len(out) < levels and min(out[-1].shape[:2]) >= 2 * min_size:
        out.append(cv2.pyrDown(out[-1]))
    return out


def quad_texture_maps(corners: np.ndarray) -> np.ndarray:
    """(N,4,3) corners TL,TR,BR,BL -> (N,4,3) matrices Wn mapping (u, v, 1) to homogeneous world points."""
    corners = np.asarray(corners, float).reshape(-1, 4, 3)
    out = np.zeros((len(corners), 4, 3))
    unit = np.float32([[0, 0], [1, 0], [1, 1], [0, 1]])
    for i, C in enumerate(corners):
        o = C[0]
        e1 = C[1] - o
        e1 /= np.linalg.norm(e1)
        e2 = C[3] - o
        e2 = e2 - e1 * np.dot(e2, e1)
        e2 /= np.linalg.norm(e2)
        p2 = np.stack([(C - o) @ e1, (C - o) @ e2], 1).astype(np.float32)
        Hp = cv2.getPerspectiveTransform(unit, p2).astype(float)
        B = np.zeros((4, 3))
        B[:3, 0], B[:3, 1], B[:3, 2], B[3, 2] = e1, e2, o, 1.0
        out[i] = B @ Hp
    return out


def billboard_corners(base: np.ndarray, size: np.ndarray, flip: np.ndarray, cam_pos: np.ndarray):
    """Corners (M,4,3) of upright billboards turned to face the camera position (about the vertical)."""
    d = base[:, :2] - cam_pos[None, :2]
    n = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.maximum(n, 1e-6)
    right = np.stack([d[:, 1], -d[:, 0]], 1)  # the camera's right, seen looking at the board
    right = np.where(flip[:, None], -right, right)  # mirrored texture: swap left and right ends
    half = right * (size[:, :1] / 2)
    C = np.zeros((len(base), 4, 3))
    left_xy, right_xy = base[:, :2] - half, base[:, :2] + half
    C[:, 0, :2], C[:, 1, :2], C[:, 2, :2], C[:, 3, :2] = left_xy, right_xy, right_xy, left_xy
    z0 = base[:, 2]
    C[:, 0, 2] = C[:, 1, 2] = z0 + size[:, 1]
    C[:, 2, 2] = C[:, 3, 2] = z0
    return C


def billboard_maps(C: np.ndarray) -> np.ndarray:
    """Wn for rectangles (affine), vectorised: X = TL + (TR-TL) u + (BL-TL) v."""
    Wn = np.zeros((len(C), 4, 3))
    Wn[:, :3, 0] = C[:, 1] - C[:, 0]
    Wn[:, :3, 1] = C[:, 3] - C[:, 0]
    Wn[:, :3, 2] = C[:, 0]
    Wn[:, 3, 2] = 1.0
    return Wn


class Renderer:
    """Z-buffered quad rasteriser for one camera.

    Buffers after :meth:`begin` / :meth:`draw`: ``fb`` (H,W,4) uint8 (BGR + the texture's 4th channel,
    which carries the night light level, see :mod:`scenesig.surveys.sim.conditions`), ``invz`` (H,W) float32
    inverse depth (0 = nothing drawn / sky), ``cls`` (H,W) uint8 class ids.
    """

    def __init__(self, camera: Camera, near: float = 0.2, far: float = 450.0, lod_bias: float = 0.0,
                 record_ids: bool = False):
        self.cam = camera
        self.K = camera.K
        self.Kinv = np.linalg.inv(self.K)
        self.W, self.H = camera.width, camera.height
        self.near, self.far = near, far
        self.lod_bias = lod_bias
        self.xs = np.arange(self.W, dtype=np.float32)
        self.ys = np.arange(self.H, dtype=np.float32)
        self.stats = {"quads": 0, "pixels": 0}
        self.record_ids = record_ids

    def begin(self):
        self.fb = np.zeros((self.H, self.W, 4), np.uint8)
        self.invz = np.zeros((self.H, self.W), np.float32)
        self.cls = np.zeros((self.H, self.W), np.uint8)
        self.stats = {"quads": 0, "pixels": 0}
        self._fb32 = self.fb.view(np.uint32)[..., 0]
        # which quad drew each pixel (-1: none); kept only on request (tests, evaluation)
        self.ids = np.full((self.H, self.W), -1, np.int32) if self.record_ids else None

    def draw(self, T_camera_world: np.ndarray, corners: np.ndarray, Wn: np.ndarray, levels_of, cls: np.ndarray,
             depth_test: bool = True, cull_far: float | None = None, draw_last: np.ndarray | None = None,
             id_offset: int = 0):
        """Draw quads.

        Parameters
        ----------
        T_camera_world : 4x4 world-to-camera transform.
        corners, Wn : (N,4,3) world corners and texture maps.
        levels_of : callable i -> mip pyramid (list of BGRA arrays) of quad i (called only if visible).
        cls : (N,) class ids.
        depth_test : False paints (the sky backdrop) without testing or writing depth.
        draw_last : optional (N,) ints; larger values are drawn later (ground after upright things).
        id_offset : added to the quad index in the id buffer (when ``record_ids``).
        """
        if len(corners) == 0:
            return
        R, t = T_camera_world[:3, :3], T_camera_world[:3, 3]
        Xc = corners @ R.T + t  # (N,4,3)
        z = Xc[..., 2]
        far = cull_far if cull_far is not None else self.far
        vis = (z.max(1) > self.near) & (z.min(1) < far)
        # frustum side planes (a quad wholly outside one plane is invisible)
        fx, fy, cx, cy = self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy
        x_l = (-0.5 - cx) / fx
        x_r = (self.W - 0.5 - cx) / fx
        y_t = (-0.5 - cy) / fy
        y_b = (self.H - 0.5 - cy) / fy
        X, Y = Xc[..., 0], Xc[..., 1]
        vis &= ~np.all(X < x_l * z, 1) & ~np.all(X > x_r * z, 1) & ~np.all(Y < y_t * z, 1) & ~np.all(Y > y_b * z, 1)
        idx = np.nonzero(vis)[0]
        if len(idx) == 0:
            return
        K = self.K
        P = np.einsum("ij,njk->nik", T_camera_world[:3, :], Wn[idx])  # (n,3,3): (u,v,1) -> camera point
        Hn = np.einsum("ij,njk->nik", K, P)                            # (u,v,1) -> pixel (homogeneous)
        # plane of each quad in camera coordinates: normal . X = dist
        Xi = Xc[idx]
        nrm = np.cross(Xi[:, 1] - Xi[:, 0], Xi[:, 3] - Xi[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        dist = np.einsum("ij,ij->i", nrm, Xi[:, 0])
        # inverse depth on the plane: 1/z = n . (Kinv [u v 1]) / dist  -> affine coefficients
        with np.errstate(divide="ignore", invalid="ignore"):
            coef = (nrm @ self.Kinv) / np.where(np.abs(dist) < 1e-9, np.nan, dist)[:, None]
        zi = Xi[..., 2]
        clipped = zi.min(1) < self.near
        uvw = Xi @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            px = uvw[..., :2] / uvw[..., 2:3]
        # screen -> texture Jacobian at the polygon centroid (for the mip level), vectorised
        with np.errstate(all="ignore"):
            Hi = np.linalg.inv(Hn)
        cen = px.mean(1)
        q = np.einsum("nij,nj->ni", Hi, np.c_[cen, np.ones(len(cen))])
        J = (Hi[:, :2, :2] * q[:, 2, None, None] - q[:, :2, None] * Hi[:, None, 2, :2]) / (q[:, 2] ** 2)[:, None, None]
        # near to far, so that hidden quads can be skipped before they are warped
        key = np.maximum(zi.min(1), self.near)
        if draw_last is not None:
            key = key + 1e6 * draw_last[idx]  # ground under everything: drawn after what may hide it
        order = np.argsort(key)
        for j in order:
            i = idx[j]
            A, Bc, Cc = coef[j]
            if not np.isfinite(A):
                continue  # seen exactly edge-on
            if clipped[j]:
                poly = _clip_near(Xi[j], self.near)
                if len(poly) < 3:
                    continue
                uvp = poly @ K.T
                pj = uvp[:, :2] / uvp[:, 2:3]
                c = pj.mean(0)
                qq = Hi[j] @ np.array([c[0], c[1], 1.0])
                Jj = (Hi[j, :2, :2] * qq[2] - np.outer(qq[:2], Hi[j, 2, :2])) / (qq[2] * qq[2])
            else:
                pj = px[j]
                Jj = J[j]
            x0 = max(int(np.floor(pj[:, 0].min())), 0)
            x1 = min(int(np.ceil(pj[:, 0].max())) + 1, self.W)
            y0 = max(int(np.floor(pj[:, 1].min())), 0)
            y1 = min(int(np.ceil(pj[:, 1].max())) + 1, self.H)
            if x1 <= x0 or y1 <= y0 or (x1 - x0) * (y1 - y0) < 4:
                continue  # off screen, or a speck smaller than a couple of pixels
            if depth_test:
                # occlusion: the quad's nearest possible point in its box is behind everything drawn there
                izmax = max(A * x0 + Bc * y0, A * (x1 - 1) + Bc * y0, A * x0 + Bc * (y1 - 1),
                            A * (x1 - 1) + Bc * (y1 - 1)) + Cc
                if izmax <= 0:
                    continue
                izr = self.invz[y0:y1, x0:x1]
                if izmax < izr.min():
                    continue
                if (x1 - x0) * (y1 - y0) >= 4096:
                    # exact visibility before warping: crop the box to the pixels where the plane is in
                    # front (the warp costs ~5x more per pixel than this test)
                    iz = np.add.outer(self.ys[y0:y1] * np.float32(Bc) + np.float32(Cc),
                                      self.xs[x0:x1] * np.float32(A))
                    vis = iz > izr
                    rows = np.flatnonzero(vis.any(1))
                    if len(rows) == 0:
                        continue
                    cols = np.flatnonzero(vis[rows[0]:rows[-1] + 1].any(0))
                    x0, x1, y0, y1 = x0 + cols[0], x0 + cols[-1] + 1, y0 + rows[0], y0 + rows[-1] + 1
                    izr = self.invz[y0:y1, x0:x1]
            pyr = levels_of(i)
            if pyr is None:
                continue
            h0, w0 = pyr[0].shape[:2]
            a, b, c_, d = Jj[0, 0] * w0, Jj[0, 1] * w0, Jj[1, 0] * h0, Jj[1, 1] * h0
            E = a * a + b * b + c_ * c_ + d * d
            D = abs(a * d - b * c_)
            smax = math.sqrt(max((E + math.sqrt(max(E * E - 4 * D * D, 0.0))) / 2, 1e-18))
            smin = max(D / smax, 1e-9)
            if not (np.isfinite(smax) and np.isfinite(smin)):
                continue
            lm = math.log2(smax)
            lvl = 0.5 * lm + 0.5 * math.log2(smin) + 0.25 + self.lod_bias
            lvl = max(lvl, lm - 1.0)  # never let the most compressed direction alias by more than 2x
            L = min(max(int(math.floor(lvl)), 0), len(pyr) - 1)
            tex = pyr[L]
            # pyrDown centres texel i of level L on level-0 texel 2^L i, so u = (2^L x + 0.5) / w0
            f = float(1 << L)
            S = np.array([[f / w0, 0, 0.5 / w0], [0, f / h0, 0.5 / h0], [0, 0, 1.0]])
            Hb = Hn[j] @ S
            Hb[0] -= x0 * Hb[2]
            Hb[1] -= y0 * Hb[2]
            bw, bh = x1 - x0, y1 - y0
            # replicate the border texels (no dark fringe from interpolating with a black border) and
            # take the quad's coverage from its projected outline instead
            patch = cv2.warpPerspective(tex, Hb, (bw, bh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            cover = np.zeros((bh, bw), np.uint8)
            cv2.fillConvexPoly(cover, np.round((pj - (x0, y0)) * 16).astype(np.int32), 1, cv2.LINE_8, 4)
            if getattr(pyr, "opaque", False):
                m = cover.view(bool)
            else:
                m = patch[..., 3] >= 128
                m &= cover.view(bool)
            iz = np.add.outer(self.ys[y0:y1] * np.float32(Bc) + np.float32(Cc), self.xs[x0:x1] * np.float32(A))
            if depth_test:
                m &= iz > izr
                np.copyto(izr, iz, where=m)
            else:
                m &= iz > 0
            np.copyto(self._fb32[y0:y1, x0:x1], patch.view(np.uint32)[..., 0], where=m)
            np.copyto(self.cls[y0:y1, x0:x1], cls[i], where=m)
            if self.ids is not None and depth_test:
                np.copyto(self.ids[y0:y1, x0:x1], id_offset + i, where=m)
            self.stats["quads"] += 1
            self.stats["pixels"] += bw * bh

    def _unoccluded_box(self, x0, x1, y0, y1, A, B, C, blk=16):
        """Shrink a bounding box to the 16x16 blocks where the plane could be in front of the z-buffer.

        The plane's inverse depth is affine, so its maximum over a block is at a block corner; a block
        whose minimum buffered inverse depth exceeds that is hidden and need not be warped.
        """
        h, w = y1 - y0, x1 - x0
        nby, nbx = -(-h // blk), -(-w // blk)
        reg = np.full((nby * blk, nbx * blk), np.inf, np.float32)
        reg[:h, :w] = self.invz[y0:y1, x0:x1]
        bmin = reg.reshape(nby, blk, nbx, blk).min(axis=(1, 3))
        gx = x0 + np.minimum(np.arange(nbx + 1) * blk, w - 1).astype(np.float32)
        gy = y0 + np.minimum(np.arange(nby + 1) * blk, h - 1).astype(np.float32)
        g = np.add.outer(gy * B + C, gx * A)
        qmax = np.maximum(np.maximum(g[:-1, :-1], g[:-1, 1:]), np.maximum(g[1:, :-1], g[1:, 1:]))
        vis = qmax >= bmin
        if not vis.any():
            return None
        rows = np.nonzero(vis.any(1))[0]
        cols = np.nonzero(vis.any(0))[0]
        return (x0 + cols[0] * blk, min(x0 + (cols[-1] + 1) * blk, x1),
                y0 + rows[0] * blk, min(y0 + (rows[-1] + 1) * blk, y1))

    def depth(self) -> np.ndarray:
        """Depth (z, metres) per pixel; inf where nothing (sky) was drawn."""
        with np.errstate(divide="ignore"):
            return np.where(self.invz > 0, 1.0 / self.invz, np.inf).astype(np.float32)


def _clip_near(P: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (k,3) against the plane z = near."""
    out = []
    n = len(P)
    for k in range(n):
        a, b = P[k], P[(k + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out)
