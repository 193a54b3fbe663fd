"""Compiled inner loops of the visual odometry (numba, nopython, float64, no fastmath).

The per-frame work of the keyframe pipelines is a handful of small loops over ~200 tracked
points: transform, project, residuals, Huber weights, Jacobian rows, depth lookups. Written
as numpy expressions they are dozens of calls of 2-20 us each per frame; here each is one
compiled loop. The callers (``estimation.pnp``, ``estimation.essential``, ``estimation.pipeline``) keep their
signatures; only their bodies call these.

Exactness: every kernel reproduces the arithmetic of the numpy code it replaced, operation
by operation, so the results are equal bit for bit (``tests/unit/test_kernels.py``). Two
details make that hold: elementwise IEEE operations are the same in numba and numpy, and the
rigid transform ``X @ R.T + t`` that numpy hands to OpenBLAS is a chain of fused
multiply-adds in the order of the inner index (OpenBLAS's kernels on FMA machines), which
:func:`_fma` spells out. The pose polish's Gauss-Newton loop and the essential matrix's
Levenberg-Marquardt loop, which depart from this on purpose (their normal equations are summed
point by point), are in ``estimation._pose_kernel`` and ``estimation._essential_kernel``.

Compiled once and cached on disk next to this module (``__pycache__``); the first import in
a fresh environment compiles them (~10 s of CPU once: `warm_up` of all five methods took
11.8 s with a cold cache and 1.8 s with a warm one, imports included; docs/estimation-log.md,
eighth and eleventh passes).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = [
    "depth_at",
    "flow_hypotheses",
    "flow_refit",
    "fuse_points",
    "invert_rigid",
    "project",
    "reproj_err2",
    "sampson_distance",
    "sampson_jacobian",
    "transform",
]


def _fma_typer(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    """Typing and code of :data:`_fma`: ``a * b + c`` rounded once (LLVM's ``llvm.fma.f64``)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        d = ir.DoubleType()
        fma_fn = ir.FunctionType(d, [d, d, d])
        fn = cgutils.get_or_insert_function(builder.module, fma_fn, "llvm.fma.f64")  # type: ignore[no-untyped-call]
        return builder.call(fn, args)

    return sig, codegen


F64 = npt.NDArray[np.float64]

_fma: Any = intrinsic(_fma_typer)
"""``_fma(a, b, c)`` in compiled code: the fused multiply-add of OpenBLAS's FMA kernels."""


@njit(cache=True)
def _dot3(A: Any, i: int, B: Any, j: int) -> float:
    """``A[i] . B[j]`` (3-vectors) as OpenBLAS rounds the product ``A @ B.T`` of an (N, 3) ``A``:
    fused multiply-adds in index order, or, for a single row (its matrix-vector path), the
    middle term first."""
    if A.shape[0] == 1:
        return float(_fma(A[i, 2], B[j, 2], _fma(A[i, 0], B[j, 0], A[i, 1] * B[j, 1])))
    return float(_fma(A[i, 2], B[j, 2], _fma(A[i, 1], B[j, 1], A[i, 0] * B[j, 0])))


@njit(cache=True)
def _xform(X: Any, T: Any, i: int, j: int) -> float:
    """Row ``j`` of ``R @ X[i] + t`` as numpy's ``X @ T[:3, :3].T + T[:3, 3]`` rounds it."""
    return float(_dot3(X, i, T, j) + T[j, 3])


@njit(cache=True)
def transform(X: Any, T: Any) -> F64:
    """``X @ T[:3, :3].T + T[:3, 3]`` for (N, 3) points and a (4, 4) (or (3, 4)) transform."""
    n = X.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        out[i, 0] = _xform(X, T, i, 0)
        out[i, 1] = _xform(X, T, i, 1)
        out[i, 2] = _xform(X, T, i, 2)
    return out


@njit(cache=True)
def fuse_points(X: Any, w: Any, idx: Any, X_cur: Any, w_cur: Any, T_ref_cur: Any) -> None:
    """Fuse measurements ``X_cur`` (M, 3, current camera; weights ``w_cur``) of the points ``idx`` of
    ``X`` (N, 3, reference frame, fusion weights ``w``) in place: each moved by ``T_ref_cur`` and
    averaged with the point by weight, the weights summed (``estimation.frontend.FrontEnd.fuse``'s
    numpy steps, the same bits)."""
    for k in range(idx.shape[0]):
        i = idx[k]
        w_old = w[i]
        wsum = w_old + w_cur[k]
        for j in range(3):
            X[i, j] = (X[i, j] * w_old + _xform(X_cur, T_ref_cur, k, j) * w_cur[k]) / wsum
        w[i] = wsum


@njit(cache=True)
def invert_rigid(T: Any) -> F64:
    """The inverse of a rigid (4, 4) transform: ``R.T`` and ``-R.T @ t`` (summed in the order of
    numpy's product, the same bits), the last row ``0 0 0 1``."""
    Ti = np.zeros((4, 4))
    for r in range(3):
        for c in range(3):
            Ti[r, c] = T[c, r]
        Ti[r, 3] = -(T[0, r] * T[0, 3] + T[1, r] * T[1, 3] + T[2, r] * T[2, 3])
    Ti[3, 3] = 1.0
    return Ti


@njit(cache=True)
def reproj_err2(X: Any, T: Any, uv: Any, fx: float, fy: float, cx: float, cy: float, z_min: float) -> F64:
    """Squared reprojection error (px^2) of (N, 3) reference points under ``T`` against (N, 2)
    pixels; ``inf`` where the point is at or behind ``z = z_min``."""
    n = X.shape[0]
    out = np.empty(n)
    for i in range(n):
        z = _xform(X, T, i, 2)
        zc = z if z > z_min or z != z else z_min
        du = fx * _xform(X, T, i, 0) / zc + cx - uv[i, 0]
        dv = fy * _xform(X, T, i, 1) / zc + cy - uv[i, 1]
        out[i] = du * du + dv * dv if z > z_min else np.inf
    return out


@njit(cache=True)
def project(
    X: Any, T: Any, fx: float, fy: float, cx: float, cy: float, width: float, height: float, margin: float
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Pinhole projection of (N, 3) points under ``T``: (N, 2) float32 pixels and (N,) bool
    "in front (z > 0.05 m) and within ``margin`` px of the image"."""
    n = X.shape[0]
    uv = np.empty((n, 2), np.float32)
    inside = np.empty(n, np.bool_)
    for i in range(n):
        z = _xform(X, T, i, 2)
        front = z > 0.05
        zc = z if front else 1.0
        u = fx * _xform(X, T, i, 0) / zc + cx
        v = fy * _xform(X, T, i, 1) / zc + cy
        uv[i, 0] = u
        uv[i, 1] = v
        inside[i] = front and u > -margin and u < width + margin and v > -margin and v < height + margin
    return uv, inside


@njit(cache=True)
def depth_at(depth: Any, u: Any, v: Any, min_m: float, max_m: float) -> F64:
    """Depth (float64 metres) of a float32 depth image at the pixels nearest (rounded half to
    even) to ``(u, v)``; NaN outside a 1-pixel border, where the pixel has no depth (<= 0),
    outside ``[min_m, max_m]``, or at a depth edge (the spread of the 4 neighbours, which
    must all have depth, reaches ``0.03 z + 0.01``)."""
    h, w = depth.shape
    n = u.shape[0]
    out = np.empty(n)
    for i in range(n):
        out[i] = np.nan
        fu = np.rint(u[i])
        fv = np.rint(v[i])
        if not (fu >= 1 and fu < w - 1 and fv >= 1 and fv < h - 1):
            continue
        iu = int(fu)
        iv = int(fv)
        c = np.float64(depth[iv, iu])
        a = depth[iv - 1, iu]
        b = depth[iv + 1, iu]
        left = depth[iv, iu - 1]
        right = depth[iv, iu + 1]
        if a != a or b != b or left != left or right != right:
            continue
        hi = np.float64(max(max(a, b), max(left, right)))
        lo = np.float64(min(min(a, b), min(left, right)))
        if c > 0 and lo > 0 and hi - lo < 0.03 * c + 0.01 and c >= min_m and c <= max_m:
            out[i] = c
    return out


@njit(cache=True)
def sampson_distance(R: Any, t: Any, x_ref: Any, x_cur: Any, f_px: float, signed: bool) -> F64:
    """Sampson distance (pixels) of (N, 3) normalised ray pairs (z = 1) to the epipolar
    geometry of ``(R, t)``: signed ``e * (f / sqrt(den))`` or ``f * |e| / sqrt(den)``."""
    E = np.empty((3, 3))
    # E = [t]x @ R as numpy's product of the skew matrix and R rounds it (one zero term).
    for j in range(3):
        E[0, j] = _fma(t[1], R[2, j], -t[2] * R[1, j])
        E[1, j] = _fma(-t[0], R[2, j], t[2] * R[0, j])
        E[2, j] = _fma(t[0], R[1, j], -t[1] * R[0, j])
    Et = np.ascontiguousarray(E.T)
    n = x_ref.shape[0]
    out = np.empty(n)
    for i in range(n):
        a0 = _dot3(x_ref, i, E, 0)  # E x_ref
        a1 = _dot3(x_ref, i, E, 1)
        a2 = _dot3(x_ref, i, E, 2)
        b0 = _dot3(x_cur, i, Et, 0)  # E^T x_cur
        b1 = _dot3(x_cur, i, Et, 1)
        # x_cur . (E x_ref) in the order of numpy's einsum for three terms.
        e = (x_cur[i, 0] * a0 + x_cur[i, 2] * a2) + x_cur[i, 1] * a1
        den = a0 * a0 + a1 * a1 + b0 * b0 + b1 * b1
        s = np.sqrt(den if den > 1e-300 or den != den else 1e-300)
        out[i] = e * (f_px / s) if signed else f_px * abs(e) / s
    return out


@njit(cache=True)
def sampson_jacobian(R: Any, t: Any, x_ref: Any, x_cur: Any, f_px: float, J: Any) -> F64:
    """Signed Sampson residuals (px) of (N, 3) ray pairs under ``(R, t)`` and, into ``J``
    (N, 6), their Jacobian in a left rotation increment and a translation increment (the
    formulas of ``estimation.essential._sampson_jacobian``, term by term)."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    n = x_ref.shape[0]
    res = np.empty(n)
    for i in range(n):
        u0 = x_ref[i, 0]
        v0 = x_ref[i, 1]
        u1 = x_cur[i, 0]
        v1 = x_cur[i, 1]
        y0 = r00 * u0 + r01 * v0 + r02
        y1 = r10 * u0 + r11 * v0 + r12
        y2 = r20 * u0 + r21 * v0 + r22
        P0 = t1 * y2 - t2 * y1
        P1 = t2 * y0 - t0 * y2
        P2 = t0 * y1 - t1 * y0
        c0 = t2 * v1 - t1
        c1 = t0 - t2 * u1
        c2 = t1 * u1 - t0 * v1
        Q0 = r00 * c0 + r10 * c1 + r20 * c2
        Q1 = r01 * c0 + r11 * c1 + r21 * c2
        e = u1 * P0 + v1 * P1 + P2
        den = P0 * P0 + P1 * P1 + Q0 * Q0 + Q1 * Q1
        if not (den > 1e-300 or den != den):
            den = 1e-300
        inv = f_px / np.sqrt(den)
        k = e / den
        ty = t0 * y0 + t1 * y1 + t2 * y2
        py = P0 * y0 + P1 * y1
        g = Q0 * (r10 * c2 - r20 * c1) + Q1 * (r11 * c2 - r21 * c1) + ty * P0 - py * t0
        J[i, 0] = (y1 * c2 - y2 * c1 - k * g) * inv
        g = Q0 * (r20 * c0 - r00 * c2) + Q1 * (r21 * c0 - r01 * c2) + ty * P1 - py * t1
        J[i, 1] = (y2 * c0 - y0 * c2 - k * g) * inv
        g = Q0 * (r00 * c1 - r10 * c0) + Q1 * (r01 * c1 - r11 * c0) - py * t2
        J[i, 2] = (y0 * c1 - y1 * c0 - k * g) * inv
        g = Q0 * (r10 - r20 * v1) + Q1 * (r11 - r21 * v1) - P1 * y2
        J[i, 3] = (y1 - y2 * v1 - k * g) * inv
        g = Q0 * (r20 * u1 - r00) + Q1 * (r21 * u1 - r01) + P0 * y2
        J[i, 4] = (y2 * u1 - y0 - k * g) * inv
        g = Q0 * (r00 * v1 - r10 * u1) + Q1 * (r01 * v1 - r11 * u1) + P1 * y0 - P0 * y1
        J[i, 5] = (y0 * v1 - y1 * u1 - k * g) * inv
        res[i] = e * inv
    return res


@njit(cache=True)
def _solve6(M: Any, y: Any) -> bool:
    """Solve the square system ``M x = y`` in place (``y`` becomes ``x``) by Gaussian
    elimination with partial pivoting (LAPACK's ``dgesv`` algorithm, unblocked); ``M`` is
    overwritten. False when a pivot is zero. (Sizes are read from ``M``: constant 6x6
    bounds made LLVM unroll every loop and compile for seconds.)"""
    m = M.shape[0]
    for c in range(m):
        p = c
        best = abs(M[c, c])
        for r in range(c + 1, m):
            if abs(M[r, c]) > best:
                best = abs(M[r, c])
                p = r
        if best == 0.0:
            return False
        if p != c:
            for k in range(m):
                tmp = M[c, k]
                M[c, k] = M[p, k]
                M[p, k] = tmp
            tmp = y[c]
            y[c] = y[p]
            y[p] = tmp
        inv = 1.0 / M[c, c]
        for r in range(c + 1, m):
            f = M[r, c] * inv
            if f != 0.0:
                for k in range(c + 1, m):
                    M[r, k] -= f * M[c, k]
                y[r] -= f * y[c]
    for c in range(m - 1, -1, -1):
        s = y[c]
        for k in range(c + 1, m):
            s -= M[c, k] * y[k]
        y[c] = s / M[c, c]
    return True


@njit(cache=True)
def flow_hypotheses(L: Any, flow: Any, idx: Any, ridge: float, thr2: float) -> tuple[int, int, npt.NDArray[np.bool_]]:
    """Score 3-point twist hypotheses of ``estimation.flow.velocity_ransac``.

    For each row of ``idx`` (k, 3), the twist that fits the three points' interaction
    matrices ``L`` (n, 2, 6) to their flow (n, 2) (normal equations with ``ridge`` on the
    diagonal), then the points whose flow it predicts within ``sqrt(thr2)``; a hypothesis's
    scoring stops once it has missed too many points to beat the best so far. Returns the
    first hypothesis with the most inliers: ``(index, count, inlier mask (n,))``.
    """
    n = L.shape[0]
    dof = L.shape[2]  # 6; read from the array so LLVM does not unroll every loop
    rows = 2 * idx.shape[1]
    A = np.empty((rows, dof))
    b = np.empty(rows)
    M = np.empty((dof, dof))
    x = np.empty(dof)
    best_j = 0
    best_count = -1
    best_mask = np.zeros(n, np.bool_)
    mask = np.empty(n, np.bool_)
    for h in range(idx.shape[0]):
        for a in range(idx.shape[1]):
            p = idx[h, a]
            for q in range(2):
                for c in range(dof):
                    A[2 * a + q, c] = L[p, q, c]
                b[2 * a + q] = flow[p, q]
        for i in range(dof):
            for j in range(dof):
                s = 0.0
                for r in range(rows):
                    s += A[r, i] * A[r, j]
                M[i, j] = s
            M[i, i] += ridge
            s = 0.0
            for r in range(rows):
                s += A[r, i] * b[r]
            x[i] = s
        if not _solve6(M, x):
            continue
        count = 0
        misses = 0
        for p in range(n):
            e0 = -flow[p, 0]
            e1 = -flow[p, 1]
            for c in range(dof):
                e0 += L[p, 0, c] * x[c]
                e1 += L[p, 1, c] * x[c]
            if e0 * e0 + e1 * e1 < thr2:
                mask[p] = True
                count += 1
            else:
                mask[p] = False
                misses += 1
                if misses >= n - best_count:
                    break  # cannot beat the best any more (ties keep the earlier one)
        if count > best_count:
            best_count = count
            best_j = h
            for p in range(n):  # (a slice assignment costs ~3 s of compilation)
                best_mask[p] = mask[p]
    return best_j, best_count, best_mask


@njit(cache=True)
def _flow_err2(L: Any, flow: Any, x: Any, e2: Any) -> None:
    """``e2[p]`` = squared norm of ``L[p] @ x - flow[p]`` (the flow a twist leaves unexplained)."""
    dof = x.shape[0]
    for p in range(L.shape[0]):
        e0 = -flow[p, 0]
        e1 = -flow[p, 1]
        for c in range(dof):
            e0 += L[p, 0, c] * x[c]
            e1 += L[p, 1, c] * x[c]
        e2[p] = e0 * e0 + e1 * e1


@njit(cache=True)
def _flow_fit(L: Any, flow: Any, w: Any, M: Any, x: Any) -> bool:
    """Weighted least-squares twist: ``x`` solves ``sum_p w[p] L[p]^T L[p] x = sum_p w[p]
    L[p]^T flow[p]`` (points of weight 0 skipped); False when the system is singular."""
    dof = x.shape[0]
    for i in range(dof):
        x[i] = 0.0
        for j in range(dof):
            M[i, j] = 0.0
    for p in range(L.shape[0]):
        wp = w[p]
        if wp == 0.0:
            continue
        for q in range(2):
            f = wp * flow[p, q]
            for i in range(dof):
                a = wp * L[p, q, i]
                if a != 0.0:
                    for j in range(i, dof):
                        M[i, j] += a * L[p, q, j]
                x[i] += L[p, q, i] * f
    for i in range(dof):
        for j in range(i):
            M[i, j] = M[j, i]
    return _solve6(M, x)


@njit(cache=True)
def flow_refit(L: Any, flow: Any, mask: Any, thr2: float, robust_iters: int) -> tuple[bool, F64, F64]:
    """The refits after ``estimation.flow.velocity_ransac``'s hypotheses, in one call.

    From the RANSAC inliers ``mask``: a least-squares fit on them, inliers re-selected
    (``e2 < thr2``); then with ``robust_iters`` > 0 that many Cauchy-reweighted refits
    (weight ``1 / (1 + e2 / s2)``, ``s2 = thr2 / 4``, 0 beyond the threshold; they stop when
    fewer than 3 points keep a weight or the system is singular), else a second plain fit.
    Returns ``(ok, twist (6,), e2 (n,))``: ok False (and a zero twist) when fewer than 3
    points are left for a plain fit or its system is singular.
    """
    n = L.shape[0]
    dof = L.shape[2]
    M = np.empty((dof, dof))
    x = np.zeros(dof)
    w = np.empty(n)
    e2 = np.empty(n)
    for p in range(n):
        w[p] = 1.0 if mask[p] else 0.0
    for k in range(1 if robust_iters > 0 else 2):
        count = 0
        for p in range(n):
            if k > 0:
                w[p] = 1.0 if e2[p] < thr2 else 0.0
            if w[p] != 0.0:
                count += 1
        if count < 3 or not _flow_fit(L, flow, w, M, x):
            return False, np.zeros(dof), e2
        _flow_err2(L, flow, x, e2)
    s2 = 0.25 * thr2
    xr = np.empty(dof)
    for _ in range(robust_iters):
        count = 0
        for p in range(n):
            if e2[p] < thr2:
                w[p] = 1.0 / (1.0 + e2[p] / s2)
                count += 1
            else:
                w[p] = 0.0
        if count < 3 or not _flow_fit(L, flow, w, M, xr):
            break
        for c in range(dof):
            x[c] = xr[c]
        _flow_err2(L, flow, x, e2)
    return True, x, e2
