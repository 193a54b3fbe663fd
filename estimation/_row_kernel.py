"""The compiled row search of ``estimation.stereo.row_disparity`` (numba, nopython).

For each left point, a square patch is compared with the right image's patches on the same
row at every whole disparity of its range by zero-mean normalised cross-correlation (ZNCC:
blind to a gain and an offset between the cameras). The best peak must score at least
``min_score`` and beat every other peak clearly (uniqueness); it is then placed to a fraction
of a pixel by a parabola through its three scores and polished by Gauss-Newton along x with a
gain and a bias between the patches. Points sit anywhere (bilinear sampling); the right
patches of one point share its fractional offsets, so they are read from one resampled strip.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation._kernels import _solve6

__all__ = ["row_match"]

_COST_FLOOR = 0.02
"""The uniqueness test counts a best cost ``1 - ZNCC`` below this as this (image noise): two
near-perfect peaks (a repeated pattern) are ambiguous, not both unique."""


@njit(cache=True)
def _bilinear(img: Any, x: float, y: float) -> float:
    """The image at ``(x, y)`` (inside, with one pixel to spare right and below), bilinear."""
    x0 = int(math.floor(x))
    y0 = int(math.floor(y))
    fx = x - x0
    fy = y - y0
    a = img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx
    b = img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx
    return float(a * (1.0 - fy) + b * fy)


@njit(cache=True)
def _refine(left_patch: Any, right: Any, u: float, v: float, half: int, d0: float, iters: int, free_y: bool) -> float:
    """Gauss-Newton on ``d`` (with a gain ``a``, a bias ``b`` and, if ``free_y``, a row offset ``e``) of
    ``sum (a R(u - d + j, v + e + i) + b - L)^2`` from ``d0``; NaN if it leaves the image, moves
    more than a pixel (``d`` or ``e``) or the system is singular."""
    h, w = right.shape
    n = 2 * half + 1
    d = d0
    e = 0.0
    a = 1.0
    b = 0.0
    k = 4 if free_y else 3
    M = np.empty((k, k))
    g = np.empty(k)
    # Unknowns (delta d, delta a, delta b, delta e); the first pass fits a and b alone at d0.
    for it in range(iters + 1):
        if u - d - half - 1.0 < 0.0 or u - d + half + 1.0 > w - 2.0:
            return np.nan
        if v + e - half - 1.0 < 0.0 or v + e + half + 1.0 > h - 2.0:
            return np.nan
        M[:, :] = 0.0
        g[:] = 0.0
        for i in range(n):
            y = v + e - half + i
            for j in range(n):
                x = u - d - half + j
                r = _bilinear(right, x, y)
                res = a * r + b - left_patch[i, j]
                jac0 = 0.0
                jac3 = 0.0
                if it > 0:
                    jac0 = -0.5 * a * (_bilinear(right, x + 1.0, y) - _bilinear(right, x - 1.0, y))
                    if free_y:
                        jac3 = 0.5 * a * (_bilinear(right, x, y + 1.0) - _bilinear(right, x, y - 1.0))
                jac = (jac0, r, 1.0, jac3)
                for p in range(k):
                    g[p] -= jac[p] * res
                    for q in range(p, k):
                        M[p, q] += jac[p] * jac[q]
        for p in range(k):
            for q in range(p):
                M[p, q] = M[q, p]
        if it == 0:
            M[0, 0] = 0.0
            # Solve for (a, b) only: rows/cols 1, 2.
            det2 = M[1, 1] * M[2, 2] - M[1, 2] * M[1, 2]
            if det2 <= 1e-9:
                return np.nan
            a += (g[1] * M[2, 2] - M[1, 2] * g[2]) / det2
            b += (M[1, 1] * g[2] - M[1, 2] * g[1]) / det2
            continue
        if not _solve6(M, g):
            return np.nan
        if abs(g[0]) > 1.0:
            return np.nan
        d += g[0]
        a += g[1]
        b += g[2]
        if free_y:
            e += g[3]
            if abs(e) > 1.0:
                return np.nan
        if abs(g[0]) < 0.005 and abs(g[3] if free_y else 0.0) < 0.005:
            break
    return d


@njit(cache=True)
def row_match(
    left: Any,
    right: Any,
    pts: Any,
    d_lo: Any,
    d_hi: Any,
    half: int,
    min_score: float,
    max_cost_ratio: float,
    min_std: float,
    gn_iters: int,
    free_y: bool,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Disparities of left points along their rows.

    Args:
        left, right: (H, W) uint8 rectified images.
        pts: (N, 2) float32 left pixels; d_lo, d_hi: (N,) float32 disparity range of each, px.
        half: the patch is ``2 half + 1`` px square.
        min_score: the best ZNCC must reach this.
        max_cost_ratio: the best's cost ``1 - ZNCC`` must be at most this share of the second peak's.
        min_std: the left patch's standard deviation must reach this (grey levels): flat patches fail.
        gn_iters: Gauss-Newton iterations after the parabola (0: the parabola only).
        free_y: the Gauss-Newton fit may move the right patch off the row (up to a pixel).

    Returns:
        ``(disparity_px, score, ok)``: (N,) float32, float32, bool.
    """
    h, w = left.shape
    n_pts = pts.shape[0]
    n = 2 * half + 1
    npix = n * n
    disp = np.full(n_pts, np.nan, np.float32)
    score = np.full(n_pts, -1.0, np.float32)
    ok = np.zeros(n_pts, np.bool_)
    lp = np.empty((n, n), np.float64)
    lraw = np.empty((n, n), np.float64)
    # Buffers of the widest search (a strip as wide as the image).
    strip = np.empty((n, w + n), np.float32)
    cs = np.empty(w + n, np.float32)
    cs2 = np.empty(w + n, np.float32)
    num = np.empty(w + n, np.float32)
    sc = np.empty(w + n, np.float32)
    for p in range(n_pts):
        u = float(pts[p, 0])
        v = float(pts[p, 1])
        if not (u - half >= 0.0 and u + half < w - 1.0 and v - half >= 0.0 and v + half < h - 1.0):
            continue
        ui = int(math.floor(u))
        vi = int(math.floor(v))
        fu = u - ui
        fv = v - vi
        # Whole disparities searched: the right patch must lie inside the image.
        k_lo = max(int(math.ceil(d_lo[p])), ui + half + 2 - w)
        k_hi = min(int(math.floor(d_hi[p])), ui - half)
        if k_hi - k_lo < 2:
            continue
        # The left patch, zero mean and unit norm.
        s = 0.0
        for i in range(n):
            for j in range(n):
                val = _bilinear(left, u - half + j, v - half + i)
                lraw[i, j] = val
                s += val
        mean = s / npix
        ss = 0.0
        for i in range(n):
            for j in range(n):
                c = lraw[i, j] - mean
                lp[i, j] = c
                ss += c * c
        if ss <= 0.0 or ss < min_std * min_std * npix:
            continue
        inv = 1.0 / math.sqrt(ss)
        for i in range(n):
            for j in range(n):
                lp[i, j] *= inv
        # The right strip: rows v - half .. v + half, columns of every candidate patch, sampled at
        # the point's fractional offsets. Column c is right x = x0 + c + fu.
        x0 = ui - k_hi - half
        ncol = (k_hi - k_lo) + n
        w00 = (1.0 - fu) * (1.0 - fv)
        w01 = fu * (1.0 - fv)
        w10 = (1.0 - fu) * fv
        w11 = fu * fv
        cs[:ncol] = 0.0
        cs2[:ncol] = 0.0
        csv = cs[:ncol]
        cs2v = cs2[:ncol]
        for i in range(n):
            y = vi - half + i
            srow = strip[i, :ncol]
            r0 = right[y, x0 : x0 + ncol + 1]
            if fu == 0.0 and fv == 0.0:  # a whole pixel (new corners): a copy
                for c in range(ncol):
                    srow[c] = r0[c]
            else:
                r1 = right[y + 1, x0 : x0 + ncol + 1]
                for c in range(ncol):
                    srow[c] = w00 * r0[c] + w01 * r0[c + 1] + w10 * r1[c] + w11 * r1[c + 1]
            for c in range(ncol):
                val = srow[c]
                csv[c] += val
                cs2v[c] += val * val
        ncand = k_hi - k_lo + 1
        # Candidate q is disparity k_hi - q: its patch starts at strip column q. The correlation
        # of every candidate at once, one patch pixel at a time (a contiguous, vectorised loop).
        num[:ncand] = 0.0
        for i in range(n):
            for j in range(n):
                c32 = np.float32(lp[i, j])
                srow = strip[i, j : j + ncand]
                nrow = num[:ncand]
                for q in range(ncand):
                    nrow[q] += c32 * srow[q]
        s1 = 0.0
        s2 = 0.0
        for j in range(n - 1):
            s1 += cs[j]
            s2 += cs2[j]
        for q in range(ncand):
            s1 += cs[q + n - 1]
            s2 += cs2[q + n - 1]
            var = s2 - s1 * s1 / npix
            sc[q] = num[q] / math.sqrt(var) if var > 1e-6 * npix else -1.0
            s1 -= cs[q]
            s2 -= cs2[q]
        # The best peak and the second-best other peak (local maxima).
        qb = 0
        for q in range(1, ncand):
            if sc[q] > sc[qb]:
                qb = q
        best = sc[qb]
        second = -1.0
        for q in range(ncand):
            if q == qb or abs(q - qb) == 1:
                continue
            left_ok = q == 0 or sc[q] >= sc[q - 1]
            right_ok = q == ncand - 1 or sc[q] >= sc[q + 1]
            if left_ok and right_ok and sc[q] > second:
                second = sc[q]
        score[p] = best
        if best < min_score or qb == 0 or qb == ncand - 1:
            continue
        if max(1.0 - best, _COST_FLOOR) > max_cost_ratio * (1.0 - second):
            continue
        # Subpixel: the parabola through the peak (disparity decreases with q).
        sm = sc[qb - 1]
        sp = sc[qb + 1]
        den = sm - 2.0 * best + sp
        off = 0.5 * (sm - sp) / den if den < 0.0 else 0.0
        d = float(k_hi - qb) - off
        if gn_iters > 0:
            d_gn = _refine(lraw, right, u, v, half, d, gn_iters, free_y)
            if math.isnan(d_gn) or abs(d_gn - d) > 1.0:
                continue
            d = d_gn
        disp[p] = d
        ok[p] = True
    return disp, score, ok
