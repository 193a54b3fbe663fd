"""The compiled corner selection and scoring of ``estimation.features.GridDetector`` (numba,
nopython).

One loop replaces a dozen numpy calls (masks, ``lexsort``, ranks within cells) of ~5-20 us
each on the ~300-1000 FAST corners of a 640x480 frame. It chooses the same corners in the
same order as the numpy code it replaced (``tests/unit/test_kernels.py`` compares them):
FAST corners sit on whole pixels, so their cells are exact integer divisions.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

__all__ = ["count_cells", "grid_select", "min_eigenvalue_at"]


@njit(cache=True)
def grid_select(
    pts: Any, resp: Any, occupied: Any, cell_px: int, ncx: int, border_px: int, width: int, height: int, budget: int
) -> npt.NDArray[np.int64]:
    """Indices into ``pts`` of the corners kept: inside the border, in cells not ``occupied``,
    the ``ceil(budget / free cells)`` strongest of each cell (ties: the earlier corner), ordered
    by cell then strength; at most ``budget``, the strongest first (stable) when cut.

    Args:
        pts: (N, 2) float32 whole-pixel corner positions; resp: (N,) float32 strengths.
        occupied: (cells,) bool, row-major cells of ``cell_px`` with ``ncx`` per row.
    """
    n = pts.shape[0]
    ncell = occupied.shape[0]
    cand = np.empty(n, np.int64)
    cell_of = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        x = pts[i, 0]
        y = pts[i, 1]
        if not (x >= border_px and x < width - border_px and y >= border_px and y < height - border_px):
            continue
        c = (int(y) // cell_px) * ncx + int(x) // cell_px
        if occupied[c]:
            continue
        cand[m] = i
        cell_of[m] = c
        m += 1
    if m == 0:
        return np.empty(0, np.int64)
    n_free = 0
    for c in range(ncell):
        if not occupied[c]:
            n_free += 1
    per_cell = max(1, int(math.ceil(budget / max(1, n_free))))
    # Counting sort of the candidates by cell (stable: corner order within a cell).
    start = np.zeros(ncell + 1, np.int64)
    for k in range(m):
        start[cell_of[k] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    by_cell = np.empty(m, np.int64)
    for k in range(m):
        c = cell_of[k]
        by_cell[fill[c]] = cand[k]
        fill[c] += 1
    chosen = np.empty(m, np.int64)
    n_chosen = 0
    picked = np.zeros(n, np.bool_)
    for c in range(ncell):
        s, e = start[c], start[c + 1]
        for _ in range(min(per_cell, e - s)):
            best = -1
            for k in range(s, e):
                j = by_cell[k]
                if not picked[j] and (best < 0 or resp[j] > resp[best]):
                    best = j
            picked[best] = True
            chosen[n_chosen] = best
            n_chosen += 1
    out = chosen[:n_chosen]
    if n_chosen > budget:
        order = np.argsort(-resp[out], kind="mergesort")
        out = out[order[:budget]]
    return out


@njit(cache=True)
def min_eigenvalue_at(gray: Any, pts: Any) -> npt.NDArray[np.float32]:
    """The Shi-Tomasi score at whole-pixel points: the smaller eigenvalue of the structure
    tensor (sums of ``gx^2, gx*gy, gy^2`` of 3x3 Sobel gradients over the 5x5 window centred
    on the pixel), in grey levels squared; 0 for points too near the border for the window.

    Args:
        gray: (H, W) uint8 image; pts: (N, 2) float32 whole-pixel positions (x, y).
    """
    h, w = gray.shape
    n = pts.shape[0]
    out = np.zeros(n, np.float32)
    for i in range(n):
        x = int(pts[i, 0])
        y = int(pts[i, 1])
        if x < 3 or y < 3 or x > w - 4 or y > h - 4:
            continue
        sxx = 0.0
        sxy = 0.0
        syy = 0.0
        for v in range(y - 2, y + 3):
            for u in range(x - 2, x + 3):
                a = float(gray[v - 1, u - 1])
                b = float(gray[v - 1, u])
                c = float(gray[v - 1, u + 1])
                d = float(gray[v, u - 1])
                f = float(gray[v, u + 1])
                g = float(gray[v + 1, u - 1])
                k = float(gray[v + 1, u])
                m = float(gray[v + 1, u + 1])
                gx = (c + 2.0 * f + m) - (a + 2.0 * d + g)
                gy = (g + 2.0 * k + m) - (a + 2.0 * b + c)
                sxx += gx * gx
                sxy += gx * gy
                syy += gy * gy
        half_tr = 0.5 * (sxx + syy)
        half_diff = 0.5 * (sxx - syy)
        out[i] = half_tr - math.sqrt(half_diff * half_diff + sxy * sxy)
    return out


@njit(cache=True)
def count_cells(px: Any, cell_px: float) -> int:
    """How many square cells of ``cell_px`` (a grid from the image origin) hold at least one of the
    (N, 2) pixels ``px`` (non-finite ones hold none): ``len(np.unique(...))`` of their cells, by a
    table over the cells they span (sorting only when they span a huge area)."""
    n = px.shape[0]
    cx = np.empty(n, np.int64)
    cy = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        u = np.float64(px[i, 0]) / cell_px
        v = np.float64(px[i, 1]) / cell_px
        if abs(u) < 2.0**52 and abs(v) < 2.0**52:  # finite, and its cell an exact integer
            cx[m] = np.int64(math.floor(u))
            cy[m] = np.int64(math.floor(v))
            m += 1
    if m == 0:
        return 0
    cx, cy = cx[:m], cy[:m]
    x0, y0 = cx.min(), cy.min()
    nx, ny = cx.max() - x0 + 1, cy.max() - y0 + 1
    limit = 16 * m + 4096
    if nx <= limit and ny <= limit // nx:
        seen = np.zeros(nx * ny, np.bool_)
        count = 0
        for i in range(m):
            j = (cy[i] - y0) * nx + (cx[i] - x0)
            if not seen[j]:
                seen[j] = True
                count += 1
        return count
    order = np.argsort(cx, kind="mergesort")  # by column, then the distinct rows of each column
    xs, ys = cx[order], cy[order]
    count = 0
    k = 0
    while k < m:
        e = k + 1
        while e < m and xs[e] == xs[k]:
            e += 1
        col = np.sort(ys[k:e])
        count += 1
        for q in range(1, e - k):
            if col[q] != col[q - 1]:
                count += 1
        k = e
    return count
