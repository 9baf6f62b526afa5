"""Keypoint-constrained diffeomorphism matching, KDM (the set stage of the point-set-domain seed, §4.2).

The seed fits a diffeomorphism ``phi`` on the *matched keypoints only* by minimising (eq. 6)

    E(phi) = Diss(R, T o phi) + rho Reg(phi),

with ``phi = exp(v)`` the exponential of a static velocity field (SVF) written in a multi-scale
reproducing-kernel basis (eqs. 7-9, after Pai et al.'s multi-scale kernel diffeomorphisms):

    v(x) = sum_m sum_i K_m(c_i, x) a_i^m,        K_m(c, x) = exp(-|x - c|^2 / (2 s_m^2)).

Here the point sets are the matched keypoints ``x_j`` (sensed image) and their targets ``z_j``
(their matches on the map taken back through the RANSAC affine the fit starts from, so ``phi``
only models what the affine leaves over), ``Diss = 1/2 sum_j |phi(x_j) - z_j|^2`` and ``Reg`` is
the RKHS norm ``sum_m tr(A_m^T K_m(C, C) A_m)`` of the field.  The exponential is the flow of
``v`` for unit time, integrated by ``steps`` fourth-order Runge-Kutta steps; ``exp(-v)`` is its
inverse (:meth:`KDM.inverse`), so the map is invertible by construction -- the property that lets
the domain stage warp either image onto the other.

The fit is Gauss-Newton on the kernel weights with the Jacobian of ``phi(x_j)`` approximated by the
mean kernel row along the point's trajectory (exact for ``exp(v) ~ id + v``), regularised by
``rho`` times the kernel Gram matrix (the gradient of ``Reg``).  Sizes are small -- at most
``max_centres`` kernel centres (the matched points, thinned on a grid) times the number of scales
-- so a fit is a few small dense solves.
"""
from __future__ import annotations

import numpy as np

from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "KDM", "fit_kdm", "thin_centres"]

#: Settings the seed leaves open (chosen on seed-0 development trials, docs/aerial.md).
default_config = {
    "scales_px": (40.0, 80.0, 160.0),   # kernel widths s_m of the multi-scale basis (eq. 7)
    "rho": 1.0,                         # weight of Reg(phi) in eq. 6
    "steps": 6,                         # RK4 steps integrating the flow of v for unit time (exp(v))
    "iterations": 8,                    # Gauss-Newton iterations
    "max_centres": 120,                 # kernel centres: the matched points thinned to at most this many
}


def _sqdist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d2 = (a * a).sum(axis=1)[:, None] + (b * b).sum(axis=1)[None, :] - 2.0 * (a @ b.T)
    return np.maximum(d2, 0.0)


def _gauss(a: np.ndarray, b: np.ndarray, s: float, d2: np.ndarray | None = None) -> np.ndarray:
    d2 = _sqdist(a, b) if d2 is None else d2
    return np.exp(d2 * (-0.5 / (s * s)))


def thin_centres(xy: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of the points, spread out: one per cell of a grid sized for ~``n`` cells (the first
    point met in each), deterministic."""
    xy = np.asarray(xy, float)
    if len(xy) <= n:
        return xy.copy()
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    cell = float(np.sqrt(span[0] * span[1] / n)) or 1.0
    k = np.floor((xy - lo) / cell).astype(np.int64)
    _, first = np.unique(k[:, 0] * 1_000_003 + k[:, 1], return_index=True)
    return xy[np.sort(first)][:n]


class KDM:
    """A fitted diffeomorphism ``phi = exp(v)`` (see the module docstring).

    Attributes
    ----------
    centres : ndarray (N, 2)
    weights : ndarray (M, N, 2)
        Kernel weights ``a_i^m`` per scale.
    scales : tuple of float
    steps : int
    rms : float
        Root-mean-square residual ``|phi(x_j) - z_j|`` over the fitted points (px).
    energy : float
        Final value of eq. 6.
    """

    def __init__(self, centres, weights, scales, steps: int, rms: float = float("nan"),
                 energy: float = float("nan")):
        self.centres = np.asarray(centres, float).reshape(-1, 2)
        self.weights = np.asarray(weights, float).reshape(len(scales), -1, 2)
        self.scales = tuple(float(s) for s in scales)
        self.steps = int(steps)
        self.rms = float(rms)
        self.energy = float(energy)

    @classmethod
    def identity(cls, scales=(1.0,), steps: int = 1) -> "KDM":
        return cls(np.zeros((0, 2)), np.zeros((len(scales), 0, 2)), scales, steps, 0.0, 0.0)

    def velocity(self, xy) -> np.ndarray:
        """The static velocity field ``v`` at points ``(..., 2)`` (eq. 7)."""
        xy = np.asarray(xy, float)
        flat = xy.reshape(-1, 2)
        v = np.zeros_like(flat)
        if len(self.centres):
            d2 = _sqdist(flat, self.centres)          # shared by every scale
            for s, a in zip(self.scales, self.weights):
                v += _gauss(flat, self.centres, s, d2) @ a
        return v.reshape(xy.shape)

    def _flow(self, xy, sign: float) -> np.ndarray:
        x = np.asarray(xy, float).copy()
        h = sign / self.steps
        for _ in range(self.steps):                   # RK4 on dx/dt = sign * v(x)
            k1 = self.velocity(x)
            k2 = self.velocity(x + 0.5 * h * k1)
            k3 = self.velocity(x + 0.5 * h * k2)
            k4 = self.velocity(x + h * k3)
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return x

    def __call__(self, xy) -> np.ndarray:
        """``phi(x) = exp(v)(x)``: the flow of ``v`` for unit time."""
        return self._flow(xy, 1.0)

    def inverse(self, xy) -> np.ndarray:
        """``phi^-1 = exp(-v)``."""
        return self._flow(xy, -1.0)

    def jacobian_det(self, xy, h: float = 0.5) -> np.ndarray:
        """Determinant of ``d phi / d x`` by central differences (> 0 everywhere for a diffeomorphism)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        ex, ey = np.array([h, 0.0]), np.array([0.0, h])
        dx = (self(xy + ex) - self(xy - ex)) / (2 * h)
        dy = (self(xy + ey) - self(xy - ey)) / (2 * h)
        return dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]


