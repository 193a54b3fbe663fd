"""PnP by P3P RANSAC, compiled (numba): the minimal solver of Lambda Twist and a 4-point RANSAC
on squared pixel reprojection errors. On the PnP calls of real runs ~0.02-0.05 ms a call, 10x
less than OpenCV's ``solvePnPRansac`` with its AP3P kernel and 20-30x less than with the
iterative one (``bench/p3p.py``).

The solver (Persson & Nordberg, "Lambda Twist: An Accurate Fast Robust Perspective Three Point
(P3P) Solver", ECCV 2018), written here from the paper's maths: with unit bearings ``y_i``, world
points ``x_i``, ``a_ij = |x_i - x_j|^2`` and ``b_ij = y_i . y_j``, the depths ``l`` satisfy
``l_i^2 + l_j^2 - 2 b_ij l_i l_j = a_ij``: three conics ``l^T M_ij l = a_ij``. Two homogeneous
combinations, ``D1 = a23 M12 - a12 M23`` and ``D2 = a23 M13 - a13 M23``, span a pencil whose
degenerate members (the real roots ``gamma`` of the cubic ``det(D1 + gamma D2) = 0``) are line
pairs through all the conics' common points; a real pair is an indefinite one (two non-zero
eigenvalues of opposite signs). On each of its lines ``l1 = w0 l2 + w1 l3``, and one more
equation is a quadratic in ``l2 / l3``; ``l3`` follows from ``a23``. Gauss-Newton on the three
equations polishes the depths; the rotation maps the point differences (and their cross product)
onto the bearing differences. Up to four poses.

The RANSAC: samples of four points (OpenCV's ``cv::RNG`` seeded as on every OpenCV call, so one
input gives one output); the first three are solved, the fourth picks the solution and rejects
the sample when even the best reprojects it beyond the threshold; a candidate is scored on every
point (squared reprojection error in pixels against ``threshold^2``; behind the camera: an
outlier) and kept only with strictly more inliers than the best so far; a new best is refitted
on its inliers (Gauss-Newton on their reprojection, ``_LO_STEPS`` steps) and scored again, and
the refit is kept unless it has fewer inliers (local optimisation: Chum, Matas & Kittler, "Locally
Optimized RANSAC", DAGM 2003); the iteration count adapts to the best inlier ratio as OpenCV's
does (``estimation._ransac_kernel``).

Functions:
    pnp_ransac(points_ref, pts_px, K, threshold_px, ...)  the RANSAC pose and its inliers
    solve_p3p(bearings_cur, points_ref)                   the minimal solver's poses
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation._pose_kernel import pose_gauss_newton
from estimation._ransac_kernel import RNG_SEED, draw_sample, update_iterations
from flightkit.errors import EstimationError

__all__ = ["pnp_ransac", "solve_p3p"]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

_COLLINEAR = 1e-10
"""Three points whose difference vectors make an angle with ``sin^2`` below this are collinear
(or repeated): no pose."""
_LINE_EPS = 1e-10
"""A line ``n . l = 0`` whose first coefficient is below this (relative) cannot give ``l1``."""
_ORTHONORMAL = 1e-9
"""A pose whose rotation is further than this from orthonormal (``R R^T - I``, largest entry) after
its polish is rejected."""
_LO_STEPS = 5
"""Gauss-Newton steps of the local optimisation at most."""
_GN_STEPS = 3
"""Gauss-Newton steps on the depths at most (each kept only when it lowers the residual)."""


@njit(cache=True)
def _det3(M: Any) -> float:
    """The determinant of a 3x3 matrix."""
    return float(
        M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1])
        - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
        + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0])
    )


@njit(cache=True)
def _cofactor_dot(A: Any, B: Any) -> float:
    """``sum_ij cof(A)_ij B_ij`` of 3x3 matrices: ``d det(A + g B) / dg`` at ``g = 0``."""
    s = 0.0
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            s += (A[i1, j1] * A[i2, j2] - A[i1, j2] * A[i2, j1]) * B[i, j]
    return s


@njit(cache=True)
def _cubic_real_roots(b: float, c: float, d: float, out: Any) -> int:
    """The real roots of ``r^3 + b r^2 + c r + d`` (closed form, then Newton) into ``out``;
    returns how many (1 or 3; 0 for a non-finite input)."""
    p = c - b * b / 3.0
    q = 2.0 * b * b * b / 27.0 - b * c / 3.0 + d
    disc = 0.25 * q * q + p * p * p / 27.0
    shift = -b / 3.0
    if not math.isfinite(disc):
        return 0
    if disc > 0.0:
        u = np.cbrt(-0.5 * q - math.copysign(math.sqrt(disc), q))
        out[0] = shift + (u - p / (3.0 * u) if u != 0.0 else 0.0)
        k = 1
    else:
        m = 2.0 * math.sqrt(-p / 3.0) if p < 0.0 else 0.0
        if p * m == 0.0:  # a triple root (p = 0, or too small to tell)
            out[0] = shift
            k = 1
        else:
            arg = min(1.0, max(-1.0, 3.0 * q / (p * m)))
            theta = math.acos(arg) / 3.0
            for i in range(3):
                out[i] = shift + m * math.cos(theta - 2.0 * math.pi * i / 3.0)
            k = 3
    for i in range(k):
        r = out[i]
        f = ((r + b) * r + c) * r + d
        for _ in range(2):
            df = (3.0 * r + 2.0 * b) * r + c
            if df == 0.0:
                break
            r2 = r - f / df
            f2 = ((r2 + b) * r2 + c) * r2 + d
            if not abs(f2) < abs(f):
                break
            r, f = r2, f2
        out[i] = r
    return k


@njit(cache=True)
def _eigenvector(D: Any, s: float, v: Any) -> bool:
    """The unit eigenvector of the symmetric 3x3 ``D`` for its simple eigenvalue ``s`` into
    ``v``: the largest cross product of two rows of ``D - s I``; False when all vanish."""
    best = 0.0
    for pair in range(3):
        i, j = (0, 1) if pair == 0 else ((0, 2) if pair == 1 else (1, 2))
        a0, a1, a2 = D[i, 0], D[i, 1], D[i, 2]
        b0, b1, b2 = D[j, 0], D[j, 1], D[j, 2]
        if i == 0:
            a0 -= s
        elif i == 1:
            a1 -= s
        if j == 1:
            b1 -= s
        else:
            b2 -= s
        c0 = a1 * b2 - a2 * b1
        c1 = a2 * b0 - a0 * b2
        c2 = a0 * b1 - a1 * b0
        nn = c0 * c0 + c1 * c1 + c2 * c2
        if nn > best:
            best = nn
            v[0], v[1], v[2] = c0, c1, c2
    if not best > 0.0:
        return False
    inv = 1.0 / math.sqrt(best)
    for k in range(3):
        v[k] *= inv
    return True


@njit(cache=True)
def _residuals(l1: float, l2: float, l3: float, a: Any, b: Any) -> tuple[float, float, float]:
    """The three distance equations' residuals (m^2) at depths ``l1, l2, l3``; ``a``, ``b``:
    ``(a12, a13, a23)`` and ``(b12, b13, b23)``."""
    return (
        l1 * l1 + l2 * l2 - 2.0 * b[0] * l1 * l2 - a[0],
        l1 * l1 + l3 * l3 - 2.0 * b[1] * l1 * l3 - a[1],
        l2 * l2 + l3 * l3 - 2.0 * b[2] * l2 * l3 - a[2],
    )


@njit(cache=True)
def _polish_depths(l1: float, l2: float, l3: float, a: Any, b: Any) -> tuple[float, float, float]:
    """Gauss-Newton (3 equations, 3 unknowns: Newton) on the depths, each step kept only when it
    lowers the squared residual."""
    r1, r2, r3 = _residuals(l1, l2, l3, a, b)
    e = r1 * r1 + r2 * r2 + r3 * r3
    for _ in range(_GN_STEPS):
        if e == 0.0:
            break
        # J = d(r1, r2, r3) / d(l1, l2, l3); J[0, 2] = J[1, 1] = J[2, 0] = 0.
        j00, j01 = 2.0 * (l1 - b[0] * l2), 2.0 * (l2 - b[0] * l1)
        j10, j12 = 2.0 * (l1 - b[1] * l3), 2.0 * (l3 - b[1] * l1)
        j21, j22 = 2.0 * (l2 - b[2] * l3), 2.0 * (l3 - b[2] * l2)
        det = -j00 * j12 * j21 - j01 * j10 * j22
        if not abs(det) > 0.0:
            break
        # Cramer's rule for J d = r.
        d1 = (-r1 * j12 * j21 - j01 * (r2 * j22 - j12 * r3)) / det
        d2 = (j00 * (r2 * j22 - j12 * r3) - r1 * j10 * j22) / det
        d3 = (r1 * j10 * j21 - j00 * r2 * j21 - j01 * j10 * r3) / det
        n1, n2, n3 = l1 - d1, l2 - d2, l3 - d3
        s1, s2, s3 = _residuals(n1, n2, n3, a, b)
        en = s1 * s1 + s2 * s2 + s3 * s3
        if not en < e:
            break
        l1, l2, l3, r1, r2, r3, e = n1, n2, n3, s1, s2, s3, en
    return l1, l2, l3


@njit(cache=True)
def _solve(y: Any, x: Any, Rs: Any, ts: Any) -> int:
    """The poses ``(R_cur_ref, t_cur_ref)`` with ``l_i y[i] = R x[i] + t`` at positive depths
    ``l_i`` (``y``: (3, 3) unit bearings in rows, ``x``: (3, 3) points in rows) into ``Rs``
    (4, 3, 3) and ``ts`` (4, 3); returns how many (0-4; 0 for collinear or repeated points)."""
    d1 = np.empty(3)  # x1 - x2
    d2 = np.empty(3)  # x1 - x3
    a = np.zeros(3)  # a12, a13, a23
    for k in range(3):
        d1[k] = x[0, k] - x[1, k]
        d2[k] = x[0, k] - x[2, k]
        d3 = x[1, k] - x[2, k]
        a[0] += d1[k] * d1[k]
        a[1] += d2[k] * d2[k]
        a[2] += d3 * d3
    nx = np.empty(3)  # d1 x d2
    nx[0] = d1[1] * d2[2] - d1[2] * d2[1]
    nx[1] = d1[2] * d2[0] - d1[0] * d2[2]
    nx[2] = d1[0] * d2[1] - d1[1] * d2[0]
    nn = nx[0] * nx[0] + nx[1] * nx[1] + nx[2] * nx[2]
    if not nn > _COLLINEAR * a[0] * a[1]:  # also NaN
        return 0
    b = np.empty(3)  # b12, b13, b23
    b[0] = y[0, 0] * y[1, 0] + y[0, 1] * y[1, 1] + y[0, 2] * y[1, 2]
    b[1] = y[0, 0] * y[2, 0] + y[0, 1] * y[2, 1] + y[0, 2] * y[2, 2]
    b[2] = y[1, 0] * y[2, 0] + y[1, 1] * y[2, 1] + y[1, 2] * y[2, 2]
    a12, a13, a23 = a[0], a[1], a[2]
    b12, b13, b23 = b[0], b[1], b[2]
    D1 = np.zeros((3, 3))
    D1[0, 0] = a23
    D1[0, 1] = D1[1, 0] = -a23 * b12
    D1[1, 1] = a23 - a12
    D1[1, 2] = D1[2, 1] = a12 * b23
    D1[2, 2] = -a12
    D2 = np.zeros((3, 3))
    D2[0, 0] = a23
    D2[0, 2] = D2[2, 0] = -a23 * b13
    D2[1, 1] = -a13
    D2[1, 2] = D2[2, 1] = a13 * b23
    D2[2, 2] = a23 - a13
    # The pencil as base + r lead with the larger determinant leading (det(D2) vanishes for
    # some configurations): the cubic det(base + r lead) = k3 r^3 + k2 r^2 + k1 r + k0.
    det1, det2 = _det3(D1), _det3(D2)
    if abs(det2) >= abs(det1):
        base, lead, k3, k0 = D1, D2, det2, det1
    else:
        base, lead, k3, k0 = D2, D1, det1, det2
    roots = np.zeros(3)
    if k3 == 0.0:  # both singular: D1 is a degenerate member already
        nr = 1
    else:
        nr = _cubic_real_roots(_cofactor_dot(lead, base) / k3, _cofactor_dot(base, lead) / k3, k0 / k3, roots)
    # Of the real roots, the most indefinite member (eigenvalues sigma1 sigma2 < 0, as equal in
    # size as possible): a real line pair, the best separated.
    D0 = np.empty((3, 3))
    best, best_score = -1, 0.0
    for i in range(nr):
        r = roots[i]
        m = 0.0
        f = 0.0
        for p in range(3):
            for q in range(3):
                v = base[p, q] + r * lead[p, q]
                f += v * v
            q1, q2 = (p + 1) % 3, (p + 2) % 3
            off = base[q1, q2] + r * lead[q1, q2]
            m += (base[q1, q1] + r * lead[q1, q1]) * (base[q2, q2] + r * lead[q2, q2]) - off * off
        if f > 0.0 and m / f < best_score:
            best, best_score = i, m / f
    if best < 0:
        return 0
    r = roots[best]
    tr = 0.0
    m = 0.0
    for p in range(3):
        for q in range(3):
            D0[p, q] = base[p, q] + r * lead[p, q]
        tr += D0[p, p]
    for p in range(3):
        q1, q2 = (p + 1) % 3, (p + 2) % 3
        m += D0[q1, q1] * D0[q2, q2] - D0[q1, q2] * D0[q2, q1]
    # Non-zero eigenvalues: the roots of s^2 - tr s + m (m < 0: real, opposite signs).
    sigma1 = 0.5 * (tr + math.copysign(math.sqrt(tr * tr - 4.0 * m), tr))
    sigma2 = m / sigma1
    e1 = np.empty(3)
    e2 = np.empty(3)
    if not (_eigenvector(D0, sigma1, e1) and _eigenvector(D0, sigma2, e2)):
        return 0
    s = math.sqrt(-sigma2 / sigma1)
    # The rows of the inverse of [d1, d2, nx] (columns): (d2 x nx, nx x d1, d1 x d2) / |nx|^2.
    Xi = np.empty((3, 3))
    Xi[0, 0] = (d2[1] * nx[2] - d2[2] * nx[1]) / nn
    Xi[0, 1] = (d2[2] * nx[0] - d2[0] * nx[2]) / nn
    Xi[0, 2] = (d2[0] * nx[1] - d2[1] * nx[0]) / nn
    Xi[1, 0] = (nx[1] * d1[2] - nx[2] * d1[1]) / nn
    Xi[1, 1] = (nx[2] * d1[0] - nx[0] * d1[2]) / nn
    Xi[1, 2] = (nx[0] * d1[1] - nx[1] * d1[0]) / nn
    for k in range(3):
        Xi[2, k] = nx[k] / nn
    n = 0
    for line in range(2):
        sign = 1.0 if line == 0 else -1.0
        # The line (e1 + sign s e2) . l = 0: l1 = w0 l2 + w1 l3.
        c0 = e1[0] + sign * s * e2[0]
        c1 = e1[1] + sign * s * e2[1]
        c2 = e1[2] + sign * s * e2[2]
        if not abs(c0) > _LINE_EPS * (abs(c1) + abs(c2)):
            continue
        w0, w1 = -c1 / c0, -c2 / c0
        # a23 (eq13) - a13 (eq23) = 0 with tau = l2 / l3, divided by l3^2.
        qa = a23 * w0 * w0 - a13
        qb = 2.0 * (a23 * (w0 * w1 - b13 * w0) + a13 * b23)
        qc = a23 * (w1 * w1 - 2.0 * b13 * w1 + 1.0) - a13
        nt = 0
        tau0 = tau1 = 0.0
        if abs(qa) <= 1e-14 * (abs(qb) + abs(qc)):
            if qb != 0.0:
                tau0 = -qc / qb
                nt = 1
        else:
            disc = qb * qb - 4.0 * qa * qc
            if disc < 0.0:
                continue
            qq = -0.5 * (qb + math.copysign(math.sqrt(disc), qb))
            tau0 = qq / qa
            nt = 1
            if qq != 0.0:
                tau1 = qc / qq
                nt = 2
        for it in range(nt):
            tau = tau0 if it == 0 else tau1
            if not tau > 0.0:
                continue
            den = tau * tau - 2.0 * b23 * tau + 1.0
            if not den > 0.0:
                continue
            l3 = math.sqrt(a23 / den)
            l2 = tau * l3
            l1 = w0 * l2 + w1 * l3
            if not l1 > 0.0:
                continue
            l1, l2, l3 = _polish_depths(l1, l2, l3, a, b)
            if not (l1 > 0.0 and l2 > 0.0 and l3 > 0.0) or n >= 4:
                continue
            if _pose(l1, l2, l3, y, x, Xi, Rs[n], ts[n]):
                n += 1
    return n


@njit(cache=True)
def _pose(l1: float, l2: float, l3: float, y: Any, x: Any, Xi: Any, R: Any, t: Any) -> bool:
    """``R`` (the nearest rotation) and ``t`` from the depths: ``R [d1, d2, d1 x d2] = [e1, e2,
    e1 x e2]`` with ``d`` the point and ``e`` the scaled bearing differences; ``Xi``: the inverse
    of the left matrix. False when the result is not a finite proper rotation."""
    e1 = np.empty(3)
    e2 = np.empty(3)
    e3 = np.empty(3)
    for k in range(3):
        e1[k] = l1 * y[0, k] - l2 * y[1, k]
        e2[k] = l1 * y[0, k] - l3 * y[2, k]
    e3[0] = e1[1] * e2[2] - e1[2] * e2[1]
    e3[1] = e1[2] * e2[0] - e1[0] * e2[2]
    e3[2] = e1[0] * e2[1] - e1[1] * e2[0]
    for i in range(3):
        for j in range(3):
            R[i, j] = e1[i] * Xi[0, j] + e2[i] * Xi[1, j] + e3[i] * Xi[2, j]
    # The nearest rotation (polar factor) by Newton: R <- (R + R^-T) / 2, R^-T = cof(R) / det(R).
    C = np.empty((3, 3))
    for _ in range(2):
        det = _det3(R)
        if not det > 0.0:
            return False
        for i in range(3):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            for j in range(3):
                j1, j2 = (j + 1) % 3, (j + 2) % 3
                C[i, j] = (R[i1, j1] * R[i2, j2] - R[i1, j2] * R[i2, j1]) / det
        for i in range(3):
            for j in range(3):
                R[i, j] = 0.5 * (R[i, j] + C[i, j])
    # Depths that fit the points (to rounding) give a rotation already; one that two Newton
    # steps left far from it came from depths that do not: no pose (also NaN).
    for i in range(3):
        for j in range(i + 1):
            d = R[i, 0] * R[j, 0] + R[i, 1] * R[j, 1] + R[i, 2] * R[j, 2] - (1.0 if i == j else 0.0)
            if not abs(d) <= _ORTHONORMAL:
                return False
    ok = True
    for i in range(3):
        t[i] = l1 * y[0, i] - (R[i, 0] * x[0, 0] + R[i, 1] * x[0, 1] + R[i, 2] * x[0, 2])
        ok &= math.isfinite(t[i])
    return ok


@njit(cache=True)
def _error2(R: Any, t: Any, X: Any, uv: Any, i: int, fx: float, fy: float, cx: float, cy: float) -> float:
    """Point ``i``'s squared reprojection error (px^2) under ``(R, t)``; inf behind the camera."""
    x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
    z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
    if not z > 0.0:
        return math.inf
    du = fx * (R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]) / z + cx - uv[i, 0]
    dv = fy * (R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]) / z + cy - uv[i, 1]
    return float(du * du + dv * dv)


