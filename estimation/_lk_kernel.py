"""Compiled pyramidal Lucas-Kanade (Bouguet's iteration) on pyramids built once per image.

The kernel behind :mod:`estimation.lk`. It follows OpenCV's ``calcOpticalFlowPyrLK``: the same
units (raw Scharr derivatives, grey levels x 32, ``min_eig`` compared with the smaller eigenvalue
of the gradient matrix over ``2 * window area`` in units of 2**20), the same stopping rules (a step
below ``eps_px``; half a step back when two steps cancel), the same bounds (a window may reach
``win`` pixels into the border: the image there is reflected, its derivatives are zero). It differs
in the arithmetic (float32 instead of 14-bit fixed point; positions agree to ~1e-4 px) and in its
memory layout: every window is first copied (as float32) into a buffer with a fixed row stride, so that
each inner loop runs over one contiguous range and compiles to vector code.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

__all__ = ["tracker"]

_FLT_EPSILON = 1.1920929e-07
_FASTMATH = {"reassoc", "contract", "nsz", "arcp", "afn"}
"""Fast-math without "nnan"/"ninf": the bounds checks must see a NaN or infinite position."""
_EIG_SCALE = 1.0 / float(1 << 20)


@numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, inline="always")
def _copy_block(img: Any, off: int, stride: int, rows: int, cols: int, buf: Any, s: int) -> None:  # pragma: no cover
    for i in range(rows):
        r = off + i * stride
        for j in range(cols):
            buf[i * s + j] = np.float32(img[r + j])


@numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, inline="always")
def _bilinear_weights(a: Any, b: Any) -> tuple[Any, Any, Any, Any]:  # pragma: no cover - compiled
    """Bilinear weights of the pixels (0, 0), (1, 0), (0, 1), (1, 1) for a point ``a``, ``b`` (0..1) into the cell."""
    one = np.float32(1.0)
    return (one - a) * (one - b), a * (one - b), (one - a) * b, a * b


@numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, inline="always")
def _scharr(b: Any, q: int, s: int) -> tuple[Any, Any]:  # pragma: no cover - compiled
    """Scharr's x and y derivatives (raw: 3, 10, 3) at ``q + s + 1`` of a buffer of row stride ``s``."""
    three = np.float32(3.0)
    ten = np.float32(10.0)
    c00 = b[q]
    c01 = b[q + 1]
    c02 = b[q + 2]
    c10 = b[q + s]
    c12 = b[q + s + 2]
    c20 = b[q + 2 * s]
    c21 = b[q + 2 * s + 1]
    c22 = b[q + 2 * s + 2]
    return three * (c02 - c00 + c22 - c20) + ten * (c12 - c10), three * (c20 - c00 + c22 - c02) + ten * (c21 - c01)