def fit_kdm(src, dst, config: dict | None = None, weights=None) -> KDM:
    """Fit ``phi`` with ``phi(src_j) ~ dst_j`` by minimising eq. 6 (see the module docstring).

    Parameters
    ----------
    src, dst : array_like (n, 2)
        Matched keypoints and their targets, in one frame (pixels).
    config : dict, optional
        Overrides of :data:`default_config`.
    weights : array_like (n,), optional
        Per-point weights of the data term (default 1).

    Returns
    -------
    KDM
        The identity when there are fewer than three points.
    """
    cfg = merge_settings(default_config, config, "KDM")
    scales = tuple(float(s) for s in cfg["scales_px"])
    if not scales or min(scales) <= 0:
        raise ValueError(f"KDM scales_px must be positive widths, got {cfg['scales_px']!r}")
    if float(cfg["rho"]) < 0 or int(cfg["steps"]) < 1:
        raise ValueError("KDM rho must be >= 0 and steps >= 1")
    src = np.asarray(src, float).reshape(-1, 2)
    dst = np.asarray(dst, float).reshape(-1, 2)
    if len(src) != len(dst):
        raise ValueError(f"KDM needs as many targets as points, got {len(src)} and {len(dst)}")
    steps = int(cfg["steps"])
    if len(src) < 3:
        return KDM.identity(scales, steps)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    C = thin_centres(src, int(cfg["max_centres"]))
    M, N = len(scales), len(C)
    rho = float(cfg["rho"])
    # Reg's Hessian: block-diagonal kernel Gram matrices (the RKHS norm of each scale's field)
    G = np.zeros((M * N, M * N))
    for m, s in enumerate(scales):
        G[m * N:(m + 1) * N, m * N:(m + 1) * N] = _gauss(C, C, s)
    theta = np.zeros((M * N, 2))
    kdm = KDM(C, theta.reshape(M, N, 2), scales, steps)
    sw = np.sqrt(w)[:, None]

    def energy(th, r):
        return 0.5 * float((w[:, None] * r ** 2).sum()) + rho * float((th * (G @ th)).sum())

    r = dst - src
    E = energy(theta, r)
    for _ in range(int(cfg["iterations"])):
        # Jacobian of phi(x_j) in the weights: mean kernel row along the trajectory (module docstring)
        traj = [src]
        x = src
        for _ in range(steps):
            x = x + kdm.velocity(x) / steps
            traj.append(x)
        mid = [0.5 * (a + b) for a, b in zip(traj[:-1], traj[1:])]
        J = np.zeros((len(src), M * N))
        for p in mid:
            d2 = _sqdist(p, C)
            J += np.hstack([_gauss(p, C, s, d2) for s in scales])
        J /= steps
        Jw = J * sw
        A = Jw.T @ Jw + 2 * rho * G + 1e-9 * np.eye(M * N)
        b = Jw.T @ (sw * r) - 2 * rho * (G @ theta)
        step = np.linalg.solve(A, b)
        improved = False
        for damp in (1.0, 0.5, 0.25):
            cand = theta + damp * step
            k2 = KDM(C, cand.reshape(M, N, 2), scales, steps)
            r2 = dst - k2(src)
            E2 = energy(cand, r2)
            if E2 < E:
                theta, kdm, r, improved = cand, k2, r2, E - E2 > 1e-6 * max(E, 1e-12)
                E = E2
                break
        if not improved:
            break
    rms = float(np.sqrt(np.mean((r ** 2).sum(axis=1))))
    return KDM(C, theta.reshape(M, N, 2), scales, steps, rms, E)
