"""The essential matrix's Levenberg-Marquardt loop on the Sampson distance, compiled (numba,
nopython, float64, no fastmath).

:func:`essential_lm` is the whole loop of ``estimation.essential.refine_essential``, and
:func:`essential_prior` the part of ``estimation.essential.essential_from_prior`` before the
metric scale (normalised rays, the gate, the loop, the inlier test). The residuals and Jacobian
are those of ``estimation._kernels`` (``sampson_jacobian``, ``sampson_distance``), called as they
are; the normal equations are summed point by point in scalars (not ``J^T W J`` in OpenBLAS's
blocked order), the 5x5 system solved by OpenCV's Cholesky algorithm (``cv::hal::Cholesky64f``,
that of ``cv2.solve(..., DECOMP_CHOLESKY)``) and the rotation updated by Rodrigues' formula (as
``cv2.Rodrigues``). So the results agree with the numpy loop this replaced to ~1e-12 relative,
not bit for bit (``tests/unit/test_essential_kernel.py`` keeps that loop and compares at 1e-9).

:func:`scale_terms` is the elementwise part of ``estimation.essential._metric_scale_rays`` (the
metric scale's per-point solutions, their median and the points near it), operation by operation
as numpy did it: equal bit for bit; the weighted mean is left to numpy's ``@`` and ``sum``.

Compiled once and cached on disk next to this module, as ``estimation._kernels``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation._kernels import sampson_distance, sampson_jacobian
from estimation._pose_kernel import _huber_weight, _rotvec_matrix

__all__ = ["essential_lm", "essential_prior", "scale_terms"]

F64 = npt.NDArray[np.float64]

_DBL_EPSILON = 2.220446049250313e-16


@njit(cache=True)
def _huber_cost(r: Any, huber: float) -> float:
    """Sum of the Huber function of the residuals ``r``: ``m (2a - m) / 2`` with ``a = |r|``,
    ``m = min(a, huber)`` (NaN when a residual is NaN)."""
    s = 0.0
    for i in range(r.shape[0]):
        a = abs(r[i])
        m = a if a < huber else huber
        s += m * (a + a - m)
    return 0.5 * s


@njit(cache=True)
def _cholesky_solve(A: Any, b: Any) -> bool:
    """Solve ``A x = b`` in place (``b`` becomes ``x``; ``A``'s lower triangle is read and
    overwritten) by OpenCV's Cholesky (``cv::hal::Cholesky64f``): False, as ``cv2.solve``, when
    a pivot falls below machine epsilon (not positive definite)."""
    m = A.shape[0]
    for i in range(m):
        for j in range(i):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s * A[j, j]
        s = A[i, i]
        for k in range(i):
            s -= A[i, k] * A[i, k]
        if s < _DBL_EPSILON:
            return False
        A[i, i] = 1.0 / np.sqrt(s)
    for i in range(m):
        s = b[i]
        for k in range(i):
            s -= A[i, k] * b[k]
        b[i] = s * A[i, i]
    for i in range(m - 1, -1, -1):
        s = b[i]
        for k in range(m - 1, i, -1):
            s -= A[k, i] * b[k]
        b[i] = s * A[i, i]
    return True


@njit(cache=True)
def _unit_cross(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float, out: Any, col: int) -> None:
    """Column ``col`` of ``out`` = the normalised cross product ``a x b``."""
    c0 = a1 * b2 - a2 * b1
    c1 = a2 * b0 - a0 * b2
    c2 = a0 * b1 - a1 * b0
    nrm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    out[0, col] = c0 / nrm
    out[1, col] = c1 / nrm
    out[2, col] = c2 / nrm


@njit(cache=True)
def essential_lm(
    R0: Any, t0: Any, x_ref: Any, x_cur: Any, f_px: float, huber: float, iterations: int
) -> tuple[F64, F64]:
    """The loop of ``estimation.essential.refine_essential``: Gauss-Newton on the Huber-weighted
    Sampson distance (pixels) over a left rotation increment and the unit translation moved in
    its tangent plane (5 DoF), a step kept only when it lowers the robust cost (else the normal
    equations' diagonal is scaled up by ``1 + lam``, Levenberg-Marquardt, up to 4 tries); stops
    after ``iterations`` accepted steps, when no try helps or a step gains less than 1e-4 of the
    cost. ``R0`` (3, 3), ``t0`` (3,) (any length) the start; ``x_ref``, ``x_cur`` (N, 3)
    contiguous normalised rays. Returns ``(R, t)``, ``|t| = 1`` (the start when N < 5)."""
    R = R0.copy()
    t = np.empty(3)
    nt = np.sqrt(t0[0] * t0[0] + t0[1] * t0[1] + t0[2] * t0[2])
    for a in range(3):
        t[a] = t0[a] / nt
    n = x_ref.shape[0]
    if n < 5:
        return R, t
    J6 = np.empty((n, 6))
    r = sampson_jacobian(R, t, x_ref, x_cur, f_px, J6)
    cost = _huber_cost(r, huber)
    lam = 0.0
    B = np.empty((3, 2))
    H = np.empty((5, 5))
    g = np.empty(5)
    A = np.empty((5, 5))
    dx = np.empty(5)
    j = np.empty(5)
    dR = np.empty((3, 3))
    for it in range(iterations):
        if it:
            r = sampson_jacobian(R, t, x_ref, x_cur, f_px, J6)
        # Tangent basis of the unit translation.
        if abs(t[0]) < 0.9:
            _unit_cross(t[0], t[1], t[2], 1.0, 0.0, 0.0, B, 0)
        else:
            _unit_cross(t[0], t[1], t[2], 0.0, 1.0, 0.0, B, 0)
        _unit_cross(t[0], t[1], t[2], B[0, 0], B[1, 0], B[2, 0], B, 1)
        # The normal equations' lower triangle (as J^T W J's: row a's weighted entry times b's).
        H[:] = 0.0
        g[:] = 0.0
        for i in range(n):
            j[0] = J6[i, 0]
            j[1] = J6[i, 1]
            j[2] = J6[i, 2]
            j[3] = J6[i, 3] * B[0, 0] + J6[i, 4] * B[1, 0] + J6[i, 5] * B[2, 0]
            j[4] = J6[i, 3] * B[0, 1] + J6[i, 4] * B[1, 1] + J6[i, 5] * B[2, 1]
            ri = r[i]
            w = _huber_weight(ri, huber)
            for a in range(5):
                wa = w * j[a]
                g[a] += wa * ri
                for b in range(a + 1):
                    H[a, b] += wa * j[b]
        accepted = False
        gain = 0.0
        for _ in range(4):
            for a in range(5):
                for b in range(a + 1):
                    A[a, b] = H[a, b]
                if lam > 0:
                    A[a, a] *= 1.0 + lam
                dx[a] = g[a]
            if not _cholesky_solve(A, dx):
                break
            for a in range(5):
                dx[a] = -dx[a]
            _rotvec_matrix(dx[0], dx[1], dx[2], dR)
            R_n = np.empty((3, 3))
            for a in range(3):
                for b in range(3):
                    R_n[a, b] = dR[a, 0] * R[0, b] + dR[a, 1] * R[1, b] + dR[a, 2] * R[2, b]
            t_n = np.empty(3)
            for a in range(3):
                t_n[a] = t[a] + (B[a, 0] * dx[3] + B[a, 1] * dx[4])
            nt = np.sqrt(t_n[0] * t_n[0] + t_n[1] * t_n[1] + t_n[2] * t_n[2])
            for a in range(3):
                t_n[a] /= nt
            cost_n = _huber_cost(sampson_distance(R_n, t_n, x_ref, x_cur, f_px, True), huber)
            if cost_n < cost:
                gain = cost - cost_n
                R, t, cost = R_n, t_n, cost_n
                lam *= 0.1
                accepted = True
                break
            lam = max(10.0 * lam, 1e-3)
        # Converged: the step no longer lowers the cost by a part in 10^4.
        if not accepted or gain < 1e-4 * cost:
            break
    return R, t


@njit(cache=True)
def essential_prior(
    px_ref: Any,
    px_cur: Any,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    R_guess: Any,
    t_guess: Any,
    gate_px: float,
    threshold_px: float,
    need: float,
    iterations: int,
) -> tuple[bool, F64, F64, npt.NDArray[np.bool_], F64]:
    """``estimation.essential.essential_from_prior`` up to the metric scale: the (N, 2) pixels'
    normalised rays (``f = (fx + fy) / 2`` turns their distances into pixels), the matches within
    ``gate_px`` (Sampson) of ``(R_guess, t_guess)`` fitted by :func:`essential_lm` (Huber
    threshold ``threshold_px``), the inliers within ``threshold_px`` of the result. Returns
    ``(ok, R, t, inliers, x_cur)`` (``x_cur`` (N, 3) the current rays); ``ok`` False when fewer
    than ``need`` matches pass the gate or the inlier test."""
    n = px_ref.shape[0]
    f = 0.5 * (fx + fy)
    x0 = np.ones((n, 3))
    x1: F64 = np.ones((n, 3))
    for i in range(n):
        x0[i, 0] = (px_ref[i, 0] - cx) / fx
        x0[i, 1] = (px_ref[i, 1] - cy) / fy
        x1[i, 0] = (px_cur[i, 0] - cx) / fx
        x1[i, 1] = (px_cur[i, 1] - cy) / fy
    gate = sampson_distance(R_guess, t_guess, x0, x1, f, False)
    m = 0
    for i in range(n):
        if gate[i] < gate_px:
            m += 1
    if m < need:
        return False, R_guess.copy(), t_guess.copy(), np.zeros(n, np.bool_), x1
    x0g = np.empty((m, 3))
    x1g = np.empty((m, 3))
    k = 0
    for i in range(n):
        if gate[i] < gate_px:
            for a in range(3):
                x0g[k, a] = x0[i, a]
                x1g[k, a] = x1[i, a]
            k += 1
    R, t = essential_lm(R_guess, t_guess, x0g, x1g, f, threshold_px, iterations)
    mask = sampson_distance(R, t, x0, x1, f, False) < threshold_px
    kept = 0
    for i in range(n):
        if mask[i]:
            kept += 1
    return kept >= need, R, t, mask, x1


@njit(cache=True)
def _median_sorted(a: Any) -> float:
    """``estimation.motion.median`` of a non-empty 1-D array (an order statistic, or the mean of
    the two middle ones: bit for bit), NaN when it holds a NaN."""
    b = np.sort(a)
    n = b.shape[0]
    if b[n - 1] != b[n - 1]:
        return np.nan
    h = n // 2
    m: float = b[h] if n % 2 else (b[h - 1] + b[h]) / 2
    return m


@njit(cache=True)
def scale_terms(R: Any, t: Any, x_cur: Any, X: Any, mask: Any) -> tuple[bool, float, F64, F64]:
    """The metric scale ``s`` of a unit translation ``t`` per match ``i`` of ``mask`` whose point
    ``X[i]`` (reference frame) is finite with ``z > 0``: ``x cross (R X + s t) = 0`` with the current
    ray ``x = (x_cur[i, 0], x_cur[i, 1], 1)``, solved where ``b = |x cross t|^2 > 1e-12``. Returns ``(ok,
    median, s_near, b_near)``: the solutions within ``3 * 1.4826 * (MAD + 1e-9)`` of their median
    and their ``b``; ``ok`` False when fewer than 3 matches are valid or fewer than 3 solve."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    n = X.shape[0]
    s_all = np.empty(n)
    bb_all = np.empty(n)
    valid = 0
    m = 0
    for i in range(n):
        X0, X1, X2 = X[i, 0], X[i, 1], X[i, 2]
        if not (mask[i] and np.isfinite(X0) and np.isfinite(X1) and np.isfinite(X2) and X2 > 0):
            continue
        valid += 1
        u, v = x_cur[i, 0], x_cur[i, 1]
        y0 = r00 * X0 + r01 * X1 + r02 * X2
        y1 = r10 * X0 + r11 * X1 + r12 * X2
        y2 = r20 * X0 + r21 * X1 + r22 * X2
        # a = x cross R X, b = x cross t, x = (u, v, 1).
        a0, a1, a2 = v * y2 - y1, y0 - u * y2, u * y1 - v * y0
        b0, b1, b2 = v * t2 - t1, t0 - u * t2, u * t1 - v * t0
        bb = b0 * b0 + b1 * b1 + b2 * b2
        if bb > 1e-12:
            s_all[m] = -(a0 * b0 + a1 * b1 + a2 * b2) / bb
            bb_all[m] = bb
            m += 1
    empty = np.empty(0)
    if valid < 3 or m < 3:
        return False, 0.0, empty, empty
    s_all = s_all[:m]
    s_med = _median_sorted(s_all)
    dev = np.abs(s_all - s_med)
    lim = 3.0 * 1.4826 * (_median_sorted(dev) + 1e-9)
    near = dev < lim
    return True, s_med, s_all[near], bb_all[:m][near]
