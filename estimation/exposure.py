"""Exposure changes between consecutive images, measured and undone before tracking.

A camera's automatic exposure scales every pixel of a frame by about the same gain. LK
tracking minimises intensity differences, so a gain change between two frames pulls every
track along its intensity gradient (the patch is matched where the brightness agrees) and
fails the forward-backward check on many others.

:func:`exposure_gain` measures the gain at the tracked points: the mean brightness of a square
around each point (from the image's integral) in the previous frame and around its predicted
position in the current one. The log-ratios' median is the gain; it is returned only when it is
significant against the ratios' own spread (more than ``z_min`` standard errors of the median
from 1), so scene changes and prediction errors on a steady exposure leave the images untouched.
:func:`match_exposure` then scales the brighter of the two images down to the other, which
saturates nothing.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from numba import njit

__all__ = ["Integral", "exposure_gain", "integral", "match_exposure"]

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]

_MIN_POINTS = 20
"""Fewer usable points than this: no measurement (gain 1)."""

_DARK, _BRIGHT = 10.0, 245.0
"""Square means outside (_DARK, _BRIGHT) are left out: near black or saturated, they do not scale."""

_SE_OF_MEDIAN = 1.2533 * 1.4826
"""Standard error of a median of n Gaussian samples is this times their MAD over sqrt(n)."""


Integral = npt.NDArray[np.float64]
"""An image's integral, (H + 1) x (W + 1) (:func:`integral`)."""


def integral(image: U8) -> Integral:
    """The integral of an 8-bit image (float64: exact at any size), for :func:`exposure_gain`."""
    return np.asarray(cv2.integral(image, sdepth=cv2.CV_64F), dtype=np.float64)


@njit(cache=True)
def _box_means(integ: Any, px: Any, cell_px: int) -> Any:
    """The mean brightness of the ``cell_px`` square around each pixel (cut at the borders), from
    the image's integral."""
    h, w = integ.shape[0] - 1, integ.shape[1] - 1
    half = cell_px // 2
    out = np.empty(px.shape[0])
    for i in range(px.shape[0]):
        x, y = int(round(px[i, 0])), int(round(px[i, 1]))
        x0, x1 = min(max(x - half, 0), w), min(max(x + half + 1, 0), w)
        y0, y1 = min(max(y - half, 0), h), min(max(y + half + 1, 0), h)
        n = (x1 - x0) * (y1 - y0)
        total = integ[y1, x1] - integ[y0, x1] - integ[y1, x0] + integ[y0, x0]
        out[i] = total / n if n > 0 else 0.0
    return out


def exposure_gain(
    prev: Integral, cur: Integral, px_prev: F32, px_cur: F32, cell_px: int, z_min: float = 3.0
) -> float:
    """The exposure gain from the previous image to the current one (``cur ~ gain * prev``), or
    exactly 1.0 when it is not measurable or not significant.

    Args:
        prev, cur: the two images' :func:`integral` (the current one's serves again next frame).
        px_prev: (N, 2) tracked points in the previous image; px_cur: where they are expected in
            the current one (a prediction is enough: the brightness is averaged over ``cell_px``
            squares).
        z_min: significance, in standard errors of the log-ratios' median.
    """
    if len(px_prev) < _MIN_POINTS:
        return 1.0
    a = _box_means(prev, np.ascontiguousarray(px_prev, dtype=np.float64), int(cell_px))
    b = _box_means(cur, np.ascontiguousarray(px_cur, dtype=np.float64), int(cell_px))
    good = (a > _DARK) & (a < _BRIGHT) & (b > _DARK) & (b < _BRIGHT)
    n = int(np.count_nonzero(good))
    if n < _MIN_POINTS:
        return 1.0
    log_ratio = np.log(b[good] / a[good])
    med = float(np.median(log_ratio))
    se = _SE_OF_MEDIAN * float(np.median(np.abs(log_ratio - med))) / math.sqrt(n)
    return math.exp(med) if abs(med) > z_min * se else 1.0


def match_exposure(prev: U8, cur: U8, gain: float) -> tuple[U8, U8]:
    """``prev`` and ``cur`` brought to one exposure (``cur ~ gain * prev``): the brighter one scaled
    down, so nothing saturates. Returns the inputs themselves when ``gain`` is 1."""
    if gain == 1.0:
        return prev, cur
    if gain > 1.0:
        return prev, np.asarray(cv2.convertScaleAbs(cur, alpha=1.0 / gain), dtype=np.uint8)
    return np.asarray(cv2.convertScaleAbs(prev, alpha=gain), dtype=np.uint8), cur
