"""Exposure changes between consecutive images, measured and undone before tracking.

A camera's automatic exposure scales every pixel of a frame by about the same gain. LK
tracking minimises intensity differences, so a gain change between two frames pulls every
track along its intensity gradient (the patch is matched where the brightness agrees) and
fails the forward-backward check on many others.

:func:`exposure_gain` measures the gain at the tracked points: the mean brightness of a square
around each point in the previous frame and around its predicted position in the current one,
from the integral of the image at half size (a square mean hardly changes, and the integral then
fits in the cache). The log-ratios' median is the gain; it is returned only when it is
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


Integral = npt.NDArray[np.int32]
"""The integral of an image at half size, (H // 2 + 1) x (W // 2 + 1) (:func:`integral`)."""


def integral(image: U8) -> Integral:
    """The integral of an 8-bit image halved (2x2 means; int32, exact up to 2^31 / 255 * 4 pixels),
    for :func:`exposure_gain`."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    if h == 0 or w == 0:  # a line of pixels: nothing to measure (every square reads as empty)
        return np.zeros((h + 1, w + 1), np.int32)
    half = cv2.resize(image[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)
    return np.asarray(cv2.integral(half), dtype=np.int32)


@njit(cache=True)
def _box_mean(integ: Any, x_px: float, y_px: float, half: int) -> float:
    """The mean brightness of the square of half-side ``half`` (half-size pixels) around the
    full-size pixel (x_px, y_px), cut at the borders, from the half-size image's integral."""
    h, w = integ.shape[0] - 1, integ.shape[1] - 1
    x, y = int(x_px * 0.5), int(y_px * 0.5)
    x0, x1 = min(max(x - half, 0), w), min(max(x + half + 1, 0), w)
    y0, y1 = min(max(y - half, 0), h), min(max(y + half + 1, 0), h)
    n = int((x1 - x0) * (y1 - y0))
    if n <= 0:
        return 0.0
    total = float(integ[y1, x1]) - float(integ[y0, x1]) - float(integ[y1, x0]) + float(integ[y0, x0])
    return total / n


@njit(cache=True)
def _log_ratios(prev: Any, cur: Any, px_prev: Any, px_cur: Any, cell_px: int) -> Any:
    """log(mean around ``px_cur`` in ``cur`` / mean around ``px_prev`` in ``prev``) over the points
    whose squares (``cell_px`` full-size pixels) are neither near black nor saturated in either."""
    half = max(cell_px // 4, 1)
    out = np.empty(px_prev.shape[0])
    n = 0
    for i in range(px_prev.shape[0]):
        a = _box_mean(prev, px_prev[i, 0], px_prev[i, 1], half)
        b = _box_mean(cur, px_cur[i, 0], px_cur[i, 1], half)
        if _DARK < a < _BRIGHT and _DARK < b < _BRIGHT:
            out[n] = math.log(b / a)
            n += 1
    return out[:n]


@njit(cache=True)
def _median_and_mad(x: Any) -> tuple[float, float]:
    """The median of ``x`` and the median absolute deviation from it."""
    med = np.median(x)
    return med, np.median(np.abs(x - med))


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
    log_ratio = _log_ratios(prev, cur, px_prev, px_cur, int(cell_px))
    n = len(log_ratio)
    if n < _MIN_POINTS:
        return 1.0
    med, mad = _median_and_mad(log_ratio)
    se = _SE_OF_MEDIAN * mad / math.sqrt(n)
    return math.exp(med) if abs(med) > z_min * se else 1.0


def match_exposure(prev: U8, cur: U8, gain: float) -> tuple[U8, U8]:
    """``prev`` and ``cur`` brought to one exposure (``cur ~ gain * prev``): the brighter one scaled
    down, so nothing saturates. Returns the inputs themselves when ``gain`` is 1."""
    if gain == 1.0:
        return prev, cur
    if gain > 1.0:
        return prev, np.asarray(cv2.convertScaleAbs(cur, alpha=1.0 / gain), dtype=np.uint8)
    return np.asarray(cv2.convertScaleAbs(prev, alpha=gain), dtype=np.uint8), cur
