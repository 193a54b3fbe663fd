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
        for a in range(dof):
            grad[a] = 0.0
            for b in range(dof):
                H[a, b] = 0.0
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
                w = _huber_weight(r[k], huber)
                for a in range(dof):
                    wa = w * J[k, a]
                    if wa != 0.0:
                        for b in range(a, dof):
                            H[a, b] += wa * J[k, b]
                        grad[a] -= wa * r[k]
        if behind:
            break
        for a in range(dof):
            for b in range(a):
                H[a, b] = H[b, a]
        if not _solve6(H, grad):
            break
        if _left_update(T, grad, dR, Tn) < stop:
            break
    return T
