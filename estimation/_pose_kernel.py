"""Compiled pose polish with each keyframe point's depth uncertainty (numba, nopython, float64).

:func:`pose_gauss_newton_whitened` is :func:`estimation._kernels.pose_gauss_newton` for points
whose keyframe depth is itself a noisy measurement: the error of a point's keyframe disparity moves
its predicted pixel and disparity in the current frame along one direction ``g``, so the point's
residuals have the covariance ``I + a g g^T`` (in units of the tracks' variance; ``a`` the keyframe
disparity's variance in the same units). Its residuals and Jacobian rows are whitened by the
inverse square root of that matrix, ``I - b g g^T`` (a rank-one update of the identity), before
the Huber weights and the normal equations. Compiled once and cached on disk as ``_kernels``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation._kernels import _huber_weight, _left_update, _solve6, _xform

__all__ = ["pose_gauss_newton_whitened"]

F64 = npt.NDArray[np.float64]


@njit(cache=True)
def pose_gauss_newton_whitened(
    X: Any,
    T0: Any,
    uv: Any,
    disp: Any,
    tw: Any,
    kf_var: Any,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    fb: float,
    huber: float,
    iterations: int,
    stop: float,
    dof: int,
) -> F64:
    """The Gauss-Newton loop of ``estimation.pnp.refine_pose`` with per-point keyframe uncertainty.

    As :func:`estimation._kernels.pose_gauss_newton` (same arguments, residuals, Jacobian,
    ``tw``, stopping rules and update), with ``kf_var[i]``: the variance of point ``i``'s keyframe
    disparity ``fb / X[i, 2]`` over the tracks' pixel variance (0: an exact point). Per point,
    ``g`` = d[u, v, d_pred] / d(keyframe disparity) at the current pose (``dX / dd = -X / d``;
    ``g_d`` = 0 without a measured disparity); the point's rows ``r`` and ``J`` become
    ``r - b g (g . r)`` and ``J - b g (g^T J)`` with ``b = (1 - 1 / sqrt(1 + a |g|^2)) / |g|^2``,
    then one Huber weight per whitened row. ``fb`` must be positive (it converts depths to
    disparities even where no disparity is measured).
    """
    n = X.shape[0]
    T: F64 = T0.copy()
    H = np.empty((dof, dof))
    grad = np.empty(dof)
    dR = np.empty((3, 3))
    Tn = np.empty((4, 4))
    J = np.zeros((3, dof))
    r = np.zeros(3)
    gv = np.zeros(3)
    q = np.zeros(dof)
    for _ in range(iterations):
        # The normal equations' upper triangle and the gradient in scalars (dense rows once whitened).
        h00 = h01 = h02 = h03 = h04 = h05 = h11 = h12 = h13 = h14 = h15 = 0.0
        h22 = h23 = h24 = h25 = h33 = h34 = h35 = h44 = h45 = h55 = 0.0
        g0 = g1 = g2 = g3 = g4 = g5 = 0.0
        behind = False
        for i in range(n):
            z = _xform(X, T, i, 2)
            if z <= 1e-6:
                behind = True
                break
            x = _xform(X, T, i, 0)
            y = _xform(X, T, i, 1)
            iz = 1.0 / z
            xz = x * iz
            yz = y * iz
            c = tw[i]
            r[0] = fx * xz + cx - uv[i, 0]
            J[0, 0] = c * (fx * iz)
            J[0, 1] = 0.0
            J[0, 2] = c * ((-fx * xz) * iz)
            J[0, 3] = (-fx * xz) * yz
            J[0, 4] = fx * (xz * xz + 1.0)
            J[0, 5] = -fx * yz
            r[1] = fy * yz + cy - uv[i, 1]
            J[1, 0] = 0.0
            J[1, 1] = c * (fy * iz)
            J[1, 2] = c * ((-fy * yz) * iz)
            J[1, 3] = -fy * (yz * yz + 1.0)
            J[1, 4] = (fy * xz) * yz
            J[1, 5] = fy * xz
            # The keyframe disparity's direction: X_kf moves by -X_kf / d_kf per pixel of it, and
            # R X_kf = X_cur - t.
            s_kf = -X[i, 2] / fb
            dx = s_kf * (x - T[0, 3])
            dy = s_kf * (y - T[1, 3])
            dz = s_kf * (z - T[2, 3])
            gv[0] = fx * (dx - xz * dz) * iz
            gv[1] = fy * (dy - yz * dz) * iz
            dm = disp[i]
            rows = 3 if dm == dm else 2
            if rows == 3:
                kz = fb * iz * iz
                r[2] = fb * iz - dm
                J[2, 0] = 0.0
                J[2, 1] = 0.0
                J[2, 2] = -kz * c
                J[2, 3] = -kz * y * c
                J[2, 4] = kz * x * c
                J[2, 5] = 0.0
                gv[2] = -kz * dz
            gg = 0.0
            for k in range(rows):
                gg += gv[k] * gv[k]
            av = kf_var[i]
            if av > 0.0 and gg > 0.0:
                bw = (1.0 - 1.0 / np.sqrt(1.0 + av * gg)) / gg
                gr = 0.0
                for k in range(rows):
                    gr += gv[k] * r[k]
                for a in range(dof):
                    s = 0.0
                    for k in range(rows):
                        s += gv[k] * J[k, a]
                    q[a] = s
                for k in range(rows):
                    r[k] -= bw * gv[k] * gr
                    for a in range(dof):
                        J[k, a] -= bw * gv[k] * q[a]
            for k in range(rows):
                j0, j1, j2, j3, j4, j5, rk = J[k, 0], J[k, 1], J[k, 2], J[k, 3], J[k, 4], J[k, 5], r[k]
                w = _huber_weight(rk, huber)
                w0, w1, w2, w3, w4, w5 = w * j0, w * j1, w * j2, w * j3, w * j4, w * j5
                h00 += w0 * j0
                h01 += w0 * j1
                h02 += w0 * j2
                h03 += w0 * j3
                h04 += w0 * j4
                h05 += w0 * j5
                h11 += w1 * j1
                h12 += w1 * j2
                h13 += w1 * j3
                h14 += w1 * j4
                h15 += w1 * j5
                h22 += w2 * j2
                h23 += w2 * j3
                h24 += w2 * j4
                h25 += w2 * j5
                h33 += w3 * j3
                h34 += w3 * j4
                h35 += w3 * j5
                h44 += w4 * j4
                h45 += w4 * j5
                h55 += w5 * j5
                g0 += w0 * rk
                g1 += w1 * rk
                g2 += w2 * rk
                g3 += w3 * rk
                g4 += w4 * rk
                g5 += w5 * rk
        if behind:
            break
        H[0, 0], H[0, 1], H[0, 2], H[0, 3], H[0, 4], H[0, 5] = h00, h01, h02, h03, h04, h05
        H[1, 1], H[1, 2], H[1, 3], H[1, 4], H[1, 5] = h11, h12, h13, h14, h15
        H[2, 2], H[2, 3], H[2, 4], H[2, 5] = h22, h23, h24, h25
        H[3, 3], H[3, 4], H[3, 5] = h33, h34, h35
        H[4, 4], H[4, 5] = h44, h45
        H[5, 5] = h55
        grad[0], grad[1], grad[2], grad[3], grad[4], grad[5] = -g0, -g1, -g2, -g3, -g4, -g5
        for a in range(dof):
            for b in range(a):
                H[a, b] = H[b, a]
        if not _solve6(H, grad):
            break
        if _left_update(T, grad, dR, Tn) < stop:
            break
    return T
