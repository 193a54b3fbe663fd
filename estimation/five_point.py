"""The essential matrix by 5-point RANSAC, compiled (numba): OpenCV's ``findEssentialMat``
(``method=RANSAC``) at about a quarter of its cost, with the same samples and decisions.

OpenCV's RANSAC (``cv::RANSACPointSetRegistrator``) draws its 5-point samples from a
``cv::RNG`` seeded with ``2^64 - 1`` on every call, scores each candidate essential matrix by
its Sampson error (normalised coordinates, rounded to float32) against ``threshold^2``, keeps
a candidate only when it has strictly more inliers than the best so far, and sizes the
iteration count from the best inlier ratio. :func:`find_essential` does the same with the same
random draws. Only the minimal solver differs: OpenCV expands the constraints in closed form
and finds the roots of a degree-10 polynomial iteratively (``solvePoly``, ~0.2 ms a sample);
here the same ten cubic constraints are eliminated to an action matrix whose real
eigenvectors are the solutions (~30 us). The candidates agree to rounding, so the inlier sets,
the chosen sample and the result agree, except where the order of a sample's solutions decides
(two with other inliers tie at a new best count) or a root is near-double (OpenCV's solver may
take it as real or not): there the call is handed to OpenCV (9 % of the calls on fr1/rpy and
7-Scenes). Figures: docs/estimation-log.md, "Issue 15, speed pass".

The constraints (Nister 2004; Stewenius et al. 2006): with ``E = x E0 + y E1 + z E2 + E3``
spanning the null space of the five epipolar equations, ``det(E) = 0`` and
``2 E E^T E - trace(E E^T) E = 0`` give ten cubic equations in ``x, y, z``; eliminating the
ten cubic monomials leaves the action of ``x`` on ``[x^2, xy, xz, y^2, yz, z^2, x, y, z, 1]``.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from llvmlite import binding as llvm
from numba import njit, types
from numba.extending import get_cython_function_address

from estimation._ransac_kernel import RNG_SEED, draw_sample, update_iterations

__all__ = ["find_essential"]

F64 = npt.NDArray[np.float64]

# Monomials in (x, y, z) up to degree 3: the ten cubic ones (eliminated) first, then the
# action matrix's basis, ``1`` last.
_MONOMIALS = [
    (3, 0, 0), (2, 1, 0), (2, 0, 1), (1, 2, 0), (1, 1, 1), (1, 0, 2), (0, 3, 0), (0, 2, 1), (0, 1, 2), (0, 0, 3),
    (2, 0, 0), (1, 1, 0), (1, 0, 1), (0, 2, 0), (0, 1, 1), (0, 0, 2), (1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 0),
]  # fmt: skip
_INDEX = {m: i for i, m in enumerate(_MONOMIALS)}


def _product_table() -> npt.NDArray[np.int64]:
    """``table[a, b]``: the index of monomial a times monomial b (-1 above degree 3)."""
    t = np.full((20, 20), -1, np.int64)
    for a, ma in enumerate(_MONOMIALS):
        for b, mb in enumerate(_MONOMIALS):
            t[a, b] = _INDEX.get((ma[0] + mb[0], ma[1] + mb[1], ma[2] + mb[2]), -1)
    return t


_PRODUCT = _product_table()
_LINEAR = np.array([_INDEX[(1, 0, 0)], _INDEX[(0, 1, 0)], _INDEX[(0, 0, 1)], _INDEX[(0, 0, 0)]], np.int64)
"""The monomials x, y, z, 1 of the null-space coefficients."""
_TIMES_X = np.array([_INDEX[(m[0] + 1, m[1], m[2])] for m in _MONOMIALS[10:]], np.int64)
"""For each basis monomial b, the index of x b."""

llvm.add_symbol("flightkit_dgeev", get_cython_function_address("scipy.linalg.cython_lapack", "dgeev"))
_dgeev: Any = types.ExternalFunction("flightkit_dgeev", types.void(*([types.voidptr] * 14)))
"""LAPACK's real eigensolver (scipy's, by its symbol: the compiled code stays cacheable): numba's
``np.linalg.eig`` refuses real matrices with complex eigenvalues, and its complex one costs 3x
as much on this 10x10."""
_JOB_N = np.frombuffer(b"N", dtype=np.uint8)
_JOB_V = np.frombuffer(b"V", dtype=np.uint8)
_LWORK = 100


@njit(cache=True)
def _eig(A: Any, wr: Any, wi: Any, vr: Any, buf: Any) -> bool:
    """Eigenvalues ``wr + i wi`` and right eigenvectors (``vr``, LAPACK's packing: a real
    eigenvalue's vector in its column) of the 10x10 ``A``; False when LAPACK fails. ``buf``:
    (10, 10) scratch."""
    # LAPACK is column-major: it gets A^T's buffer and fills vr^T's.
    for i in range(10):
        for j in range(10):
            buf[j, i] = A[i, j]
    ints = np.empty(4, np.int32)  # n, lwork, info, 1
    ints[0] = 10
    ints[1] = _LWORK
    ints[3] = 1
    work = np.empty(_LWORK)
    vrt = np.empty((10, 10))
    vl = np.empty(1)
    n = ints[0:1].ctypes
    _dgeev(_JOB_N.ctypes, _JOB_V.ctypes, n, buf.ctypes, n, wr.ctypes, wi.ctypes, vl.ctypes, ints[3:4].ctypes,
           vrt.ctypes, n, work.ctypes, ints[1:2].ctypes, ints[2:3].ctypes)  # fmt: skip
    for i in range(10):
        for j in range(10):
            vr[i, j] = vrt[j, i]
    return bool(ints[2] == 0)


@njit(cache=True)
def _gauss_jordan(M: Any, n: int) -> bool:
    """Reduce the first ``n`` columns of ``M`` (n rows) to the identity in place (partial
    pivoting); False when they are singular."""
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(M[r, c]) > abs(M[p, c]):
                p = r
        if not abs(M[p, c]) > 1e-300:
            return False
        if p != c:
            for k in range(M.shape[1]):
                M[c, k], M[p, k] = M[p, k], M[c, k]
        inv = 1.0 / M[c, c]
        for k in range(M.shape[1]):
            M[c, k] *= inv
        for r in range(n):
            if r != c and M[r, c] != 0.0:
                f = M[r, c]
                for k in range(M.shape[1]):
                    M[r, k] -= f * M[c, k]
    return True


@njit(cache=True)
def _null_space(Q: Any, out: Any) -> None:
    """An orthonormal basis of the null space of the (5, 9) ``Q`` into the rows of ``out``
    (4, 9): the last four columns of the orthogonal factor of ``Q^T`` (Householder)."""
    H = np.eye(9)  # the accumulated orthogonal factor
    R = Q.T.copy()  # (9, 5)
    v = np.empty(9)
    for c in range(5):
        norm = 0.0
        for r in range(c, 9):
            norm += R[r, c] * R[r, c]
        norm = np.sqrt(norm)
        if norm == 0.0:
            continue
        alpha = -norm if R[c, c] > 0 else norm
        vv = 0.0
        for r in range(9):
            v[r] = 0.0 if r < c else R[r, c]
        v[c] -= alpha
        for r in range(c, 9):
            vv += v[r] * v[r]
        if vv == 0.0:
            continue
        # R <- (I - 2 v v^T / vv) R, H <- H (I - 2 v v^T / vv)
        for k in range(5):
            d = 0.0
            for r in range(c, 9):
                d += v[r] * R[r, k]
            d *= 2.0 / vv
            for r in range(c, 9):
                R[r, k] -= d * v[r]
        for r in range(9):
            d = 0.0
            for k in range(c, 9):
                d += H[r, k] * v[k]
            d *= 2.0 / vv
            for k in range(c, 9):
                H[r, k] -= d * v[k]
    for j in range(4):
        for r in range(9):
            out[j, r] = H[r, 5 + j]


_REAL = 1e-11
"""An eigenvalue (of the action matrix) whose imaginary part is within this (relative) is real."""
_COMPLEX = 1e-6
"""... and beyond this complex; in between, a root OpenCV's solver may take either way."""

@njit(cache=True)
def _polymul_add(p: Any, q: Any, scale: float, out: Any) -> None:
    """``out += scale * p * q`` for polynomials over the 20 monomials (terms above degree 3
    dropped: the callers' products stay within it)."""
    for a in range(20):
        if p[a] == 0.0:
            continue
        sa = scale * p[a]
        for b in range(20):
            if q[b] != 0.0:
                k = _PRODUCT[a, b]
                if k >= 0:
                    out[k] += sa * q[b]


@njit(cache=True)
def _solve5(q1: Any, q2: Any, out: Any, certain: Any) -> int:
    """The essential matrices (unit Frobenius norm, into ``out`` (10, 3, 3)) of five normalised
    matches ``q1 -> q2`` ((5, 2) each, ``q2^T E q1 = 0``); returns how many. ``certain[i]``:
    solution i is real beyond doubt (else its root is within ``_COMPLEX`` of the real axis: two
    close real roots, or a complex pair, which OpenCV's root finder may take either way)."""
    Q = np.empty((5, 9))
    for i in range(5):
        x1, y1, x2, y2 = q1[i, 0], q1[i, 1], q2[i, 0], q2[i, 1]
        Q[i, 0] = x1 * x2
        Q[i, 1] = y1 * x2
        Q[i, 2] = x2
        Q[i, 3] = x1 * y2
        Q[i, 4] = y1 * y2
        Q[i, 5] = y2
        Q[i, 6] = x1
        Q[i, 7] = y1
        Q[i, 8] = 1.0
    basis = np.empty((4, 9))  # E0, E1, E2, E3 (row-major 3x3 each)
    _null_space(Q, basis)
    # Each entry of E as a polynomial (linear in x, y, z, 1).
    E = np.zeros((3, 3, 20))
    for r in range(3):
        for c in range(3):
            for k in range(4):
                E[r, c, _LINEAR[k]] = basis[k, 3 * r + c]
    C = np.zeros((10, 20))
    # det(E) by the first row's cofactors.
    minor = np.empty(20)
    for c in range(3):
        c1, c2 = (c + 1) % 3, (c + 2) % 3
        for m in range(20):
            minor[m] = 0.0
        _polymul_add(E[1, c1], E[2, c2], 1.0, minor)
        _polymul_add(E[1, c2], E[2, c1], -1.0, minor)
        _polymul_add(E[0, c], minor, 1.0, C[0])
    # 2 E E^T E - trace(E E^T) E.
    EEt = np.zeros((3, 3, 20))
    tr = np.zeros(20)
    for r in range(3):
        for c in range(3):
            for k in range(3):
                _polymul_add(E[r, k], E[c, k], 1.0, EEt[r, c])
        for m in range(20):
            tr[m] += EEt[r, r, m]
    for r in range(3):
        for c in range(3):
            row = C[1 + 3 * r + c]
            for k in range(3):
                _polymul_add(EEt[r, k], E[k, c], 2.0, row)
            _polymul_add(tr, E[r, c], -1.0, row)
    # Eliminate the cubic monomials: cubic_i = -G[i] . basis.
    if not _gauss_jordan(C, 10):  # a degenerate sample
        return 0
    G = C[:, 10:]
    # The action of x on the basis: x b_j = A[j] . basis.
    A = np.zeros((10, 10))
    for j in range(10):
        k = _TIMES_X[j]
        if k < 10:
            for m in range(10):
                A[j, m] = -G[k, m]
        else:
            A[j, k - 10] = 1.0
    wr = np.empty(10)
    wi = np.empty(10)
    v = np.empty((10, 10))
    if not _eig(A, wr, wi, v, np.empty((10, 10))):
        return 0
    n = 0
    for s in range(10):
        scale = max(1.0, abs(wr[s]))
        if abs(wi[s]) > _COMPLEX * scale:
            continue
        certain[n] = abs(wi[s]) <= _REAL * scale
        # A complex eigenvalue's vector is spread over two columns (real and imaginary parts;
        # the first one's is the conjugate's too): x, y, z the real parts of the ratios.
        col = s if wi[s] >= 0.0 else s - 1
        im = 0.0 if wi[s] == 0.0 else (1.0 if wi[s] > 0 else -1.0)
        c = v[9, col]
        d = im * v[9, col + 1] if im != 0.0 else 0.0
        den = c * c + d * d
        if den < 1e-24:
            continue
        xyz = np.empty(3)
        for q in range(3):
            a = v[6 + q, col]
            b = im * v[6 + q, col + 1] if im != 0.0 else 0.0
            xyz[q] = (a * c + b * d) / den
        x, y, z = xyz[0], xyz[1], xyz[2]
        nrm = 0.0
        for r in range(3):
            for c in range(3):
                e = x * basis[0, 3 * r + c] + y * basis[1, 3 * r + c] + z * basis[2, 3 * r + c] + basis[3, 3 * r + c]
                out[n, r, c] = e
                nrm += e * e
        nrm = np.sqrt(nrm)
        if not nrm > 0.0:
            continue
        for r in range(3):
            for c in range(3):
                out[n, r, c] /= nrm
        n += 1
    return n


@njit(cache=True)
def _inliers(E: Any, p1: Any, p2: Any, thr2: np.float32, mask: Any) -> int:
    """Marks (and counts) the matches whose Sampson error under ``E``, rounded to float32,
    is at most ``thr2`` (OpenCV's test)."""
    count = 0
    for i in range(p1.shape[0]):
        x1, y1, x2, y2 = p1[i, 0], p1[i, 1], p2[i, 0], p2[i, 1]
        a0 = E[0, 0] * x1 + E[0, 1] * y1 + E[0, 2]
        a1 = E[1, 0] * x1 + E[1, 1] * y1 + E[1, 2]
        a2 = E[2, 0] * x1 + E[2, 1] * y1 + E[2, 2]
        b0 = E[0, 0] * x2 + E[1, 0] * y2 + E[2, 0]
        b1 = E[0, 1] * x2 + E[1, 1] * y2 + E[2, 1]
        d = x2 * a0 + y2 * a1 + a2
        err = np.float32(d * d / (a0 * a0 + a1 * a1 + b0 * b0 + b1 * b1))
        ok = err <= thr2
        mask[i] = ok
        count += int(ok)
    return count


@njit(cache=True)
def _same(a: Any, b: Any) -> bool:
    """Two masks are equal."""
    for i in range(a.shape[0]):
        if a[i] != b[i]:
            return False
    return True


@njit(cache=True)
def _close(A: Any, B: Any) -> bool:
    """Two unit-norm essential matrices are the same to 1e-6, up to their sign (a near-double
    root's two solutions, which OpenCV's order cannot tell apart either)."""
    dp = 0.0
    dm = 0.0
    for r in range(3):
        for c in range(3):
            dp = max(dp, abs(A[r, c] - B[r, c]))
            dm = max(dm, abs(A[r, c] + B[r, c]))
    return min(dp, dm) < 1e-6


@njit(cache=True)
def _ransac(p1: Any, p2: Any, thr2: np.float32, confidence: float, max_iters: int) -> tuple[int, F64, Any, bool]:
    """5-point RANSAC over normalised matches (see the module docstring); returns the best
    inlier count (0: none), its essential matrix, its inlier mask, and whether OpenCV's order
    of a sample's solutions could have chosen another matrix (a tie at a new best count)."""
    n = p1.shape[0]
    best_E = np.zeros((3, 3))
    best_mask = np.zeros(n, np.bool_)
    mask = np.zeros(n, np.bool_)
    models = np.empty((10, 3, 3))
    certain = np.zeros(10, np.bool_)
    s1 = np.empty((5, 2))
    s2 = np.empty((5, 2))
    idx = np.empty(5, np.int64)
    state = RNG_SEED
    best = 0
    ambiguous = False
    niters = max(max_iters, 1)
    it = 0
    while it < niters:
        state = draw_sample(state, n, idx)
        for i in range(5):
            j = idx[i]
            s1[i, 0], s1[i, 1] = p1[j, 0], p1[j, 1]
            s2[i, 0], s2[i, 1] = p2[j, 0], p2[j, 1]
        nm = _solve5(s1, s2, models, certain)
        prior = max(best, 4)
        top = prior
        ties = 0
        for m in range(nm):
            good = _inliers(models[m], p1, p2, thr2, mask)
            if not certain[m]:
                # A root OpenCV may or may not have: ambiguous if it would have mattered.
                ambiguous |= good > prior
                continue
            if good > top:
                top, ties = good, 1
            elif good == top and good > prior and not (_same(mask, best_mask) and _close(models[m], best_E)):
                ties += 1
            if good > max(best, 4):
                best_mask, mask = mask, best_mask
                for r in range(3):
                    for c in range(3):
                        best_E[r, c] = models[m, r, c]
                best = good
                niters = update_iterations(confidence, (n - good) / n, 5, niters)
        # Two different solutions of one sample at a new best count (a planar scene has two
        # with the same inliers): OpenCV keeps the first in its own order of the solutions,
        # which this solver does not reproduce.
        ambiguous |= ties > 1
        it += 1
    return best, best_E, best_mask, ambiguous


def find_essential(
    px_ref: F64, px_cur: F64, K: F64, threshold_px: float = 1.0, confidence: float = 0.999, max_iters: int = 1000
) -> tuple[F64 | None, npt.NDArray[np.bool_]]:
    """The essential matrix of pixel matches ``px_ref -> px_cur`` ((N, 2) float64, N >= 6, one
    pinhole camera ``K``) by 5-point RANSAC, as ``cv2.findEssentialMat(px_ref, px_cur, K,
    cv2.RANSAC, confidence, threshold_px)``; returns it (None when no sample gave 5 inliers)
    and the inlier mask."""
    if len(px_ref) < 6:
        return None, np.zeros(len(px_ref), dtype=bool)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    p1 = np.empty_like(px_ref)
    p1[:, 0] = (px_ref[:, 0] - cx) / fx
    p1[:, 1] = (px_ref[:, 1] - cy) / fy
    p2 = np.empty_like(px_cur)
    p2[:, 0] = (px_cur[:, 0] - cx) / fx
    p2[:, 1] = (px_cur[:, 1] - cy) / fy
    thr = threshold_px / ((fx + fy) / 2)
    best, E, mask, ambiguous = _ransac(p1, p2, np.float32(thr * thr), float(confidence), int(max_iters))
    if ambiguous:
        # A few % of the calls: OpenCV's own answer.
        E_cv, mask_cv = cv2.findEssentialMat(
            px_ref, px_cur, K, method=cv2.RANSAC, prob=confidence, threshold=threshold_px
        )
        if E_cv is None or mask_cv is None:
            return None, np.zeros(len(px_ref), dtype=bool)
        return np.asarray(E_cv[:3], dtype=np.float64), mask_cv.ravel() > 0
    return (E if best > 0 else None), mask