@njit(cache=True)
def _local_fit(X: Any, uv: Any, mask: Any, R: Any, t: Any, fx: float, fy: float, cx: float, cy: float) -> F64:
    """The pose of ``R``, ``t`` refitted on the points of ``mask``: Gauss-Newton on their pixel
    reprojection errors (plain least squares, ``_LO_STEPS`` steps at most), as a (4, 4) matrix."""
    m = 0
    for i in range(mask.shape[0]):
        m += int(mask[i])
    Xi = np.empty((m, 3))
    ui = np.empty((m, 2))
    k = 0
    for i in range(mask.shape[0]):
        if mask[i]:
            for c in range(3):
                Xi[k, c] = X[i, c]
            ui[k, 0], ui[k, 1] = uv[i, 0], uv[i, 1]
            k += 1
    T0 = np.eye(4)
    for r in range(3):
        T0[r, 3] = t[r]
        for c in range(3):
            T0[r, c] = R[r, c]
    none = np.empty(0)  # no disparities, no translation weights, exact points
    return pose_gauss_newton(Xi, T0, ui, none, none, none, fx, fy, cx, cy, 0.0, 1e9, _LO_STEPS, 1e-12, 6)


@njit(cache=True)
def _ransac(
    X: Any, uv: Any, fx: float, fy: float, cx: float, cy: float, thr2: float, confidence: float, max_iters: int
) -> tuple[int, F64, F64, Any]:
    """4-point RANSAC (see the module docstring) over points ``X`` (N, 3) and their pixels ``uv``
    (N, 2), N >= 4; returns the best inlier count (0: no sample passed), its ``R``, ``t`` and
    inlier mask."""
    n = X.shape[0]
    Y = np.empty((n, 3))
    for i in range(n):
        a, b = (uv[i, 0] - cx) / fx, (uv[i, 1] - cy) / fy
        s = 1.0 / math.sqrt(a * a + b * b + 1.0)
        Y[i, 0], Y[i, 1], Y[i, 2] = a * s, b * s, s
    best_R = np.eye(3)
    best_t = np.zeros(3)
    best_mask = np.zeros(n, np.bool_)
    mask = np.zeros(n, np.bool_)
    Rs = np.empty((4, 3, 3))
    ts = np.empty((4, 3))
    ys = np.empty((3, 3))
    xs = np.empty((3, 3))
    idx = np.empty(4, np.int64)
    state = RNG_SEED
    best = 0
    niters = max(max_iters, 1)
    it = 0
    while it < niters:
        it += 1
        state = draw_sample(state, n, idx)
        for i in range(3):
            for k in range(3):
                ys[i, k] = Y[idx[i], k]
                xs[i, k] = X[idx[i], k]
        ns = _solve(ys, xs, Rs, ts)
        pick, pick_e2 = -1, thr2
        for m in range(ns):
            e2 = _error2(Rs[m], ts[m], X, uv, idx[3], fx, fy, cx, cy)
            if e2 <= pick_e2:
                pick, pick_e2 = m, e2
        if pick < 0:
            continue
        good = 0
        for i in range(n):
            inl = _error2(Rs[pick], ts[pick], X, uv, i, fx, fy, cx, cy) <= thr2
            mask[i] = inl
            good += int(inl)
        if good > best and good >= 4:
            best_mask, mask = mask, best_mask
            for r in range(3):
                best_t[r] = ts[pick, r]
                for c in range(3):
                    best_R[r, c] = Rs[pick, r, c]
            best = good
            if good >= 6:
                # A new best: refit on its inliers and re-score (local optimisation), kept when it
                # does not lose inliers.
                T = _local_fit(X, uv, best_mask, best_R, best_t, fx, fy, cx, cy)
                good2 = 0
                for i in range(n):
                    inl = _error2(T[:3, :3], T[:3, 3], X, uv, i, fx, fy, cx, cy) <= thr2
                    mask[i] = inl
                    good2 += int(inl)
                if good2 >= good:
                    best_mask, mask = mask, best_mask
                    for r in range(3):
                        best_t[r] = T[r, 3]
                        for c in range(3):
                            best_R[r, c] = T[r, c]
                    best = good = good2
            niters = update_iterations(confidence, (n - good) / n, 4, niters)
    return best, best_R, best_t, best_mask


