"""Compiled per-detection loops of the eq. 10 solver (numba): residuals, Huber cost, normal equations.

:class:`scenesig.localiser.solver._Problem` evaluates the cost and builds the Gauss-Newton system about twenty
times per detector frame, each time on a few dozen detections: in numpy that is some forty small
array operations per call, whose interpreter overhead is most of the solve.  These loops compute
the same quantities per detection -- the landmark in the vehicle and camera frames, the whitened
residual ``e = W (z - h)``, its norm, the Huber cost, and the IRLS-weighted ``Σ w A^T A`` and
``Σ w A^T e`` with ``A = W ∂h/∂p_c R_cv [P_v]x|-I`` -- in one pass.  The arithmetic is the same,
but sums run in a different order than numpy's (``einsum``, matmul), so results agree with the numpy
code to rounding (about 1e-15 relative), not bit for bit; the tests compare the two and the
solver's results on the demo's live runs.  The motion-prior term stays in the caller (GTSAM's
``Pose3`` maps).
"""
from __future__ import annotations

import numpy as np

from scenesig.surveys.compiled import AVAILABLE, lazy_njit

__all__ = ["AVAILABLE", "residuals", "normal_equations", "warm_up"]


def _residuals(L, uv, W, R_pv, t_pv, R_cv, t_cv, fx, fy, cx, cy, min_depth, behind, huber_k):
    n = L.shape[0]
    e = np.zeros((n, 2))
    c = np.empty(n)
    front = np.empty(n, np.bool_)
    P_v = np.empty((n, 3))
    P_c = np.empty((n, 3))
    cost = 0.0
    for i in range(n):
        d0, d1, d2 = L[i, 0] - t_pv[0], L[i, 1] - t_pv[1], L[i, 2] - t_pv[2]
        for j in range(3):                                   # R_pv^T (p - t)
            P_v[i, j] = d0 * R_pv[0, j] + d1 * R_pv[1, j] + d2 * R_pv[2, j]
        for j in range(3):                                   # R_cv P_v + t_cv
            P_c[i, j] = R_cv[j, 0] * P_v[i, 0] + R_cv[j, 1] * P_v[i, 1] + R_cv[j, 2] * P_v[i, 2] + t_cv[j]
        z = P_c[i, 2]
        front[i] = z > min_depth
        if front[i]:
            r0 = uv[i, 0] - (fx * P_c[i, 0] / z + cx)
            r1 = uv[i, 1] - (fy * P_c[i, 1] / z + cy)
            e[i, 0] = W[i, 0, 0] * r0 + W[i, 0, 1] * r1
            e[i, 1] = W[i, 1, 0] * r0 + W[i, 1, 1] * r1
            c[i] = np.sqrt(e[i, 0] * e[i, 0] + e[i, 1] * e[i, 1])
        else:
            c[i] = behind
        if c[i] < huber_k:
            cost += c[i] * c[i]
        else:
            cost += 2.0 * huber_k * c[i] - huber_k * huber_k
    return e, c, front, P_v, P_c, 0.5 * cost


def _normal_equations(e, c, front, P_v, P_c, W, R_cv, fx, fy, huber_k):
    L = np.zeros((6, 6))
    b = np.zeros(6)
    D = np.zeros((3, 6))
    A = np.empty((2, 6))
    for i in range(e.shape[0]):
        if not front[i]:
            continue                                        # weight 0: behind the camera
        w = 1.0 if c[i] < huber_k else huber_k / max(c[i], 1e-300)
        x, y, z = P_v[i, 0], P_v[i, 1], P_v[i, 2]
        # d P_v / d xi = [ [P_v]x | -I ] (surveys.geometry.point_pose_jacobian)
        D[0, 1], D[0, 2], D[0, 3] = -z, y, -1.0
        D[1, 0], D[1, 2], D[1, 4] = z, -x, -1.0
        D[2, 0], D[2, 1], D[2, 5] = -y, x, -1.0
        zc = P_c[i, 2]
        J00, J02 = fx / zc, -fx * P_c[i, 0] / (zc * zc)      # d uv / d P_c (pinhole)
        J11, J12 = fy / zc, -fy * P_c[i, 1] / (zc * zc)
        for k in range(6):
            g0 = R_cv[0, 0] * D[0, k] + R_cv[0, 1] * D[1, k] + R_cv[0, 2] * D[2, k]
            g1 = R_cv[1, 0] * D[0, k] + R_cv[1, 1] * D[1, k] + R_cv[1, 2] * D[2, k]
            g2 = R_cv[2, 0] * D[0, k] + R_cv[2, 1] * D[1, k] + R_cv[2, 2] * D[2, k]
            h0, h1 = J00 * g0 + J02 * g2, J11 * g1 + J12 * g2
            A[0, k] = W[i, 0, 0] * h0 + W[i, 0, 1] * h1
            A[1, k] = W[i, 1, 0] * h0 + W[i, 1, 1] * h1
        for p in range(6):
            wa0, wa1 = w * A[0, p], w * A[1, p]
            b[p] += wa0 * e[i, 0] + wa1 * e[i, 1]
            for q in range(6):
                L[p, q] += wa0 * A[0, q] + wa1 * A[1, q]
    return L, b


_RESIDUALS = lazy_njit(_residuals)
_NORMAL_EQUATIONS = lazy_njit(_normal_equations)


def residuals(L, uv, W, R_pv, t_pv, R_cv, t_cv, fx, fy, cx, cy, min_depth, behind, huber_k):
    """``(e, c, front, P_v, P_c, cost)``: whitened residuals (n, 2) (zero behind the camera), their
    norms (``behind`` behind it), the front mask, the landmarks in the vehicle and camera frames and
    the detections' Huber cost ``1/2 Σ ρ(c)``."""
    return _RESIDUALS(L, uv, W, R_pv, t_pv, R_cv, t_cv, float(fx), float(fy), float(cx), float(cy),
                      float(min_depth), float(behind), float(huber_k))


def normal_equations(e, c, front, P_v, P_c, W, R_cv, fx, fy, huber_k):
    """``(Λ, rhs)`` of the detections: ``Σ w A^T A`` and ``Σ w A^T e`` (IRLS Huber weights ``w``)."""
    return _NORMAL_EQUATIONS(e, c, front, P_v, P_c, W, R_cv, float(fx), float(fy), float(huber_k))


def warm_up() -> None:
    """Load the compiled loops now (from numba's cache): before a replay's clock starts."""
    if AVAILABLE:
        L = np.zeros((1, 3)) + [0.0, 0.0, 5.0]
        W = np.eye(2)[None].copy()
        I3, z3 = np.eye(3), np.zeros(3)
        ev = residuals(L, np.zeros((1, 2)), W, I3, z3, I3, z3, 1.0, 1.0, 0.0, 0.0, 0.05, 100.0, 1.5)
        normal_equations(*ev[:5], W, I3, 1.0, 1.0, 1.5)