@functools.cache
def tracker(win: int) -> Callable[..., None]:
    """The kernel for windows of ``win`` pixels (a compile-time constant: the window loops then
    compile to straight vector code, 2-3x faster than with the size as an argument)."""
    s = (win + 10) // 8 * 8  # row stride of the window buffers: win + 3 columns, a multiple of 8
    m = s * win  # a window buffer: win rows of stride s; columns >= win are masked out

    @numba.njit(cache=True, fastmath=_FASTMATH, nogil=True)
    def lk_track(  # pragma: no cover - compiled
        i_flat: Any,
        i_offsets: Any,
        i_pad: int,
        j_flat: Any,
        j_offsets: Any,
        j_pad: int,
        sizes: Any,
        p0: Any,
        p1: Any,
        status: Any,
        n_levels: int,
        max_iters: int,
        eps_px: float,
        min_eig: float,
    ) -> None:
        """Track ``p0`` (N, 2) from image I into image J; writes ``p1`` (N, 2; on entry: the start at
        level 0) and ``status`` (N,) in place.

        ``i_flat``/``j_flat``: the padded uint8 levels of each pyramid, one after the other, level
        ``l`` starting at ``i_offsets[l]``/``j_offsets[l]``, of ``sizes[l]`` = (width, height) before
        padding by ``i_pad``/``j_pad`` pixels on every side (at least ``win + 2``); ``n_levels``: the
        levels used.
        """
        n = p0.shape[0]
        half = np.float32((win - 1) * 0.5)
        block = np.zeros(s * (win + 4), np.float32)  # a window's pixels, as float32
        inter = np.zeros(s * (win + 4), np.float32)  # I interpolated around the window
        gxg = np.zeros(s * (win + 2), np.float32)
        gyg = np.zeros(s * (win + 2), np.float32)
        t_i = np.zeros(m, np.float32)
        t_x = np.zeros(m, np.float32)
        t_y = np.zeros(m, np.float32)
        colmask = np.zeros(m, np.float32)
        for q in range(m):
            if q % s < win:
                colmask[q] = 1.0
        eps2 = eps_px * eps_px
        for k in range(n):
            status[k] = True
        for level in range(n_levels - 1, -1, -1):
            cols = sizes[level, 0]
            rows = sizes[level, 1]
            i_stride = cols + 2 * i_pad
            j_stride = cols + 2 * j_pad
            i_base = i_offsets[level] + i_pad * i_stride + i_pad  # index of the level's pixel (0, 0)
            j_base = j_offsets[level] + j_pad * j_stride + j_pad
            scale = np.float32(1.0 / (1 << level))
            for k in range(n):
                up = scale if level == n_levels - 1 else np.float32(2.0)
                p1[k, 0] *= up
                p1[k, 1] *= up
                px = p0[k, 0] * scale - half
                py = p0[k, 1] * scale - half
                # (on the floats: floor(x) in [-win, cols) is x in [-win, cols); NaN fails it too)
                if not (-win <= px < cols and -win <= py < rows):
                    if level == 0:
                        status[k] = False
                    continue
                ix0 = int(math.floor(px))
                iy0 = int(math.floor(py))
                # the template: I's pixels around the window (one more on each side) ...
                _copy_block(i_flat, i_base + (iy0 - 1) * i_stride + ix0 - 1, i_stride, win + 3, win + 3, block, s)
                w00, w01, w10, w11 = _bilinear_weights(np.float32(px - ix0), np.float32(py - iy0))
                a11 = np.float32(0.0)
                a12 = np.float32(0.0)
                a22 = np.float32(0.0)
                if ix0 < 0 or iy0 < 0 or ix0 + win >= cols or iy0 + win >= rows:
                    # At the border: Scharr derivatives on the integer grid (zero outside the
                    # image), then all three interpolated at the window's sub-pixel position.
                    for q in range(s * (win + 1)):
                        gxg[q], gyg[q] = _scharr(block, q, s)
                    for gi in range(win + 1):
                        for gj in range(win + 1):
                            if not (0 <= iy0 + gi < rows and 0 <= ix0 + gj < cols):
                                gxg[gi * s + gj] = 0.0
                                gyg[gi * s + gj] = 0.0
                    for q in range(m):
                        c = q + s + 1
                        t_i[q] = w00 * block[c] + w01 * block[c + 1] + w10 * block[c + s] + w11 * block[c + s + 1]
                        gx = (w00 * gxg[q] + w01 * gxg[q + 1] + w10 * gxg[q + s] + w11 * gxg[q + s + 1]) * colmask[q]
                        gy = (w00 * gyg[q] + w01 * gyg[q + 1] + w10 * gyg[q + s] + w11 * gyg[q + s + 1]) * colmask[q]
                        t_x[q] = gx
                        t_y[q] = gy
                        a11 += gx * gx
                        a12 += gx * gy
                        a22 += gy * gy
                else:
                    # Inside: I interpolated one pixel around the window, then its Scharr
                    # derivatives (both filters are linear and shift-invariant: the same as
                    # interpolating the grid's derivatives, with a third of the interpolation).
                    for q in range(s * (win + 2)):
                        inter[q] = w00 * block[q] + w01 * block[q + 1] + w10 * block[q + s] + w11 * block[q + s + 1]
                    for q in range(m):
                        sx, sy = _scharr(inter, q, s)
                        gx = sx * colmask[q]
                        gy = sy * colmask[q]
                        t_i[q] = inter[q + s + 1]
                        t_x[q] = gx
                        t_y[q] = gy
                        a11 += gx * gx
                        a12 += gx * gy
                        a22 += gy * gy
                a11 *= _EIG_SCALE
                a12 *= _EIG_SCALE
                a22 *= _EIG_SCALE
                det = a11 * a22 - a12 * a12
                eig = (a22 + a11 - math.sqrt((a11 - a22) * (a11 - a22) + 4.0 * a12 * a12)) / (2.0 * win * win)
                if eig < min_eig or det < _FLT_EPSILON:
                    if level == 0:
                        status[k] = False
                    continue
                inv_det = np.float32(32.0 * _EIG_SCALE / det)
                nx = p1[k, 0] - half
                ny = p1[k, 1] - half
                pdx = np.float32(0.0)
                pdy = np.float32(0.0)
                for j in range(max_iters):
                    if not (-win <= nx < cols and -win <= ny < rows):
                        if level == 0:
                            status[k] = False
                        break
                    jx0 = int(math.floor(nx))
                    jy0 = int(math.floor(ny))
                    _copy_block(j_flat, j_base + jy0 * j_stride + jx0, j_stride, win + 1, win + 1, block, s)
                    v00, v01, v10, v11 = _bilinear_weights(np.float32(nx - jx0), np.float32(ny - jy0))
                    b1 = np.float32(0.0)
                    b2 = np.float32(0.0)
                    for q in range(m):
                        d = (v00 * block[q] + v01 * block[q + 1] + v10 * block[q + s] + v11 * block[q + s + 1]) - t_i[q]
                        b1 += d * t_x[q]
                        b2 += d * t_y[q]
                    ddx = (a12 * b2 - a22 * b1) * inv_det
                    ddy = (a12 * b1 - a11 * b2) * inv_det
                    nx += ddx
                    ny += ddy
                    p1[k, 0] = nx + half
                    p1[k, 1] = ny + half
                    if ddx * ddx + ddy * ddy <= eps2:
                        break
                    if j > 0 and abs(ddx + pdx) < 0.01 and abs(ddy + pdy) < 0.01:
                        p1[k, 0] -= ddx * np.float32(0.5)
                        p1[k, 1] -= ddy * np.float32(0.5)
                        break
                    pdx = ddx
                    pdy = ddy

    return lk_track