def solve_p3p(bearings_cur: npt.ArrayLike, points_ref: npt.ArrayLike) -> list[tuple[F64, F64]]:
    """Every pose that puts three reference-frame points on three bearings of the current camera
    at positive depths (Lambda Twist; see the module docstring).

    Args:
        bearings_cur: (3, 3) directions in the current camera frame, one a row (any length > 0).
        points_ref: (3, 3) the points in the reference frame, metres, one a row.

    Returns:
        Up to four ``(R_cur_ref (3, 3), t_cur_ref (3,) m)`` with ``depth_i * bearing_i = R
        point_i + t``; none for collinear or repeated points (or a configuration with no real
        pose).

    Raises:
        EstimationError: the arrays are not (3, 3).
    """
    y = np.array(bearings_cur, dtype=np.float64)
    x = np.ascontiguousarray(points_ref, dtype=np.float64)
    if y.shape != (3, 3) or x.shape != (3, 3):
        raise EstimationError(f"solve_p3p got bearings {y.shape} and points {x.shape}; give (3, 3) each, one a row")
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    Rs = np.empty((4, 3, 3))
    ts = np.empty((4, 3))
    n = _solve(y, x, Rs, ts)
    return [(Rs[i].copy(), ts[i].copy()) for i in range(n)]


def pnp_ransac(
    points_ref: npt.ArrayLike,
    pts_px: npt.ArrayLike,
    K: npt.ArrayLike,
    threshold_px: float = 3.0,
    confidence: float = 0.999,
    max_iters: int = 100,
) -> tuple[bool, F64, F64, Mask]:
    """The pose of the current camera from reference-frame points and their pixels by P3P RANSAC
    (see the module docstring). Deterministic: the same input gives the same output.

    Args:
        points_ref: (N, 3) points in the reference camera frame, metres.
        pts_px: (N, 2) their pixels in the current (undistorted) image.
        K: (3, 3) intrinsic matrix (fx, fy, cx, cy are used).
        threshold_px: inlier threshold on the reprojection error, px.
        confidence: the probability of drawing one all-inlier sample that sizes the iterations.
        max_iters: samples drawn at most.

    Returns:
        ``(ok, R_cur_ref (3, 3), t_cur_ref (3,) m, inliers (N,) bool)``: the best sample's pose
        (``x_cur = R x_ref + t``) and the points it reprojects within ``threshold_px``; ``ok`` is
        False (identity, zero, no inliers) with fewer than 4 points or when no sample's pose
        reprojected its fourth point within the threshold.

    Raises:
        EstimationError: mismatched arrays, a threshold that is not positive, a confidence
            outside (0, 1), or a ``K`` without positive focal lengths.
    """
    X = np.ascontiguousarray(points_ref, dtype=np.float64).reshape(-1, 3)
    uv = np.ascontiguousarray(pts_px, dtype=np.float64).reshape(-1, 2)
    Km = np.asarray(K, dtype=np.float64)
    n = len(X)
    if len(uv) != n:
        raise EstimationError(f"pnp_ransac got {n} points and {len(uv)} pixels; give one pixel per point")
    if not threshold_px > 0:
        raise EstimationError(f"pnp_ransac threshold_px is {threshold_px}; use a positive threshold (3 px is typical)")
    if not 0 < confidence < 1:
        raise EstimationError(f"pnp_ransac confidence is {confidence}; use a probability in (0, 1) (0.999 is typical)")
    fx, fy, cx, cy = float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2])
    if not (fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()):
        raise EstimationError(
            f"pnp_ransac got K with fx={fx}, fy={fy}, cx={cx}, cy={cy}; give a pinhole K (fx, fy > 0, all finite)"
        )
    if n < 4:
        return False, np.eye(3), np.zeros(3), np.zeros(n, dtype=bool)
    best, R, t, mask = _ransac(X, uv, fx, fy, cx, cy, float(threshold_px) ** 2, float(confidence), int(max_iters))
    if best < 4:
        return False, np.eye(3), np.zeros(3), np.zeros(n, dtype=bool)
    return True, R, t, mask
