"""The bookkeeping of the compiled RANSACs (``estimation.five_point``, ``estimation.p3p``), in one
place: OpenCV's random generator, its draw of a sample and its adaptive iteration count (numba,
nopython, float64).

Compiled once and cached on disk next to this module, as ``estimation._kernels``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

_RNG_COEFF = np.uint64(4164903690)
_LOW32 = np.uint64(0xFFFFFFFF)
_SHIFT32 = np.uint64(32)

RNG_SEED = np.uint64(0xFFFFFFFFFFFFFFFF)
"""The state OpenCV's RANSAC seeds its ``cv::RNG`` with on every call (``2^64 - 1``)."""


@njit(cache=True)
def rng_next(state: Any) -> tuple[Any, int]:
    """One step of OpenCV's ``cv::RNG`` (multiply-with-carry): the new state and the 32-bit draw."""
    state = (state & _LOW32) * _RNG_COEFF + (state >> _SHIFT32)
    return state, int(state & _LOW32)


@njit(cache=True)
def draw_sample(state: np.uint64, n: int, idx: Any) -> np.uint64:
    """Fill ``idx`` with distinct indices below ``n``, drawn one after the other (a repeat is drawn
    again), as OpenCV's RANSAC draws a sample; returns the generator's new state."""
    for i in range(idx.shape[0]):
        while True:
            state, r = rng_next(state)
            j = r % n
            dup = False
            for k in range(i):
                if idx[k] == j:
                    dup = True
            if not dup:
                break
        idx[i] = j
    return state


@njit(cache=True)
def update_iterations(confidence: float, outlier_ratio: float, sample_size: int, max_iters: int) -> int:
    """OpenCV's ``RANSACUpdateNumIters``: the draws for ``confidence`` of one all-inlier sample of
    ``sample_size`` points at this outlier ratio, at most ``max_iters`` (0 when no point is an
    outlier)."""
    num = max(1.0 - confidence, 2.2250738585072014e-308)
    denom = 1.0 - (1.0 - outlier_ratio) ** sample_size
    if denom < 2.2250738585072014e-308:
        return 0
    num = np.log(num)
    denom = np.log(denom)
    if denom >= 0 or -num >= max_iters * (-denom):
        return max_iters
    return int(np.rint(num / denom))
